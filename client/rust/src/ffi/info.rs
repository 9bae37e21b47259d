//! C ABI of server information: `info` (version, tick rate, limits; asked of the server) and
//! the last `stats` publication (PROTOCOL.md section 10; kept as received, never blocks).
use super::{bad, copy_out, fail, fill, guard, opt_str, DrapeClient, DRAPE_NO_DATA, DRAPE_OK};
use crate::wire::reader::Reader;
use crate::wire::Result;
use std::ffi::c_char;

/// A server's `info` reply (PROTOCOL.md section 7); numbers it did not report are 0.
#[repr(C)]
pub struct DrapeServerInfo {
    pub server: [c_char; 72],
    /// Protocol version the server speaks, e.g. 1 and 4.
    pub version_major: u32,
    pub version_minor: u32,
    /// Ticks per second.
    pub tick_rate: f64,
    pub tick: u64,
    pub cloths: u64,
    pub clients: u64,
    pub vertices: u64,
    pub solver: [c_char; 32],
    pub device: [c_char; 128],
    pub max_cloths: u64,
    pub max_cloths_per_client: u64,
    pub max_vertices_per_cloth: u64,
    pub max_total_vertices: u64,
    pub max_message_bytes: u64,
    pub max_pin_updates: u64,
    pub max_batch_items: u64,
    pub max_colliders: u64,
    pub max_iterations: u64,
    pub max_substeps: u64,
    pub grace_period_s: f64,
    pub stats_period_s: f64,
}

/// A server's last stats publication (PROTOCOL.md section 10); fields it did not report are 0.
#[repr(C)]
pub struct DrapeServerStats {
    pub server: [c_char; 72],
    pub tick: u64,
    /// Server wall clock (Unix ns) of the publication.
    pub time_ns: u64,
    pub uptime_s: f64,
    pub tick_rate: f64,
    pub cloths: u64,
    pub clients: u64,
    pub alive_clients: u64,
    pub vertices: u64,
    /// Ticks run; tick deadlines skipped because a tick overran (cumulative).
    pub ticks: u64,
    pub missed_ticks: u64,
    /// Frames the publisher coalesced (cumulative).
    pub skipped_frames: u64,
    pub published: u64,
    pub unwatched: u64,
    pub publish_errors: u64,
    pub overload_refusals: u64,
    pub nan_resets: u64,
    pub reclaimed: u64,
    pub controls_applied: u64,
    pub controls_coalesced: u64,
    pub bundles: u64,
    /// The `tick` phase over the last stats period.
    pub tick_mean_ms: f64,
    pub tick_max_ms: f64,
    /// Cloths below the quality preset their client asked for (adaptive quality).
    pub quality_degraded: u64,
}

fn u(r: &Reader<'_>, k: &str) -> u64 {
    r.u64(k, false).ok().flatten().unwrap_or(0)
}

fn f(r: &Reader<'_>, k: &str) -> f64 {
    r.f64(k, false).ok().flatten().unwrap_or(0.0)
}

fn info_of(r: &Reader<'_>, o: &mut DrapeServerInfo) -> Result<()> {
    fill(&mut o.server, r.str("server", false)?.unwrap_or(""));
    let version = r.str("version", false)?.unwrap_or("1.0");
    let (ma, mi) = version.split_once('.').unwrap_or((version, "0"));
    o.version_major = ma.parse().unwrap_or(1);
    o.version_minor = mi.parse().unwrap_or(0);
    o.tick_rate = f(r, "tick_rate");
    o.tick = u(r, "tick");
    o.cloths = u(r, "cloths");
    o.clients = u(r, "clients");
    o.vertices = u(r, "vertices");
    fill(&mut o.solver, r.str("solver", false).ok().flatten().unwrap_or(""));
    fill(&mut o.device, r.str("device", false).ok().flatten().unwrap_or(""));
    if let Some(l) = r.sub("limits", false)? {
        o.max_cloths = u(&l, "max_cloths");
        o.max_cloths_per_client = u(&l, "max_cloths_per_client");
        o.max_vertices_per_cloth = u(&l, "max_vertices_per_cloth");
        o.max_total_vertices = u(&l, "max_total_vertices");
        o.max_message_bytes = u(&l, "max_message_bytes");
        o.max_pin_updates = u(&l, "max_pin_updates");
        o.max_batch_items = u(&l, "max_batch_items");
        o.max_colliders = u(&l, "max_colliders");
        o.max_iterations = u(&l, "max_iterations");
        o.max_substeps = u(&l, "max_substeps");
    }
    o.grace_period_s = f(r, "grace_period_s");
    o.stats_period_s = f(r, "stats_period_s");
    Ok(())
}

