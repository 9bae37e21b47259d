//! What a game loop's per-tick pin moves cost the client to build and encode, and their size on
//! the wire, as protocol 1.1 batch items (one item per cloth, requests of `MAX_BATCH_ITEMS`)
//! against one 1.4 `moves` block (PROTOCOL.md 5.1.1), in the same process: `n` cloths moving
//! their 2 pins. Client side only (no server: what the block saves the server is measured by
//! the server's own benchmarks). Prints a markdown table of medians and the machine.
//!     cargo run --release --no-default-features --example moves_bench
#[path = "bench/mod.rs"]
mod bench;
use drape::wire::{Control, ControlBatch, Moves, Pins, MAX_BATCH_ITEMS};
use std::hint::black_box;

fn main() {
    let k = 2usize;
    let indices = [0u32, 7];
    println!("machine: {}\n", bench::machine());
    println!("| cloths | items: requests | items: bytes | items: µs per tick | moves: requests | moves: bytes | moves: µs per tick | bytes ratio | time ratio |");
    println!("| ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: |");
    for n in [16usize, 64, 256, 1024] {
        let ids: Vec<String> = (0..n).map(|j| format!("{:016x}", 0x5ba8_8a14_c526_242fu64 ^ j as u64)).collect();
        let tokens: Vec<String> = (0..n).map(|j| format!("{:032x}", 0x0123_4567_89ab_cdef_0123_4567_89ab_cdefu128 ^ j as u128)).collect();
        let targets: Vec<f32> = (0..3 * k * n).map(|i| (i % 97) as f32 * 0.01).collect();
        // what send_batch does per tick: one Control per cloth, requests of MAX_BATCH_ITEMS
        let items = || -> Vec<Vec<u8>> {
            let controls: Vec<Control> = (0..n)
                .map(|j| Control {
                    pins: Some(Pins { indices: indices.to_vec(), targets: targets[3 * k * j..3 * k * (j + 1)].to_vec() }),
                    ..Control::new(&ids[j], &tokens[j])
                })
                .collect();
            controls.chunks(MAX_BATCH_ITEMS).map(|c| ControlBatch { rid: 7, client: "game-7".into(), items: c.to_vec() }.encode()).collect()
        };
        // what move_pins_many does per tick: one block (n <= MAX_BATCH_MOVES)
        let block = || -> Vec<u8> {
            let mv = Moves { cloths: ids.clone(), tokens: tokens.clone(), indices: indices.to_vec(), targets: targets.clone() };
            ControlBatch { rid: 7, client: "game-7".into(), items: Vec::new() }.encode_with_moves(Some(&mv))
        };
        let (reqs, blk) = (items(), block());
        let item_bytes: usize = reqs.iter().map(Vec::len).sum();
        let iters = (20_000 / n).max(5);
        let t_items = bench::median_ns(31, iters, || { black_box(items()); }) / 1e3;
        let t_block = bench::median_ns(31, iters, || { black_box(block()); }) / 1e3;
        println!("| {n} | {} | {item_bytes} | {t_items:.1} | 1 | {} | {t_block:.1} | {:.2} | {:.2} |",
                 reqs.len(), blk.len(), blk.len() as f64 / item_bytes as f64, t_block / t_items);
    }
}
