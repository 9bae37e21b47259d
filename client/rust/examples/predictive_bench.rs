//! Decode cost of predictive states (protocol 1.5) in ns per vertex: a recorded stream of states
//! (`python -m drape.server.tools.codecbench --stream FILE` writes one: the cape motion's 240
//! states, each prefixed by its u32 length) decoded from its keyframe on, 64 times, into reused
//! buffers; the median of 15 rounds. Then the client's path for the same states (what a cloth
//! of `drape::client` does per state): the header checked (`parse_state`), the state decoded on
//! delivery into the float32 state kept (`decode_to_float32`, one allocation) and read into the
//! game's buffer (`decode_state_into`). Each path prints the median and the least of its rounds
//! in wall time and in this thread's CPU time (`/proc/thread-self/schedstat`: the time it ran,
//! what a machine shared with other jobs does not inflate by preemption), and the machine's
//! load average.
//!     cargo run --release --no-default-features --example predictive_bench -- FILE
use drape::wire::PredictiveStream;
use std::hint::black_box;
use std::time::Instant;

/// This thread's CPU time in ns (0 where /proc does not say).
fn cpu_ns() -> u64 {
    std::fs::read_to_string("/proc/thread-self/schedstat")
        .ok()
        .and_then(|s| s.split_whitespace().next().and_then(|x| x.parse().ok()))
        .unwrap_or(0)
}

/// Time `f` 15 times: (wall, CPU) ns per vertex of each round, `per` vertices a round.
fn rounds(per: usize, mut f: impl FnMut()) -> (Vec<f64>, Vec<f64>) {
    let (mut wall, mut cpu) = (Vec::new(), Vec::new());
    for _ in 0..15 {
        let (t, c) = (Instant::now(), cpu_ns());
        f();
        cpu.push((cpu_ns() - c) as f64 / per as f64);
        wall.push(t.elapsed().as_nanos() as f64 / per as f64);
    }
    wall.sort_by(|a, b| a.partial_cmp(b).unwrap());
    cpu.sort_by(|a, b| a.partial_cmp(b).unwrap());
    (wall, cpu)
}

fn report(what: &str, (wall, cpu): (Vec<f64>, Vec<f64>)) {
    println!(
        "{what}: ns per vertex, median / min of 15: wall {:.2} / {:.2}, CPU {:.2} / {:.2}",
        wall[7], wall[0], cpu[7], cpu[0]
    );
}

fn main() {
    let path = std::env::args()
        .nth(1)
        .expect("usage: predictive_bench FILE");
    let data = std::fs::read(&path).unwrap_or_else(|e| panic!("{path}: {e}"));
    let mut states = Vec::new();
    let mut at = 0;
    while at + 4 <= data.len() {
        let n = u32::from_le_bytes(data[at..at + 4].try_into().unwrap()) as usize;
        states.push(&data[at + 4..at + 4 + n]);
        at += 4 + n;
    }
    let n = drape::wire::parse_predictive(states[0])
        .unwrap()
        .vertex_count as usize;
    let mut pos = vec![0f32; 3 * n];
    let per = 64 * states.len() * n;
    println!("{} states of {} vertices, 64 streams", states.len(), n);
    report(
        "decode",
        rounds(per, || {
            for _ in 0..64 {
                let mut s = PredictiveStream::new();
                for st in &states {
                    black_box(s.decode(st, &mut pos, None).unwrap().expect("in order"));
                }
            }
        }),
    );
    report(
        "client path (header check, decode on delivery into the float32 state kept, read into \
         the caller's buffer)",
        rounds(per, || {
            for _ in 0..64 {
                let mut s = PredictiveStream::new();
                for st in &states {
                    black_box(drape::wire::parse_state(st).unwrap());
                    let (kept, _) = s.decode_to_float32(st).unwrap().expect("in order");
                    black_box(drape::wire::decode_state_into(&kept, &mut pos, None).unwrap());
                }
            }
        }),
    );
    let load = std::fs::read_to_string("/proc/loadavg").unwrap_or_default();
    println!("load average: {}", load.split_whitespace().take(3).collect::<Vec<_>>().join(" "));
}
