//! Timing helpers shared by the benchmark examples (`decode_bench`, `moves_bench`).
use std::time::Instant;

/// Median over `rounds` of the mean time of `iters` calls, in ns.
pub fn median_ns(rounds: usize, iters: usize, mut f: impl FnMut()) -> f64 {
    let mut t: Vec<f64> = (0..rounds)
        .map(|_| {
            let t0 = Instant::now();
            for _ in 0..iters {
                f();
            }
            t0.elapsed().as_nanos() as f64 / iters as f64
        })
        .collect();
    t.sort_by(|a, b| a.partial_cmp(b).unwrap());
    t[rounds / 2]
}

/// The machine in words, for the printed figures: CPU model, core count, load average.
pub fn machine() -> String {
    let cpu = std::fs::read_to_string("/proc/cpuinfo").unwrap_or_default();
    let model = cpu.lines().find(|l| l.starts_with("model name")).and_then(|l| l.split(':').nth(1)).unwrap_or("?").trim().to_string();
    let cores = std::thread::available_parallelism().map_or(0, |n| n.get());
    let load = std::fs::read_to_string("/proc/loadavg").unwrap_or_default();
    format!("{model}, {cores} cores, load average {}", load.split_whitespace().take(3).collect::<Vec<_>>().join(" "))
}
