//! Decode cost per state and per bundle, in ns per vertex, of this crate and of the Python
//! SDK on the same payloads. Writes the payloads to target/bench-payloads/, times the Rust
//! decoders (into reused caller buffers), runs examples/decode_bench.py on the same files with
//! $DRAPE_PYTHON (default ../../.venv/bin/python) and prints a markdown table of medians.
//!     cargo run --release --no-default-features --example decode_bench
use drape::wire::{decode_state_into, encode_bundle, encode_state, parse_bundle, Encoding};
use std::hint::black_box;
use std::path::PathBuf;
#[path = "bench/mod.rs"]
mod bench;
use bench::median_ns;

fn grid(cols: usize, rows: usize, phase: f32) -> Vec<f32> {
    (0..rows * cols)
        .flat_map(|i| {
            let (r, c) = ((i / cols) as f32, (i % cols) as f32);
            [c / cols as f32, 2.0 - r / rows as f32 + 0.01 * (c + phase).sin(), 0.05 * (r * 0.3 + phase).cos()]
        })
        .collect()
}

fn normals(n: usize) -> Vec<f32> {
    (0..n).flat_map(|i| { let a = i as f32 * 0.01; [a.sin() * 0.6, 0.0, a.cos() * 0.8] }).collect()
}

fn main() {
    let dir = PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("target/bench-payloads");
    std::fs::create_dir_all(&dir).unwrap();
    let mut cases: Vec<(String, Vec<u8>, usize, bool)> = Vec::new(); // name, payload, vertices, bundle
    for (enc, nrm) in [(Encoding::Float32, false), (Encoding::Float16, false), (Encoding::Quant16, false), (Encoding::Quant16, true)] {
        let pos = grid(64, 64, 0.0);
        let n = normals(4096);
        let st = encode_state(1042, 1, &pos, nrm.then_some(&n[..]), enc, 0).unwrap();
        cases.push((format!("state_64x64_{}{}", enc.name(), if nrm { "_normals" } else { "" }), st, 4096, false));
    }
    for (enc, cloths) in [(Encoding::Float32, 16), (Encoding::Quant16, 16), (Encoding::Quant16, 64)] {
        let states: Vec<(String, Vec<u8>)> = (0..cloths)
            .map(|k| (format!("{:016x}", 0x5ba8_8a14_c526_2420u64 + k), encode_state(7, 42, &grid(32, 32, k as f32), None, enc, 0).unwrap()))
            .collect();
        let refs: Vec<(&str, &[u8])> = states.iter().map(|(c, s)| (c.as_str(), s.as_slice())).collect();
        cases.push((format!("bundle_{cloths}x32x32_{}", enc.name()), encode_bundle(7, 42, &refs, 0).unwrap(), cloths as usize * 1024, true));
    }
    let mut pos = vec![0f32; 3 * 4096];
    let mut nrm = vec![0f32; 3 * 4096];
    let mut rows = Vec::new();
    for (name, data, verts, bundle) in &cases {
        std::fs::write(dir.join(format!("{name}.bin")), data).unwrap();
        let iters = (2_000_000 / verts).max(10);
        let ns = if *bundle {
            median_ns(31, iters, || {
                let b = parse_bundle(black_box(data)).unwrap();
                for i in 0..b.entries.len() {
                    black_box(b.decode_into(i, &mut pos, Some(&mut nrm)).unwrap());
                }
            })
        } else {
            median_ns(31, iters, || {
                black_box(decode_state_into(black_box(data), &mut pos, Some(&mut nrm)).unwrap());
            })
        };
        rows.push((name.clone(), *verts, data.len(), ns));
    }
    let python = std::env::var("DRAPE_PYTHON")
        .unwrap_or_else(|_| format!("{}/../../.venv/bin/python", env!("CARGO_MANIFEST_DIR")));
    let script = PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("examples/decode_bench.py");
    let py = std::process::Command::new(&python).arg(&script).arg(&dir).output();
    let mut py_ns = std::collections::HashMap::new();
    match py {
        Ok(out) if out.status.success() => {
            for line in String::from_utf8_lossy(&out.stdout).lines() {
                let f: Vec<&str> = line.split_whitespace().collect();
                if f.len() == 3 {
                    py_ns.insert(f[0].to_string(), (f[1].parse::<f64>().unwrap(), f[2].parse::<f64>().unwrap()));
                }
            }
        }
        Ok(out) => eprintln!("python bench failed: {}", String::from_utf8_lossy(&out.stderr)),
        Err(e) => eprintln!("cannot run {python}: {e}"),
    }
    println!("machine: {}\n", bench::machine());
    println!("| payload | vertices | bytes | Rust decode into caller buffers, ns/vertex | Python decode, ns/vertex | Python decode + copy into a caller array, ns/vertex |");
    println!("| --- | ---: | ---: | ---: | ---: | ---: |");
    for (name, verts, bytes, ns) in rows {
        let (p, pc) = py_ns.get(&name).map_or(("n/a".into(), "n/a".into()), |(a, b)| (format!("{:.2}", a / verts as f64), format!("{:.2}", b / verts as f64)));
        println!("| {name} | {verts} | {bytes} | {:.2} | {p} | {pc} |", ns / verts as f64);
    }
}
