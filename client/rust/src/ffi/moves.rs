//! C ABI of protocol 1.4 `moves` (PROTOCOL.md 5.1.1): the same pinned vertices of many cloths
//! moved with one block per server (batch items toward an older server). See `mod.rs` for the
//! conventions.
use super::cloth::{slice, DrapeCloth};
use super::{bad, fail, guard, DrapeClient, DRAPE_OK};
use crate::client::Cloth;

/// Move pinned vertices `indices[0..index_count]` of each of the `cloth_count` cloths
/// `cloths[j]`: its vertex `indices[i]` goes to `targets[3 * (j * index_count + i) ..][0..3]`
/// (`3 * cloth_count * index_count` floats, cloth by cloth). To a protocol 1.4 server one
/// `moves` block per request (`Client::move_pins_many`); to an older one, batch items.
/// `wait`: block for the replies; cloth j's status goes to `codes[j]` and its first tick showing
/// the move to `ticks[j]` (either may be NULL, else `cloth_count` long); DRAPE_OK then means the
/// requests were answered, each cloth's outcome is in `codes`. Not waiting: failures arrive as
/// REQUEST_FAILED events. Bad input (targets NULL, repeated indices, a non-finite target, a cloth
/// not live) is refused before anything is sent.
#[no_mangle]
pub unsafe extern "C" fn drape_move_pins_many(client: *const DrapeClient, cloths: *const *const DrapeCloth,
                                              cloth_count: usize, indices: *const u32, index_count: usize,
                                              targets: *const f32, wait: bool, codes: *mut i32, ticks: *mut u64) -> i32 {
    guard(|| {
        let Some(c) = client.as_ref() else { return bad("client is NULL") };
        let Some(ptrs) = slice(cloths, cloth_count) else { return bad("cloths is NULL") };
        let mut list: Vec<Cloth> = Vec::with_capacity(ptrs.len());
        for p in ptrs {
            match p.as_ref() {
                Some(dc) => list.push(dc.cloth.clone()),
                None => return bad("a cloth is NULL"),
            }
        }
        let (Some(idx), Some(tgt)) = (slice(indices, index_count), slice(targets, 3 * cloth_count * index_count)) else {
            return bad("indices or targets is NULL");
        };
        match c.client.move_pins_many(&list, idx, tgt, wait) {
            Ok(Some(results)) => {
                for (j, r) in results.iter().enumerate() {
                    if !codes.is_null() {
                        *codes.add(j) = r.as_ref().map_or_else(|e| e.code as i32, |_| DRAPE_OK);
                    }
                    if !ticks.is_null() {
                        *ticks.add(j) = *r.as_ref().unwrap_or(&0);
                    }
                }
                DRAPE_OK
            }
            Ok(None) => DRAPE_OK,
            Err(e) => fail(e),
        }
    })
}
