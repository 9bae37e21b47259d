//! The placement rule of PROTOCOL.md 11.3 (protocol 1.4), without any network: how a client
//! ranks the live servers for a new cloth (and for a failover resubmission, 11.1) by their
//! published stats ([`ServerLoad`], [`rank`]), and which refusals send a cloth to the next
//! server ([`PLACE_ELSEWHERE`]). The client's state (stats received, its own submissions not
//! yet counted in them) is `client::placement`.
//!
//! The rank, best first: servers with stats before those without; then the least load (the
//! stats' `vertices` plus this client's `pending` vertices there); then the lowest
//! `phases.tick.mean_ms`; then [`tiebreak`], a hash of (client id, server id), so that clients
//! seeing equal loads prefer different servers. The hash is the Python SDK's
//! (`client/placement.py`: BLAKE2b with an 8-byte digest of `client \0 server`, big-endian), so
//! a Rust and a Python client with the same id rank servers alike.
use super::error::ErrorCode;
use super::reader::{Map, Reader};

/// Refusals of a submission that another server may not give: try the next one in the rank
/// (`unavailable`: no reply). Other errors mean the request itself is wrong and are reported.
pub const PLACE_ELSEWHERE: [ErrorCode; 4] =
    [ErrorCode::Overloaded, ErrorCode::Busy, ErrorCode::LimitExceeded, ErrorCode::Unavailable];

/// One server as the rule sees it: `known` (its stats received and not stale), its stats'
/// `vertices` and mean tick (ms), and `pending`: this client's vertices placed there that
/// those stats do not count yet.
#[derive(Debug, Clone, PartialEq)]
pub struct ServerLoad {
    pub server: String,
    pub known: bool,
    pub vertices: u64,
    pub tick_ms: f64,
    pub pending: u64,
}

impl ServerLoad {
    /// A server's load from its decoded stats publication (None: none received, or stale).
    pub fn from_stats(server: &str, stats: Option<&Map>, pending: u64) -> ServerLoad {
        let Some(m) = stats else {
            return ServerLoad { server: server.to_string(), known: false, vertices: 0, tick_ms: 0.0, pending };
        };
        let r = Reader::new(m, "");
        let tick_ms = r
            .sub("phases", false)
            .ok()
            .flatten()
            .and_then(|p| p.sub("tick", false).ok().flatten())
            .and_then(|t| t.f64("mean_ms", false).ok().flatten())
            .filter(|x| x.is_finite())
            .unwrap_or(0.0);
        let vertices = r.u64("vertices", false).ok().flatten().unwrap_or(0);
        ServerLoad { server: server.to_string(), known: true, vertices, tick_ms, pending }
    }

    /// The load the rule compares: the stats' vertices plus this client's pending ones.
    pub fn total(&self) -> u64 {
        self.vertices.saturating_add(self.pending)
    }
}

/// Server ids best first by the rule of PROTOCOL.md 11.3 (module docs).
pub fn rank(loads: &[ServerLoad], client_id: &str) -> Vec<String> {
    let mut keyed: Vec<(&ServerLoad, u64)> = loads.iter().map(|l| (l, tiebreak(client_id, &l.server))).collect();
    keyed.sort_by(|(a, ha), (b, hb)| {
        (!a.known)
            .cmp(&!b.known)
            .then(a.total().cmp(&b.total()))
            .then(a.tick_ms.total_cmp(&b.tick_ms))
            .then(ha.cmp(hb))
            .then(a.server.cmp(&b.server))
    });
    keyed.into_iter().map(|(l, _)| l.server.clone()).collect()
}

/// A stable number per (client, server): the rule's last key. BLAKE2b-64 of
/// `client \0 server` read big-endian, as the Python SDK's `placement.tiebreak`.
pub fn tiebreak(client_id: &str, server: &str) -> u64 {
    let mut msg = Vec::with_capacity(client_id.len() + server.len() + 1);
    msg.extend_from_slice(client_id.as_bytes());
    msg.push(0);
    msg.extend_from_slice(server.as_bytes());
    u64::from_be_bytes(blake2b_64(&msg))
}

