//! A small game loop in Rust: submit a 16x12 cape pinned at its two top corners, move the
//! pins along a circle every frame (controls not waited for), read each new state into one
//! reused buffer and print what arrives. Usage:
//!     cargo run --example cape -- [ENDPOINT] [FRAMES]      (default tcp/127.0.0.1:7447, 120)
use drape::client::{Client, ClientOptions, Event};
use drape::wire::{Grid, Orientation, Shape, Submit};
use std::time::{Duration, Instant};

fn main() -> Result<(), Box<dyn std::error::Error>> {
    let args: Vec<String> = std::env::args().collect();
    let endpoint = args.get(1).cloned().unwrap_or_else(|| "tcp/127.0.0.1:7447".into());
    let frames: u32 = args.get(2).map_or(Ok(120), |s| s.parse())?;
    let client = Client::open(ClientOptions { connect: vec![endpoint], timeout: Duration::from_secs(30), ..Default::default() })?;
    println!("client {} using server {}", client.client_id(), client.server_id()?);
    let (cols, rows) = (16u32, 12u32);
    let grid = Grid { cols, rows, width: 0.8, height: 1.0, orientation: Orientation::Vertical, origin: [-0.4, 1.8, 0.0] };
    let pins = [0, cols - 1];
    let cape = client.submit_grid(grid, Submit { pinned: pins.to_vec(), ..Submit::new("", Shape::Grid(Grid::new(1, 1))) })?;
    println!("cape {} ({} vertices) from tick {}", cape.id(), cape.vertex_count(), cape.first_tick());
    let mut positions = vec![0f32; 3 * cape.vertex_count() as usize];
    let (mut received, t0) = (0u32, Instant::now());
    for frame in 0..frames {
        let a = frame as f32 * 0.05;
        let (dx, dz) = (0.3 * a.cos(), 0.3 * a.sin());
        let targets = [-0.4 + dx, 1.8, dz, 0.4 + dx, 1.8, dz];
        cape.move_pins(&pins, &targets, false)?;
        if let Some(st) = cape.wait_state(&mut positions, None, Duration::from_millis(100))? {
            received += 1;
            let hem = &positions[3 * ((rows - 1) * cols + cols / 2) as usize..][..3];
            if frame % 20 == 0 {
                println!("frame {frame:3}: tick {} hem at ({:+.3}, {:+.3}, {:+.3}) latency {:.1} ms", st.tick, hem[0], hem[1], hem[2],
                         (st.receive_time_ns.saturating_sub(st.server_time_ns)) as f64 / 1e6);
            }
        }
        while let Some(ev) = client.poll_event(Duration::ZERO) {
            if !matches!(ev, Event::ServerFound { .. }) {
                println!("event: {ev:?}");
            }
        }
    }
    let (got, dropped, invalid) = cape.counters();
    println!("{frames} frames in {:.2} s: {received} states read ({got} received, {dropped} replaced unread, {invalid} invalid)",
             t0.elapsed().as_secs_f64());
    println!("removed; last tick {}", cape.remove()?);
    client.close(true);
    if received == 0 {
        return Err("no state received".into());
    }
    Ok(())
}
