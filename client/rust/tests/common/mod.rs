//! Starting a real `drape serve` process for the live tests: found through `DRAPE_BIN`
//! (default `../../.venv/bin/drape` from this crate), on a loopback port of its own, stopped
//! when the test process ends (a watchdog shell kills it) or when `kill()` is called; `twin`:
//! states compared with a float32 twin's.
#![allow(dead_code)]
pub mod twin;

use std::io::{BufRead, BufReader};
use std::path::PathBuf;
use std::process::{Command, Stdio};
use std::time::Duration;

pub struct Server {
    pub id: String,
    pub endpoint: String,
    pub pid: u32,
    pub log: PathBuf,
}

/// The drape binary, or None (the test skips) outside CI; in CI (CI=true) a missing binary fails.
pub fn drape_bin() -> Option<PathBuf> {
    let bin = std::env::var_os("DRAPE_BIN").map(PathBuf::from)
        .unwrap_or_else(|| PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../../.venv/bin/drape"));
    if bin.exists() {
        return Some(bin);
    }
    let msg = format!("live tests need the drape server: {} does not exist (set DRAPE_BIN, or create the venv: \
                       python3 -m venv .venv && .venv/bin/pip install -e .)", bin.display());
    if std::env::var("CI").map(|v| v.eq_ignore_ascii_case("true") || v == "1").unwrap_or(false) {
        panic!("{msg}");
    }
    eprintln!("SKIPPED: {msg}");
    None
}

pub fn free_port() -> u16 {
    std::net::TcpListener::bind("127.0.0.1:0").unwrap().local_addr().unwrap().port()
}

/// Start `drape serve` (grace period 1 s) and return once its process is running; clients find
/// it by liveliness (their timeout covers its start-up).
pub fn start(bin: &PathBuf, extra: &[&str]) -> Server {
    let port = free_port();
    let id = format!("rs-{port}");
    let endpoint = format!("tcp/127.0.0.1:{port}");
    let log = std::env::temp_dir().join(format!("drape-live-{port}.log"));
    let script = r#"parent=$1; log=$2; shift 2; "$@" >"$log" 2>&1 & child=$!; echo $child;
        while kill -0 "$parent" 2>/dev/null && kill -0 "$child" 2>/dev/null; do sleep 0.3; done; kill "$child" 2>/dev/null"#;
    let mut cmd = Command::new("sh");
    cmd.arg("-c").arg(script).arg("sh").arg(std::process::id().to_string()).arg(&log).arg(bin)
        .args(["serve", "--listen", &endpoint, "--server-id", &id, "--grace-period", "1", "--stats-period", "0.5"])
        // Admission control (1.2, `overloaded`) measures tick cost; on a shared 2-core machine
        // running every live test at once it refuses tiny cloths at random. The tests of the
        // client's functions run without it; `overloaded_submissions` turns it on deliberately.
        .args(if extra.iter().any(|a| a.starts_with("--admission")) { &[][..] } else { &["--no-admission"][..] })
        .args(extra)
        .stdout(Stdio::piped());
    let mut child = cmd.spawn().expect("cannot start sh for drape serve");
    let mut line = String::new();
    BufReader::new(child.stdout.take().unwrap()).read_line(&mut line).unwrap();
    let pid = line.trim().parse().expect("watchdog did not report the server pid");
    std::thread::spawn(move || child.wait());
    Server { id, endpoint, pid, log }
}

impl Server {
    /// SIGKILL: the server vanishes without removing anything (its liveliness token goes).
    pub fn kill(&self) {
        let _ = Command::new("kill").args(["-9", &self.pid.to_string()]).status();
    }
    pub fn log_text(&self) -> String {
        std::fs::read_to_string(&self.log).unwrap_or_default()
    }
}

impl Drop for Server {
    fn drop(&mut self) {
        let _ = Command::new("kill").arg(self.pid.to_string()).stderr(Stdio::null()).status();
    }
}

pub const START_TIMEOUT: Duration = Duration::from_secs(60);
/// A loaded machine's patience for an event that must come (a state, an applied control, a reply's
/// event): a deadline, never a rate; the tests pass as soon as it comes.
pub const WAIT: Duration = Duration::from_secs(60);

/// A client connected to every server of `servers` (timeout 10 s), returned once it sees each
/// one's liveliness token (a cold server builds its kernels first: up to `START_TIMEOUT`).
pub fn connect(servers: &[&Server], server_id: Option<&str>, failover: bool) -> drape::client::Client {
    let opts = drape::client::ClientOptions {
        connect: servers.iter().map(|s| s.endpoint.clone()).collect(),
        server_id: server_id.map(str::to_string),
        timeout: Duration::from_secs(10),
        failover,
        ..Default::default()
    };
    let client = drape::client::Client::open(opts).expect("open");
    let t0 = std::time::Instant::now();
    for s in servers {
        while !client.servers(Duration::from_millis(500)).unwrap().contains(&s.id) {
            assert!(t0.elapsed() < START_TIMEOUT, "server {} not up; its log:\n{}", s.id, s.log_text());
            std::thread::sleep(Duration::from_millis(200));
        }
    }
    client
}

/// C ABI client options: the endpoints `connect` (comma-separated), the server `server_id`
/// (None: placement by load), the client id `client_id` (None: `$DRAPE_CLIENT_ID` or random), the
/// default namespace, `timeout_ms`, failover off when `no_failover`, not lazy. The strings must
/// outlive the options.
pub fn c_client_options(connect: &std::ffi::CStr, server_id: Option<&std::ffi::CStr>, client_id: Option<&std::ffi::CStr>,
                        timeout_ms: u32, no_failover: bool) -> drape::ffi::DrapeClientOptions {
    let ptr = |s: Option<&std::ffi::CStr>| s.map_or(std::ptr::null(), |s| s.as_ptr());
    drape::ffi::DrapeClientOptions {
        connect: connect.as_ptr(),
        server_id: ptr(server_id),
        client_id: ptr(client_id),
        namespace_: std::ptr::null(),
        timeout_ms,
        no_failover,
        lazy: false,
    }
}

/// A C ABI client of `server` (`drape_client_open`, asserted to succeed): its endpoint and id,
/// the client id `client_id` (None: `$DRAPE_CLIENT_ID` or random), a 60 s timeout, failover off,
/// not lazy. The caller closes it (`drape_client_close`).
pub fn c_open(server: &Server, client_id: Option<&str>) -> *mut drape::ffi::DrapeClient {
    let connect = std::ffi::CString::new(server.endpoint.clone()).unwrap();
    let id = std::ffi::CString::new(server.id.clone()).unwrap();
    let me = client_id.map(|c| std::ffi::CString::new(c).unwrap());
    let opts = c_client_options(&connect, Some(&id), me.as_deref(), 60_000, true);
    let mut client = std::ptr::null_mut();
    assert_eq!(unsafe { drape::ffi::drape_client_open(&opts, &mut client) }, drape::ffi::DRAPE_OK);
    client
}

/// Polls `drape_cloth_read_state` (positions only, into `pos`) until the C ABI cloth's first state,
/// failing the test after `within`.
///
/// # Safety
/// `cloth` is a live cloth of the C ABI.
pub unsafe fn c_first_state(cloth: *const drape::ffi::DrapeCloth, pos: &mut [f32], within: Duration) {
    let t0 = std::time::Instant::now();
    let mut got = drape::ffi::DRAPE_NO_DATA;
    while got == drape::ffi::DRAPE_NO_DATA && t0.elapsed() < within {
        std::thread::sleep(Duration::from_millis(20));
        got = drape::ffi::drape_cloth_read_state(cloth, pos.as_mut_ptr(), pos.len(), std::ptr::null_mut(), 0, std::ptr::null_mut());
    }
    assert_eq!(got, drape::ffi::DRAPE_OK, "no state within {within:?}");
}

/// The newest state received (`Cloth::latest_state`), for a cloth that has received one: the
/// call never blocks, so it returns None while a Zenoh thread is delivering a state at that very
/// instant (a preempted delivery holds the slot for as long as it is off the CPU); tried again
/// until it answers, failing the test after `WAIT`.
pub fn latest(cloth: &drape::client::Cloth, pos: &mut [f32]) -> drape::client::StateInfo {
    let t0 = std::time::Instant::now();
    loop {
        if let Some(st) = cloth.latest_state(pos, None).unwrap() {
            return st;
        }
        assert!(t0.elapsed() < WAIT, "no latest state within {WAIT:?}");
        std::thread::yield_now();
    }
}

/// `latest` through the C ABI (`drape_cloth_read_latest`): DRAPE_NO_DATA while a state is being
/// delivered at that instant, tried again; any other answer than DRAPE_OK fails the test.
///
/// # Safety
/// `cloth` is a live cloth of the C ABI that has received a state.
pub unsafe fn c_latest(cloth: *const drape::ffi::DrapeCloth, pos: &mut [f32], info: *mut drape::ffi::DrapeStateInfo) {
    let t0 = std::time::Instant::now();
    loop {
        let rc = drape::ffi::drape_cloth_read_latest(cloth, pos.as_mut_ptr(), pos.len(), std::ptr::null_mut(), 0, info);
        if rc == drape::ffi::DRAPE_OK {
            return;
        }
        assert_eq!(rc, drape::ffi::DRAPE_NO_DATA, "drape_cloth_read_latest");
        assert!(t0.elapsed() < WAIT, "no latest state within {WAIT:?}");
        std::thread::yield_now();
    }
}

/// C ABI submission options pinning `pins`: float32, no bundle, server defaults for the rest.
pub fn c_cloth_options(pins: &[u32], normals: bool) -> drape::ffi::DrapeClothOptions {
    drape::ffi::DrapeClothOptions {
        pinned: pins.as_ptr(),
        pinned_count: pins.len(),
        encoding: 0,
        normals,
        bundle: false,
        quality: std::ptr::null(),
        gravity: std::ptr::null(),
        ..Default::default()
    }
}

/// Moves pins 0 and 7 of an 8 x 4 grid cloth, waiting for the reply, then reads states with
/// `wait` until the one of the tick the reply named, where the pinned vertices are at their targets.
/// Returns that tick.
pub fn pins_follow(
    cloth: &drape::client::Cloth,
    pos: &mut [f32],
    wait: impl Fn(&drape::client::Cloth, &mut [f32]) -> drape::client::StateInfo,
) -> u64 {
    let targets = [0.1f32, 2.5, 0.2, 1.5, 2.5, 0.2];
    let tick = cloth.move_pins(&[0, 7], &targets, true).unwrap().unwrap();
    loop {
        let st = wait(cloth, pos);
        if st.tick >= tick {
            assert_eq!((&pos[0..3], &pos[21..24]), (&targets[0..3], &targets[3..6]));
            return tick;
        }
    }
}