/// How uneven a placement is: max / mean - 1 of the per-server counts (0: even).
pub fn spread(counts: &[usize]) -> f64 {
    let mean = counts.iter().sum::<usize>() as f64 / counts.len().max(1) as f64;
    if mean > 0.0 { *counts.iter().max().unwrap_or(&0) as f64 / mean - 1.0 } else { 0.0 }
}

const IV: [u64; 8] = [
    0x6a09e667f3bcc908, 0xbb67ae8584caa73b, 0x3c6ef372fe94f82b, 0xa54ff53a5f1d36f1,
    0x510e527fade682d1, 0x9b05688c2b3e6c1f, 0x1f83d9abfb41bd6b, 0x5be0cd19137e2179,
];

/// The message schedule of each round; rounds 10 and 11 reuse rows 0 and 1 (RFC 7693, 2.7).
const SIGMA: [[usize; 16]; 10] = [
    [0, 1, 2, 3, 4, 5, 6, 7, 8, 9, 10, 11, 12, 13, 14, 15],
    [14, 10, 4, 8, 9, 15, 13, 6, 1, 12, 0, 2, 11, 7, 5, 3],
    [11, 8, 12, 0, 5, 2, 15, 13, 10, 14, 3, 6, 7, 1, 9, 4],
    [7, 9, 3, 1, 13, 12, 11, 14, 2, 6, 5, 10, 4, 0, 15, 8],
    [9, 0, 5, 7, 2, 4, 10, 15, 14, 1, 11, 12, 6, 8, 3, 13],
    [2, 12, 6, 10, 0, 11, 8, 3, 4, 13, 7, 5, 15, 14, 1, 9],
    [12, 5, 1, 15, 14, 13, 4, 10, 0, 7, 6, 3, 9, 2, 8, 11],
    [13, 11, 7, 14, 12, 1, 3, 9, 5, 0, 15, 4, 8, 6, 2, 10],
    [6, 15, 14, 9, 11, 3, 0, 8, 12, 2, 13, 7, 1, 4, 10, 5],
    [10, 2, 8, 4, 7, 6, 1, 5, 15, 11, 9, 14, 3, 12, 13, 0],
];

/// BLAKE2b (RFC 7693) without a key and with an 8-byte digest (the digest size is part of its
/// parameter block: not a truncated BLAKE2b-512).
fn blake2b_64(msg: &[u8]) -> [u8; 8] {
    let mut h = IV;
    h[0] ^= 0x0101_0000 ^ 8;
    let blocks = msg.len().div_ceil(128).max(1);
    for b in 0..blocks {
        let mut block = [0u8; 128];
        let chunk = &msg[b * 128..msg.len().min(b * 128 + 128)];
        block[..chunk.len()].copy_from_slice(chunk);
        let last = b + 1 == blocks;
        let t = if last { msg.len() } else { (b + 1) * 128 } as u128;
        compress(&mut h, &block, t, last);
    }
    let mut out = [0u8; 8];
    out.copy_from_slice(&h[0].to_le_bytes());
    out
}