/// Ask `server` (NULL: this client's default server) for its info: version, tick rate, load,
/// limits. Waits for the reply (up to the timeout): call it at load time, not every frame.
#[no_mangle]
pub unsafe extern "C" fn drape_client_server_info(client: *const DrapeClient, server: *const c_char,
                                                  out: *mut DrapeServerInfo) -> i32 {
    guard(|| {
        let (Some(c), Some(o)) = (client.as_ref(), out.as_mut()) else { return bad("client or out is NULL") };
        let server = match opt_str(server, "server") {
            Ok(Some(s)) => s.to_string(),
            Ok(None) => match c.client.server_id() {
                Ok(s) => s,
                Err(e) => return fail(e),
            },
            Err(code) => return code,
        };
        let m = match c.client.info_of(&server) {
            Ok(m) => m,
            Err(e) => return fail(e),
        };
        *o = std::mem::zeroed();
        match info_of(&Reader::new(&m, ""), o) {
            Ok(()) => DRAPE_OK,
            Err(e) => fail(e),
        }
    })
}

/// The last stats publication of `server` (NULL: this client's default server, else the first
/// live one), as received on `{ns}/server/{server}/stats` every stats period: DRAPE_OK, or
/// DRAPE_NO_DATA when none has arrived yet. Never blocks.
#[no_mangle]
pub unsafe extern "C" fn drape_client_server_stats(client: *const DrapeClient, server: *const c_char,
                                                   out: *mut DrapeServerStats) -> i32 {
    guard(|| {
        let (Some(c), Some(o)) = (client.as_ref(), out.as_mut()) else { return bad("client or out is NULL") };
        let server = match opt_str(server, "server") {
            Ok(Some(s)) => s.to_string(),
            Ok(None) => match c.client.known_server() {
                Some(s) => s,
                None => return DRAPE_NO_DATA,
            },
            Err(code) => return code,
        };
        let Some(m) = c.client.stats(&server) else { return DRAPE_NO_DATA };
        let r = Reader::new(&m, "");
        *o = std::mem::zeroed();
        fill(&mut o.server, &server);
        o.tick = u(&r, "tick");
        o.time_ns = u(&r, "time_ns");
        o.uptime_s = f(&r, "uptime_s");
        o.tick_rate = f(&r, "tick_rate");
        o.cloths = u(&r, "cloths");
        o.clients = u(&r, "clients");
        o.alive_clients = u(&r, "alive_clients");
        o.vertices = u(&r, "vertices");
        o.ticks = u(&r, "ticks");
        o.missed_ticks = u(&r, "missed_ticks");
        o.skipped_frames = u(&r, "skipped_frames");
        o.published = u(&r, "published");
        o.unwatched = u(&r, "unwatched");
        o.publish_errors = u(&r, "publish_errors");
        o.overload_refusals = u(&r, "overload_refusals");
        o.nan_resets = u(&r, "nan_resets");
        o.reclaimed = u(&r, "reclaimed");
        o.controls_applied = u(&r, "controls_applied");
        o.controls_coalesced = u(&r, "controls_coalesced");
        o.bundles = u(&r, "bundles");
        if let Ok(Some(p)) = r.sub("phases", false) {
            if let Ok(Some(t)) = p.sub("tick", false) {
                o.tick_mean_ms = f(&t, "mean_ms");
                o.tick_max_ms = f(&t, "max_ms");
            }
        }
        if let Ok(Some(q)) = r.sub("quality", false) {
            o.quality_degraded = u(&q, "degraded");
        }
        DRAPE_OK
    })
}

/// The name of the server this client uses by default (as `drape_client_server_id`) if one is
/// known already, without waiting: DRAPE_OK, or DRAPE_NO_DATA before any server was seen.
#[no_mangle]
pub unsafe extern "C" fn drape_client_known_server(client: *const DrapeClient, buf: *mut c_char, len: usize) -> i32 {
    guard(|| {
        let Some(c) = client.as_ref() else { return bad("client is NULL") };
        match c.client.known_server() {
            Some(s) => copy_out(&s, buf, len),
            None => DRAPE_NO_DATA,
        }
    })
}
