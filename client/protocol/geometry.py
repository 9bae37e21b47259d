"""Geometry a client needs without the server package: grid rest pose and triangles, Wavefront
OBJ parsing (PROTOCOL.md section 4). drape.server.sim.fabric uses these same functions (it keeps
the float64 positions; the wire and the device get them rounded to float32)."""

from __future__ import annotations

from collections.abc import Iterable

import numpy as np

from .vocabulary import ORIENTATIONS


def grid_positions(
    cols: int,
    rows: int,
    width: float = 1.0,
    height: float = 1.0,
    orientation: str = "horizontal",
    origin: Iterable[float] = (0.0, 0.0, 0.0),
) -> tuple[np.ndarray, np.ndarray]:
    """Rest positions (rows*cols, 3) float64 and triangles (m, 3) int64 of a grid cloth, the
    server's own evaluation (see grid_geometry for the rules)."""
    if cols < 1 or rows < 1:
        raise ValueError("a grid needs at least one column and one row")
    if orientation not in ORIENTATIONS:
        raise ValueError(f"orientation must be one of {list(ORIENTATIONS)}, got {orientation!r}")
    ox, oy, oz = (float(v) for v in origin)
    u = np.linspace(0.0, float(width), cols) if cols > 1 else np.zeros(1)
    w = np.linspace(0.0, float(height), rows) if rows > 1 else np.zeros(1)
    cc, rr = np.meshgrid(u, w)
    verts = np.zeros((rows * cols, 3))
    verts[:, 0] = ox + cc.ravel()
    if orientation == "horizontal":
        verts[:, 1] = oy
        verts[:, 2] = oz + rr.ravel()
    else:
        verts[:, 1] = oy - rr.ravel()
        verts[:, 2] = oz
    r, c = np.meshgrid(np.arange(rows - 1), np.arange(cols - 1), indexing="ij")
    a = (r * cols + c).ravel().astype(np.int64)
    b, d, e = a + 1, a + cols, a + cols + 1
    tris = np.concatenate([np.stack([a, d, b], 1), np.stack([b, d, e], 1)]).reshape(-1, 3)
    return verts, tris


def grid_geometry(
    cols: int,
    rows: int,
    width: float = 1.0,
    height: float = 1.0,
    orientation: str = "horizontal",
    origin: Iterable[float] = (0.0, 0.0, 0.0),
) -> tuple[np.ndarray, np.ndarray]:
    """Rest positions (rows*cols, 3) float32 and triangles (m, 3) uint32 of a grid cloth, exactly
    as the server builds them (drape.server.sim.fabric.grid_mesh is grid_positions).

    Vertex (r, c) = r * cols + c. Evaluated in float64, then rounded to float32:
    u_c = c * width / (cols - 1) (numpy.linspace: the last column is exactly ``width``; 0 when
    cols == 1), likewise v_r = r * height / (rows - 1) (0 when rows == 1); x = origin.x + u_c;
    horizontal: y = origin.y, z = origin.z + v_r; vertical: y = origin.y - v_r, z = origin.z.
    Triangles: for every cell (r, c) in row-major order, a = r*cols + c, b = a + 1, d = a + cols,
    e = d + 1: first all (a, d, b), then all (b, d, e); none when cols == 1 or rows == 1."""
    v, t = grid_positions(cols, rows, width, height, orientation, origin)
    return v.astype(np.float32), t.astype(np.uint32)


def parse_obj_exact(text: str) -> tuple[np.ndarray, np.ndarray]:
    """Vertices (n, 3) float64 and triangles (m, 3) int64 of Wavefront OBJ text.

    ``v x y z [w]`` lines are vertices, ``f`` lines faces of three or more vertex references,
    fan-triangulated ((i0, i1, i2), (i0, i2, i3), ...); a reference is ``i``, ``i/t``, ``i//n`` or
    ``i/t/n`` with ``i`` 1-based, or negative (-1 = the last vertex defined so far). Every other
    line (vt, vn, o, g, s, usemtl, comments) is ignored. A reference that is 0 or outside the
    vertices (at the end of the file for positive ones, at that line for negative ones) is a
    ValueError naming the line, as is a malformed number."""
    verts: list[tuple[float, float, float]] = []
    tris: list[tuple[int, int, int]] = []
    faces: list[tuple[int, list[int]]] = []  # (line number, resolved 0-based indices)
    for lineno, line in enumerate(text.splitlines(), 1):
        parts = line.split("#", 1)[0].split()
        if not parts:
            continue
        try:
            if parts[0] == "v":
                if len(parts) < 4:
                    raise ValueError("vertex needs x y z")
                verts.append((float(parts[1]), float(parts[2]), float(parts[3])))
            elif parts[0] == "f":
                idx = []
                for p in parts[1:]:
                    i = int(p.split("/")[0])
                    if i == 0:
                        raise ValueError("vertex index 0 (OBJ indices start at 1)")
                    if i < 0 and -i > len(verts):
                        raise ValueError(f"vertex index {i} refers before the first vertex")
                    idx.append(i - 1 if i > 0 else len(verts) + i)
                if len(idx) < 3:
                    raise ValueError("face needs three vertices")
                faces.append((lineno, idx))
        except ValueError as e:
            raise ValueError(f"OBJ line {lineno}: {e}") from None
    n = len(verts)
    for lineno, idx in faces:
        if max(idx) >= n:
            raise ValueError(f"OBJ line {lineno}: vertex index {max(idx) + 1} but the file has {n} vertices")
        for k in range(1, len(idx) - 1):
            tris.append((idx[0], idx[k], idx[k + 1]))
    return np.asarray(verts, np.float64).reshape(-1, 3), np.asarray(tris, np.int64).reshape(-1, 3)


def parse_obj(text: str) -> tuple[np.ndarray, np.ndarray]:
    """parse_obj_exact's mesh as the wire carries it: vertices float32, triangles uint32."""
    v, t = parse_obj_exact(text)
    return v.astype(np.float32), t.astype(np.uint32)
