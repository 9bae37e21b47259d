//! Geometry a client needs without asking the server: grid rest positions and triangles
//! (PROTOCOL.md section 4, bit-identical to the reference) and Wavefront OBJ parsing.
use super::error::{invalid, Result};
use super::msg::Orientation;

/// Rest positions (`3 * rows * cols` floats) and triangles (`3 * m` indices) of a grid, exactly
/// as the server builds them: vertex (r, c) = r * cols + c; coordinates computed in float64.
pub fn grid_geometry(
    cols: u32,
    rows: u32,
    width: f64,
    height: f64,
    orientation: Orientation,
    origin: [f64; 3],
) -> Result<(Vec<f32>, Vec<u32>)> {
    if cols < 1 || rows < 1 {
        return Err(invalid("a grid needs at least one column and one row"));
    }
    // numpy.linspace(0, extent, k): i * (extent / (k - 1)), the last one exactly extent.
    let lin = |i: u32, k: u32, extent: f64| -> f64 {
        if k < 2 {
            0.0
        } else if i == k - 1 {
            extent
        } else {
            i as f64 * (extent / (k - 1) as f64)
        }
    };
    let mut verts = Vec::with_capacity(3 * (rows * cols) as usize);
    for r in 0..rows {
        let w = lin(r, rows, height);
        for c in 0..cols {
            let x = origin[0] + lin(c, cols, width);
            let (y, z) = match orientation {
                Orientation::Horizontal => (origin[1], origin[2] + w),
                Orientation::Vertical => (origin[1] - w, origin[2]),
            };
            verts.extend_from_slice(&[x as f32, y as f32, z as f32]);
        }
    }
    let cells = ((rows - 1) * (cols - 1)) as usize;
    let mut tris = Vec::with_capacity(6 * cells);
    for second in [false, true] {
        for r in 0..rows.saturating_sub(1) {
            for c in 0..cols.saturating_sub(1) {
                let a = r * cols + c;
                let (b, d) = (a + 1, a + cols);
                let e = d + 1;
                tris.extend_from_slice(&if second { [b, d, e] } else { [a, d, b] });
            }
        }
    }
    Ok((verts, tris))
}

/// Vertices (`3n` floats) and triangles (`3m` indices) of Wavefront OBJ text: faces
/// fan-triangulated, `v/vt/vn` and negative indices accepted, everything else ignored (the
/// reference's rules). Errors name the line.
pub fn parse_obj(text: &str) -> Result<(Vec<f32>, Vec<u32>)> {
    let mut verts: Vec<f32> = Vec::new();
    let mut tris: Vec<u32> = Vec::new();
    let mut idx: Vec<i64> = Vec::new();
    for (lineno, line) in text.lines().enumerate() {
        let lineno = lineno + 1;
        let line = line.split('#').next().unwrap_or("");
        let mut parts = line.split_whitespace();
        match parts.next() {
            Some("v") => {
                let xyz: Vec<&str> = parts.take(3).collect();
                if xyz.len() < 3 {
                    return Err(invalid(format!("OBJ line {lineno}: vertex needs x y z")));
                }
                for p in xyz {
                    let v: f64 = p.parse().map_err(|_| invalid(format!("OBJ line {lineno}: {p:?} is not a number")))?;
                    verts.push(v as f32);
                }
            }
            Some("f") => {
                idx.clear();
                let n = (verts.len() / 3) as i64;
                for p in parts {
                    let first = p.split('/').next().unwrap_or("");
                    let i: i64 =
                        first.parse().map_err(|_| invalid(format!("OBJ line {lineno}: {p:?} is not a vertex index")))?;
                    idx.push(if i > 0 { i - 1 } else { n + i });
                }
                if idx.len() < 3 {
                    return Err(invalid(format!("OBJ line {lineno}: face needs three vertices")));
                }
                if idx.iter().any(|&i| i < 0 || i >= n) {
                    return Err(invalid(format!("OBJ line {lineno}: vertex index out of range")));
                }
                for k in 1..idx.len() - 1 {
                    tris.extend_from_slice(&[idx[0] as u32, idx[k] as u32, idx[k + 1] as u32]);
                }
            }
            _ => {}
        }
    }
    Ok((verts, tris))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn grid_2x2_horizontal() {
        let (v, t) = grid_geometry(2, 2, 1.0, 2.0, Orientation::Horizontal, [0.0, 1.0, 0.0]).unwrap();
        assert_eq!(v, vec![0.0, 1.0, 0.0, 1.0, 1.0, 0.0, 0.0, 1.0, 2.0, 1.0, 1.0, 2.0]);
        assert_eq!(t, vec![0, 2, 1, 1, 2, 3]);
    }

    #[test]
    fn obj_quad_with_slashes_and_negative_indices() {
        let (v, t) = parse_obj("# quad\nv 0 0 0\nv 1 0 0\nv 1 0 1\nv 0 0 1\nvt 0 0\nf 1/1 2/1/1 3//1 -1\n").unwrap();
        assert_eq!(v.len(), 12);
        assert_eq!(t, vec![0, 1, 2, 0, 2, 3]);
        assert!(parse_obj("v 0 0\n").unwrap_err().message.contains("line 1"));
        assert!(parse_obj("v 0 0 0\nf 1 2 3\n").is_err());
    }
}
