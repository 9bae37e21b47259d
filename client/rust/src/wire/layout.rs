//! Byte layouts of the binary payloads (PROTOCOL.md sections 9 and 9.1), field by field: the
//! offsets `parse_state` / `encode_state` and `parse_bundle` / `encode_bundle` read and write.
//! They are the packed structs of `client/protocol/drape_wire.h` (generated from the Python
//! package): `tests/layout.rs` compiles that header with `cc` and checks every field's
//! `offsetof` and `sizeof`, each struct's size and the constants against these tables.

/// One field of a header: its name in `drape_wire.h`, byte offset and size.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Field {
    pub name: &'static str,
    pub offset: usize,
    pub size: usize,
}

const fn f(name: &'static str, offset: usize, size: usize) -> Field {
    Field { name, offset, size }
}

/// `drape_state_header` (64 bytes; the vertex data starts at `header_size`).
pub mod state {
    use super::{f, Field};
    pub const MAGIC: Field = f("magic", 0, 4);
    pub const MAJOR: Field = f("major", 4, 1);
    pub const MINOR: Field = f("minor", 5, 1);
    pub const HEADER_SIZE: Field = f("header_size", 6, 2);
    pub const ENCODING: Field = f("encoding", 8, 1);
    pub const RESERVED0: Field = f("reserved0", 9, 1);
    pub const FLAGS: Field = f("flags", 10, 2);
    pub const VERTEX_COUNT: Field = f("vertex_count", 12, 4);
    pub const TICK: Field = f("tick", 16, 8);
    pub const SERVER_TIME_NS: Field = f("server_time_ns", 24, 8);
    pub const BOUNDS_MIN: Field = f("bounds_min", 32, 12);
    pub const BOUNDS_MAX: Field = f("bounds_max", 44, 12);
    pub const RESERVED1: Field = f("reserved1", 56, 8);
    pub const SIZE: usize = 64;
    pub const FIELDS: [Field; 13] = [MAGIC, MAJOR, MINOR, HEADER_SIZE, ENCODING, RESERVED0, FLAGS, VERTEX_COUNT, TICK,
        SERVER_TIME_NS, BOUNDS_MIN, BOUNDS_MAX, RESERVED1];
}

/// `drape_bundle_header` (32 bytes; the first entry starts at `header_size`).
pub mod bundle {
    use super::{f, Field};
    pub const MAGIC: Field = f("magic", 0, 4);
    pub const MAJOR: Field = f("major", 4, 1);
    pub const MINOR: Field = f("minor", 5, 1);
    pub const HEADER_SIZE: Field = f("header_size", 6, 2);
    pub const COUNT: Field = f("count", 8, 4);
    pub const FLAGS: Field = f("flags", 12, 4);
    pub const TICK: Field = f("tick", 16, 8);
    pub const SERVER_TIME_NS: Field = f("server_time_ns", 24, 8);
    pub const SIZE: usize = 32;
    pub const FIELDS: [Field; 8] = [MAGIC, MAJOR, MINOR, HEADER_SIZE, COUNT, FLAGS, TICK, SERVER_TIME_NS];
}

/// `drape_bundle_entry` (8 bytes, then the cloth id, zero padding and the state).
pub mod entry {
    use super::{f, Field};
    pub const HEADER_SIZE: Field = f("header_size", 0, 2);
    pub const ID_LENGTH: Field = f("id_length", 2, 1);
    pub const RESERVED: Field = f("reserved", 3, 1);
    pub const STATE_SIZE: Field = f("state_size", 4, 4);
    pub const SIZE: usize = 8;
    pub const FIELDS: [Field; 4] = [HEADER_SIZE, ID_LENGTH, RESERVED, STATE_SIZE];
}

/// Entries and the states inside a bundle start at multiples of this.
pub const BUNDLE_ALIGN: usize = 8;

impl Field {
    /// The field's bytes in `data` (which must hold the whole header).
    #[inline]
    pub fn get<'a>(&self, data: &'a [u8]) -> &'a [u8] {
        &data[self.offset..self.offset + self.size]
    }
    #[inline]
    pub fn at<'a>(&self, data: &'a [u8], base: usize) -> &'a [u8] {
        &data[base + self.offset..base + self.offset + self.size]
    }
    #[inline]
    pub fn u8(&self, data: &[u8]) -> u8 {
        self.get(data)[0]
    }
    #[inline]
    pub fn u16(&self, data: &[u8]) -> u16 {
        u16::from_le_bytes(self.get(data).try_into().unwrap())
    }
    #[inline]
    pub fn u32(&self, data: &[u8]) -> u32 {
        u32::from_le_bytes(self.get(data).try_into().unwrap())
    }
    #[inline]
    pub fn u64(&self, data: &[u8]) -> u64 {
        u64::from_le_bytes(self.get(data).try_into().unwrap())
    }
    /// Three little-endian float32 (bounds).
    #[inline]
    pub fn f32x3(&self, data: &[u8]) -> [f32; 3] {
        let b = self.get(data);
        [0, 1, 2].map(|i| f32::from_le_bytes(b[4 * i..4 * i + 4].try_into().unwrap()))
    }
    /// Write `bytes` (exactly `size` of them) at the field's offset in `out`, from `base`.
    #[inline]
    pub fn put(&self, out: &mut [u8], base: usize, bytes: &[u8]) {
        assert_eq!(bytes.len(), self.size, "field {} holds {} bytes", self.name, self.size);
        out[base + self.offset..base + self.offset + self.size].copy_from_slice(bytes);
    }
}
