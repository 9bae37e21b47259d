//! The C ABI's parity additions against a real `drape serve` (issue 25): opening with nothing
//! listening, asynchronous submissions with colliders, wind and a material, every control field
//! through `DrapeControl` (waited for and asynchronous, with their events), state queues and
//! counters, the latest-state read, server info and stats, id getters refusing short buffers, and
//! a refused unwaited move naming its cloth. Every assertion counts events or checks positions;
//! none depends on machine speed (waits are bounded by generous deadlines only).
mod common;
use drape::ffi::*;
use std::ffi::{c_char, CStr, CString};
use std::time::{Duration, Instant};

fn last_error() -> String {
    let mut buf = [0 as c_char; 512];
    unsafe { drape_last_error(buf.as_mut_ptr(), buf.len()) };
    unsafe { CStr::from_ptr(buf.as_ptr()) }.to_string_lossy().into_owned()
}

fn cstr(b: &[c_char]) -> String {
    unsafe { CStr::from_ptr(b.as_ptr()) }.to_string_lossy().into_owned()
}

fn open(endpoint: &str, timeout_ms: u32) -> (i32, *mut DrapeClient) {
    let connect = CString::new(endpoint).unwrap();
    let opts = common::c_client_options(&connect, None, None, timeout_ms, true);
    let mut client = std::ptr::null_mut();
    let rc = unsafe { drape_client_open(&opts, &mut client) };
    (rc, client)
}

/// Poll events until `pred` accepts one (or the deadline): the events seen.
fn events_until(client: *mut DrapeClient, secs: u64, mut pred: impl FnMut(&DrapeEvent) -> bool) -> Vec<DrapeEvent> {
    let t0 = Instant::now();
    let mut seen = Vec::new();
    while t0.elapsed() < Duration::from_secs(secs) {
        let mut ev: DrapeEvent = unsafe { std::mem::zeroed() };
        if unsafe { drape_client_poll_event(client, 100, &mut ev) } == DRAPE_OK {
            let done = pred(&ev);
            seen.push(ev);
            if done {
                break;
            }
        }
    }
    seen
}

fn counters(cloth: *mut DrapeCloth) -> DrapeStateCounters {
    let mut k = DrapeStateCounters::default();
    assert_eq!(unsafe { drape_cloth_counters(cloth, &mut k) }, DRAPE_OK);
    k
}

fn adds_up(k: &DrapeStateCounters) -> bool {
    k.read + k.replaced + k.missed + k.unread == k.ticks && k.received == k.read + k.replaced + k.unread
}

#[test]
fn open_fails_without_a_server() {
    let port = common::free_port(); // nothing listens there
    let t0 = Instant::now();
    let (rc, client) = open(&format!("tcp/127.0.0.1:{port}"), 500);
    assert_eq!(rc, DRAPE_E_UNAVAILABLE, "{}", last_error());
    assert!(client.is_null());
    assert!(t0.elapsed() < Duration::from_secs(30));
    let msg = last_error();
    assert!(msg.contains("no Drape server") && !msg.contains(".rs:"), "{msg}");
    // a malformed endpoint: refused with a message free of the build machine's paths
    let (rc, _) = open("tcp/127.0.0.1:not-a-port", 500);
    assert_ne!(rc, DRAPE_OK);
    let msg = last_error();
    assert!(!msg.contains(".rs:") && !msg.contains(".cargo"), "{msg}");
}