fn compress(h: &mut [u64; 8], block: &[u8; 128], t: u128, last: bool) {
    let m: Vec<u64> = block.chunks_exact(8).map(|c| u64::from_le_bytes(c.try_into().unwrap())).collect();
    let mut v = [0u64; 16];
    v[..8].copy_from_slice(h);
    v[8..].copy_from_slice(&IV);
    v[12] ^= t as u64;
    v[13] ^= (t >> 64) as u64;
    if last {
        v[14] = !v[14];
    }
    let g = |v: &mut [u64; 16], a: usize, b: usize, c: usize, d: usize, x: u64, y: u64| {
        v[a] = v[a].wrapping_add(v[b]).wrapping_add(x);
        v[d] = (v[d] ^ v[a]).rotate_right(32);
        v[c] = v[c].wrapping_add(v[d]);
        v[b] = (v[b] ^ v[c]).rotate_right(24);
        v[a] = v[a].wrapping_add(v[b]).wrapping_add(y);
        v[d] = (v[d] ^ v[a]).rotate_right(16);
        v[c] = v[c].wrapping_add(v[d]);
        v[b] = (v[b] ^ v[c]).rotate_right(63);
    };
    for round in 0..12 {
        let s = SIGMA[round % 10];
        g(&mut v, 0, 4, 8, 12, m[s[0]], m[s[1]]);
        g(&mut v, 1, 5, 9, 13, m[s[2]], m[s[3]]);
        g(&mut v, 2, 6, 10, 14, m[s[4]], m[s[5]]);
        g(&mut v, 3, 7, 11, 15, m[s[6]], m[s[7]]);
        g(&mut v, 0, 5, 10, 15, m[s[8]], m[s[9]]);
        g(&mut v, 1, 6, 11, 12, m[s[10]], m[s[11]]);
        g(&mut v, 2, 7, 8, 13, m[s[12]], m[s[13]]);
        g(&mut v, 3, 4, 9, 14, m[s[14]], m[s[15]]);
    }
    for i in 0..8 {
        h[i] ^= v[i] ^ v[i + 8];
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::wire::reader::{s, Value};

    /// Values of the Python SDK's `drape.client.placement.tiebreak` (computed with it).
    #[test]
    fn tiebreak_is_the_python_sdks() {
        assert_eq!(tiebreak("game-7", "s1"), 12931143466789179004);
        assert_eq!(tiebreak("game-7", "s2"), 6294678467654749080);
        assert_eq!(tiebreak("alice", "eu-1"), 1708364578552437188);
        assert_eq!(tiebreak("", ""), 10734006239897485896);
        // a 129-byte message: two blocks
        assert_eq!(tiebreak(&"c".repeat(64), &"x".repeat(64)), 857617485553176565);
    }

    fn stats(vertices: u64, tick_ms: f64) -> Map {
        let tick = Value::Map(vec![(s("mean_ms"), Value::F64(tick_ms))]);
        vec![(s("vertices"), Value::from(vertices)), (s("phases"), Value::Map(vec![(s("tick"), tick)]))]
    }

    #[test]
    fn rank_known_first_then_load_then_tick_then_hash() {
        let (a, b, c) = (stats(100, 2.0), stats(100, 1.0), stats(50, 9.0));
        let loads = [
            ServerLoad::from_stats("none", None, 0),
            ServerLoad::from_stats("a", Some(&a), 0),
            ServerLoad::from_stats("b", Some(&b), 0),
            ServerLoad::from_stats("c", Some(&c), 0),
        ];
        assert_eq!(rank(&loads, "game-7"), ["c", "b", "a", "none"]);
        // pending vertices count: 60 placed on c makes it heavier than a and b
        let mut l2 = loads.clone();
        l2[3].pending = 60;
        assert_eq!(rank(&l2, "game-7"), ["b", "a", "c", "none"]);
        // equal loads: the hash decides, per client (game-7 prefers s2, whose hash is lower)
        let e = stats(0, 0.0);
        let eq = [ServerLoad::from_stats("s1", Some(&e), 0), ServerLoad::from_stats("s2", Some(&e), 0)];
        assert_eq!(rank(&eq, "game-7"), ["s2", "s1"]);
        let first = |client: &str| rank(&eq, client)[0].clone();
        assert!((0..32).map(|i| first(&format!("c{i}"))).any(|s| s == "s1"), "some clients prefer s1");
        assert_eq!(spread(&[4, 4]), 0.0);
        assert_eq!(spread(&[6, 2]), 0.5);
    }
}
