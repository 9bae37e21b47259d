//! The state bundle payload `DRPB` (PROTOCOL.md section 9.1): parsing with the reading rules
//! (entries point into the payload, nothing is copied) and encoding.
use super::error::{malformed, Error, ErrorCode, Result};
use super::keys::valid_id;
use super::layout::{bundle as B, entry as E, BUNDLE_ALIGN};
use super::state::{decode_state_into, StateHeader};
use super::{PROTOCOL_MAJOR, PROTOCOL_MINOR};

pub const BUNDLE_MAGIC: &[u8; 4] = b"DRPB";
pub const BUNDLE_HEADER_SIZE: usize = B::SIZE;
const ENTRY_SIZE: usize = E::SIZE;

/// Round up to a multiple of 8.
pub fn align8(n: usize) -> usize {
    (n + BUNDLE_ALIGN - 1) & !(BUNDLE_ALIGN - 1)
}

/// One entry of a bundle: the cloth id and where its state payload lies in the bundle.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct BundleEntry<'a> {
    pub cloth: &'a str,
    /// Offset of the entry itself and of its state payload from the start of the bundle.
    pub entry_offset: usize,
    pub state_offset: usize,
    pub state_size: usize,
}

/// A parsed bundle: every header field and the entries (states are decoded on demand).
#[derive(Debug, Clone, PartialEq)]
pub struct Bundle<'a> {
    pub major: u8,
    pub minor: u8,
    pub header_size: u16,
    pub flags: u32,
    pub tick: u64,
    pub server_time_ns: u64,
    pub entries: Vec<BundleEntry<'a>>,
    pub data: &'a [u8],
}

impl<'a> Bundle<'a> {
    /// The state payload bytes of entry `i` (exactly what its own key would carry).
    pub fn payload(&self, i: usize) -> &'a [u8] {
        let e = &self.entries[i];
        &self.data[e.state_offset..e.state_offset + e.state_size]
    }
    /// Decode entry `i`'s state into caller buffers (see [`decode_state_into`]).
    pub fn decode_into(&self, i: usize, positions: &mut [f32], normals: Option<&mut [f32]>) -> Result<StateHeader> {
        decode_state_into(self.payload(i), positions, normals)
    }
}

/// Parse a bundle's header and entry table. Errors: bad magic, unknown major, header_size
/// below 32, an entry running past the end, `h < 8 + L`, an invalid id. A longer header,
/// unknown flags and bytes after the last entry are accepted.
pub fn parse_bundle(data: &[u8]) -> Result<Bundle<'_>> {
    let size = data.len();
    if size < BUNDLE_HEADER_SIZE {
        return Err(malformed(format!("bundle of {size} bytes is shorter than the 32-byte header")));
    }
    if B::MAGIC.get(data) != BUNDLE_MAGIC {
        return Err(malformed(format!("bundle magic {:?} is not \"DRPB\"", String::from_utf8_lossy(B::MAGIC.get(data)))));
    }
    let (major, minor) = (B::MAJOR.u8(data), B::MINOR.u8(data));
    if major != PROTOCOL_MAJOR {
        return Err(Error::new(
            ErrorCode::UnsupportedVersion,
            format!("bundle version {major}.{minor} is not supported; this side speaks {PROTOCOL_MAJOR}.{PROTOCOL_MINOR}"),
        ));
    }
    let header_size = B::HEADER_SIZE.u16(data);
    if (header_size as usize) < BUNDLE_HEADER_SIZE {
        return Err(malformed(format!("bundle header_size {header_size} is below 32")));
    }
    let count = B::COUNT.u32(data) as usize;
    let flags = B::FLAGS.u32(data);
    let tick = B::TICK.u64(data);
    let server_time_ns = B::SERVER_TIME_NS.u64(data);
    let mut entries = Vec::with_capacity(count.min(1024));
    let mut at = header_size as usize;
    for i in 0..count {
        if at + ENTRY_SIZE > size {
            return Err(malformed(format!("bundle entry {i} of {count} starts at byte {at}, past the end ({size})")));
        }
        let h = u16::from_le_bytes(E::HEADER_SIZE.at(data, at).try_into().unwrap()) as usize;
        let id_len = E::ID_LENGTH.at(data, at)[0] as usize;
        let st_size = u32::from_le_bytes(E::STATE_SIZE.at(data, at).try_into().unwrap()) as usize;
        if h < ENTRY_SIZE + id_len {
            return Err(malformed(format!("bundle entry {i}: entry header size {h} is below 8 + id length {id_len}")));
        }
        if at + h + st_size > size {
            return Err(malformed(format!(
                "bundle entry {i}: state of {st_size} bytes at byte {} runs past the end ({size})",
                at + h
            )));
        }
        let cloth = std::str::from_utf8(&data[at + ENTRY_SIZE..at + ENTRY_SIZE + id_len]).unwrap_or("");
        if !valid_id(cloth) {
            return Err(malformed(format!("bundle entry {i}: invalid cloth id")));
        }
        entries.push(BundleEntry { cloth, entry_offset: at, state_offset: at + h, state_size: st_size });
        at = align8(at + h + st_size);
    }
    Ok(Bundle { major, minor, header_size, flags, tick, server_time_ns, entries, data })
}

/// Encode a bundle of (cloth id, state payload) pairs in order (each state should carry the
/// bundle's tick and server time).
pub fn encode_bundle(tick: u64, server_time_ns: u64, states: &[(&str, &[u8])], flags: u32) -> Result<Vec<u8>> {
    let mut out = vec![0u8; BUNDLE_HEADER_SIZE];
    B::MAGIC.put(&mut out, 0, BUNDLE_MAGIC);
    B::MAJOR.put(&mut out, 0, &[PROTOCOL_MAJOR]);
    B::MINOR.put(&mut out, 0, &[PROTOCOL_MINOR]);
    B::HEADER_SIZE.put(&mut out, 0, &(BUNDLE_HEADER_SIZE as u16).to_le_bytes());
    B::COUNT.put(&mut out, 0, &(states.len() as u32).to_le_bytes());
    B::FLAGS.put(&mut out, 0, &flags.to_le_bytes());
    B::TICK.put(&mut out, 0, &tick.to_le_bytes());
    B::SERVER_TIME_NS.put(&mut out, 0, &server_time_ns.to_le_bytes());
    for (cloth, st) in states {
        if !valid_id(cloth) {
            return Err(super::error::invalid(format!("invalid cloth id {cloth:?}")));
        }
        let h = align8(ENTRY_SIZE + cloth.len());
        let e = out.len();
        out.resize(e + ENTRY_SIZE, 0);
        E::HEADER_SIZE.put(&mut out, e, &(h as u16).to_le_bytes());
        E::ID_LENGTH.put(&mut out, e, &[cloth.len() as u8]);
        E::STATE_SIZE.put(&mut out, e, &(st.len() as u32).to_le_bytes());
        out.extend_from_slice(cloth.as_bytes());
        out.resize(out.len() + h - ENTRY_SIZE - cloth.len(), 0);
        out.extend_from_slice(st);
        out.resize(align8(out.len()), 0);
    }
    Ok(out)
}
