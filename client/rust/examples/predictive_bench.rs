//! Decode cost of predictive states (protocol 1.5) in ns per vertex: a recorded stream of states
//! (`python -m drape.server.tools.codecbench --stream FILE` writes one: the cape motion's 240
//! states, each prefixed by its u32 length) decoded from its keyframe on, 64 times, into reused
//! buffers; the median of 15 rounds. Then the client's path for the same states (what a cloth
//! of `drape::client` does per state): the header checked (`parse_state`), the state decoded on
//! delivery into the float32 state kept (`decode_to_float32`, one allocation) and read into the
//! game's buffer (`decode_state_into`).
//!     cargo run --release --no-default-features --example predictive_bench -- FILE
use drape::wire::PredictiveStream;
use std::hint::black_box;
use std::time::Instant;

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
    let mut rounds = Vec::new();
    for _ in 0..15 {
        let t = Instant::now();
        for _ in 0..64 {
            let mut s = PredictiveStream::new();
            for st in &states {
                black_box(s.decode(st, &mut pos, None).unwrap().expect("in order"));
            }
        }
        rounds.push(t.elapsed().as_nanos() as f64 / (64 * states.len() * n) as f64);
    }
    rounds.sort_by(|a, b| a.partial_cmp(b).unwrap());
    println!(
        "{} states of {} vertices, 64 streams: {:.2} ns per vertex (median of 15)",
        states.len(),
        n,
        rounds[7]
    );
    let mut client = Vec::new();
    for _ in 0..15 {
        let t = Instant::now();
        for _ in 0..64 {
            let mut s = PredictiveStream::new();
            for st in &states {
                black_box(drape::wire::parse_state(st).unwrap());
                let (kept, _) = s.decode_to_float32(st).unwrap().expect("in order");
                black_box(drape::wire::decode_state_into(&kept, &mut pos, None).unwrap());
            }
        }
        client.push(t.elapsed().as_nanos() as f64 / (64 * states.len() * n) as f64);
    }
    client.sort_by(|a, b| a.partial_cmp(b).unwrap());
    println!(
        "client path (header check, decode on delivery into the float32 state kept, read into \
         the caller's buffer): {:.2} ns per vertex (median of 15)",
        client[7]
    );
}