#[test]
fn parity_controls_queues_and_counters() {
    let Some(bin) = common::drape_bin() else { return };
    let server = common::start(&bin, &[]);
    let (rc, client) = open(&server.endpoint, 60_000);
    assert_eq!(rc, DRAPE_OK, "{}", last_error());
    unsafe {
        let mut info: DrapeServerInfo = std::mem::zeroed();
        assert_eq!(drape_client_server_info(client, std::ptr::null(), &mut info), DRAPE_OK, "{}", last_error());
        assert_eq!(cstr(&info.server), server.id);
        assert!(info.tick_rate > 0.0 && info.version_major == 1 && info.max_colliders > 0);

        // an id buffer too small is an error with an empty string, not a silent truncation
        let mut small = [1 as c_char; 4];
        assert_eq!(drape_client_id(client, small.as_mut_ptr(), small.len()), DRAPE_E_INVALID_VALUE);
        assert_eq!(small[0], 0);

        // a horizontal 8x8 cloth at y = 2 over a floor plane at y = 1.5, asynchronously, with a
        // material and wind, keeping 256 states unread
        let wind = [0.5f64, 0.0, 0.0];
        let material = DrapeMaterial { fields: DRAPE_MATERIAL_MASS | DRAPE_MATERIAL_DAMPING, mass: 0.5, stiffness: [0.0; 3],
                                       compliance: [0.0; 3], damping: 0.05, friction: 0.0, drag: 0.0, lift: 0.0,
                                       air_density: 0.0, tether_limit: 0.0 };
        let floor = DrapeCollider { kind: DRAPE_COLLIDER_PLANE, a: [0.0, 1.0, 0.0], b: [0.0; 3], radius: 0.0, offset: 1.5 };
        let opts = DrapeClothOptions { wind: wind.as_ptr(), material: &material, colliders: &floor, collider_count: 1,
                                       features: DRAPE_FEATURE_COLLIDERS | DRAPE_FEATURE_WIND, queue_size: 256,
                                       ..Default::default() };
        let grid = DrapeGrid { cols: 8, rows: 8, width: 1.0, height: 1.0, vertical: false, origin: [0.0, 2.0, 0.0] };
        let mut cloth = std::ptr::null_mut();
        assert_eq!(drape_submit_grid_async(client, &grid, &opts, &mut cloth), DRAPE_OK, "{}", last_error());
        let handle = drape_cloth_handle(cloth);
        let seen = events_until(client, 60, |e| e.kind == DRAPE_EVENT_SUBMITTED || e.kind == DRAPE_EVENT_SUBMIT_FAILED);
        let ev = seen.last().expect("no submit event");
        assert_eq!((ev.kind, ev.handle), (DRAPE_EVENT_SUBMITTED, handle), "{}", cstr(&ev.message));
        assert_eq!(drape_cloth_status(cloth), DRAPE_CLOTH_LIVE);
        let mut id = [0 as c_char; DRAPE_ID_MAX];
        assert_eq!(drape_cloth_id(cloth, id.as_mut_ptr(), id.len()), DRAPE_OK);
        assert_eq!(cstr(&ev.cloth), cstr(&id));

        // nothing read for a while: every state waits in the queue (none replaced)
        let t0 = Instant::now();
        while counters(cloth).received < 90 && t0.elapsed() < Duration::from_secs(60) {
            std::thread::sleep(Duration::from_millis(50));
        }
        let k = counters(cloth);
        assert!(k.received >= 90 && k.replaced == 0 && k.unread == k.received && adds_up(&k), "{k:?}");
        let n = 3 * 64;
        let mut pos = vec![0f32; n];
        let mut st: DrapeStateInfo = std::mem::zeroed();
        // a buffer counted in vertices, not floats, is refused before anything is taken
        assert_eq!(drape_cloth_read_state(cloth, pos.as_mut_ptr(), 64, std::ptr::null_mut(), 0, &mut st), DRAPE_E_INVALID_VALUE);
        let (mut read, mut last) = (0u64, 0u64);
        loop {
            if drape_cloth_read_state(cloth, pos.as_mut_ptr(), n, std::ptr::null_mut(), 0, &mut st) == DRAPE_OK {
                assert!(st.tick > last, "oldest first: {} after {last}", st.tick);
                last = st.tick;
                read += 1;
            } else if counters(cloth).unread == 0 {
                break; // (NO_DATA with states queued: one was being stored at that instant)
            }
        }
        assert!(read >= k.received, "{read} read of {k:?}");
        let k = counters(cloth);
        assert!(adds_up(&k) && k.replaced == 0 && k.read == read, "{k:?}");
        // the floor held the cloth above y = 1.5 (it fell from y = 2 for 1.5 s and more)
        let lowest = pos.chunks(3).map(|p| p[1]).fold(f32::MAX, f32::min);
        assert!(lowest > 1.45 && lowest < 1.7, "lowest vertex at y = {lowest}: the floor collider was not applied");

        // the latest state again (read before: not counted again)
        common::c_latest(cloth, &mut pos[..n], &mut st);
        assert!(st.tick >= last);

        // every control field, waited for: the floor removed and the cloth falls below it
        let gravity = [0.0f64, -9.81, 0.0];
        let ctl = DrapeControl { gravity: gravity.as_ptr(), wind: wind.as_ptr(), material: &material, set_colliders: true,
                                 collider_count: 0, features_add: DRAPE_FEATURE_NORMALS, iterations: 8, substeps: 2,
                                 set_state: true, encoding: 1, normals: true, ..Default::default() };
        let (mut tick, mut features) = (0u64, 0u32);
        assert_eq!(drape_cloth_control(cloth, &ctl, &mut tick, &mut features), DRAPE_OK, "{}", last_error());
        assert!(tick > 0 && features & DRAPE_FEATURE_NORMALS != 0 && features != DRAPE_FEATURES_UNKNOWN, "0x{features:x}");
        let t0 = Instant::now();
        let mut normals = vec![0f32; n];
        let mut fell = false;
        while !fell && t0.elapsed() < Duration::from_secs(60) {
            if drape_cloth_read_state(cloth, pos.as_mut_ptr(), n, normals.as_mut_ptr(), n, &mut st) == DRAPE_OK && st.tick > tick {
                assert!(st.has_normals && st.encoding == 1);
                fell = pos.chunks(3).any(|p| p[1] < 1.3);
            } else {
                std::thread::sleep(Duration::from_millis(10));
            }
        }
        assert!(fell, "the cloth did not fall once its colliders were removed");

        // asynchronous: done with its request number; a refused one names its cloth
        let ctl = DrapeControl { features_remove: DRAPE_FEATURE_WIND, ..Default::default() };
        let mut req = 0u64;
        assert_eq!(drape_cloth_control_async(cloth, &ctl, &mut req), DRAPE_OK);
        let bad_idx = [5u32];
        let bad_target = [0f32; 3];
        let bad = DrapeControl { pin_indices: bad_idx.as_ptr(), pin_count: 1, pin_targets: bad_target.as_ptr(), ..Default::default() };
        let mut bad_req = 0u64;
        assert_eq!(drape_cloth_control_async(cloth, &bad, &mut bad_req), DRAPE_OK);
        assert!(req != 0 && bad_req != 0 && req != bad_req);
        let (mut done, mut failed) = (None, None);
        events_until(client, 30, |e| {
            if e.kind == DRAPE_EVENT_REQUEST_DONE && e.request == req {
                done = Some((e.tick, e.features, cstr(&e.cloth)));
            }
            if e.kind == DRAPE_EVENT_REQUEST_FAILED && e.request == bad_req {
                failed = Some((e.code, cstr(&e.cloth)));
            }
            done.is_some() && failed.is_some()
        });
        let (t, f, c) = done.expect("no REQUEST_DONE");
        assert!(t > 0 && f & DRAPE_FEATURE_WIND == 0 && f != DRAPE_FEATURES_UNKNOWN && c == cstr(&id), "{t} 0x{f:x} {c}");
        let (code, c) = failed.expect("no REQUEST_FAILED");
        assert!(code != DRAPE_OK && c == cstr(&id), "{code} {c}");

        // a refused move not waited for (vertex 5 is not pinned) names its cloth too
        let idx = [5u32];
        let cl = [cloth as *const DrapeCloth];
        assert_eq!(drape_move_pins_many(client, cl.as_ptr(), 1, idx.as_ptr(), 1, bad_target.as_ptr(), false,
                                        std::ptr::null_mut(), std::ptr::null_mut()), DRAPE_OK);
        let seen = events_until(client, 30, |e| e.kind == DRAPE_EVENT_REQUEST_FAILED);
        let ev = seen.last().expect("no event");
        assert_eq!((ev.kind, ev.handle, cstr(&ev.cloth)), (DRAPE_EVENT_REQUEST_FAILED, handle, cstr(&id)), "{}", cstr(&ev.message));

        // stats arrive (stats period 0.5 s) and are read without blocking
        let mut stats: DrapeServerStats = std::mem::zeroed();
        let t0 = Instant::now();
        while drape_client_server_stats(client, std::ptr::null(), &mut stats) != DRAPE_OK && t0.elapsed() < Duration::from_secs(30) {
            std::thread::sleep(Duration::from_millis(50));
        }
        assert!(stats.ticks > 0 && stats.cloths >= 1 && cstr(&stats.server) == server.id, "{} {}", stats.ticks, stats.cloths);

        // an asynchronous submission removed before its reply is cancelled (removed if placed)
        let mut pending = std::ptr::null_mut();
        assert_eq!(drape_submit_grid_async(client, &grid, std::ptr::null(), &mut pending), DRAPE_OK);
        assert_eq!(drape_cloth_remove(pending, std::ptr::null_mut()), DRAPE_OK);
        assert_eq!(drape_cloth_status(pending), DRAPE_CLOTH_REMOVED);
        drape_cloth_free(pending);

        let k = counters(cloth);
        assert!(adds_up(&k), "{k:?}");
        assert_eq!(drape_cloth_remove(cloth, std::ptr::null_mut()), DRAPE_OK);
        drape_cloth_free(cloth);
        drape_client_close(client, true);
    }
}
