//! Protocol 1.4 `moves` blocks from the client's side (PROTOCOL.md 5.1.1): the same pinned
//! vertices of many cloths moved with one columnar block per server (and per `MAX_BATCH_MOVES`
//! cloths) instead of one batch item per cloth.
//!
//! - [`Client::move_pins_many`]: every cloth of a list moves its pins `indices` (the game loop's
//!   per-tick call, as the Python SDK's `move_pins_many`).
//! - [`take_block`]: a [`super::Batch`]'s pins-only items that share one index list (two or
//!   more, one per cloth not otherwise in the batch) go as one block; the other items as before.
//!
//! Both send blocks only to a server whose `info.version` is 1.4 or later (a 1.3 server ignores
//! the field): to an older one the same moves go as batch items (or single controls to 1.0).
//! Each cloth's last targets are recorded for the failover (PROTOCOL.md 11.1) as for a control.
use super::cloth::{self, Batch, ClothInner};
use super::{failover, Client, Event, Inner};
use crate::wire::error::{Error, ErrorCode, Result};
use crate::wire::msg::{Control, ControlBatch, Material, Pins};
use crate::wire::reader::Map;
use crate::wire::replies::Applied;
use crate::wire::moves::check_block;
use crate::wire::{Limits, Moves, MovesReply, MAX_BATCH_MOVES};
use std::collections::{BTreeMap, HashMap};
use std::sync::{Arc, Weak};

/// One cloth of a block: its position in the caller's list, the cloth, its id and token on its
/// server, and its `3 k` targets.
struct Mover<'a> {
    pos: usize,
    cloth: Arc<ClothInner>,
    id: String,
    token: String,
    targets: &'a [f32],
}

impl Client {
    /// 1.4: move the same pinned vertices `indices` of every cloth of `cloths`: cloth `j`'s vertex
    /// `indices[i]` goes to `targets[3(j k + i) .. 3(j k + i) + 3]` (`k = indices.len()`; the
    /// targets cloth by cloth). One `moves` block per server speaking 1.4 (PROTOCOL.md 5.1.1),
    /// batch items to older servers. `wait`: each cloth's first tick showing its move, or its
    /// error (`invalid_value` for an index that is not one of its pinned vertices...); otherwise
    /// return at once (failures become [`Event::RequestFailed`]; nothing is sent when a cloth is
    /// not live or an index is beyond its vertices). Bad input (targets of another length,
    /// repeated indices, a non-finite target) is refused before anything is sent.
    pub fn move_pins_many(&self, cloths: &[super::Cloth], indices: &[u32], targets: &[f32], wait: bool)
                          -> Result<Option<Vec<Result<u64>>>> {
        let inner = &self.inner;
        inner.check_open()?;
        let (n, k) = (cloths.len(), indices.len());
        if n == 0 {
            return Ok(wait.then(Vec::new));
        }
        // the shape and values of the moves, whatever the servers (checked again per block
        // with each server's limits)
        check_block(n, indices, targets, &Limits::default())?;
        let mut results: Vec<Result<Applied>> = vec![Ok(Applied::default()); n];
        let mut by_server: BTreeMap<String, Vec<Mover<'_>>> = BTreeMap::new();
        for (pos, c) in cloths.iter().enumerate() {
            if !Arc::ptr_eq(&c.client, inner) {
                results[pos] = Err(Error::new(ErrorCode::InvalidValue, format!("cloth {} belongs to another client", c.handle())));
                continue;
            }
            match c.inner.owner() {
                Ok((server, id, token, nv)) => match indices.iter().find(|i| **i >= nv) {
                    Some(i) => {
                        results[pos] = Err(Error::new(ErrorCode::IndexOutOfRange, format!("pin index {i} but cloth {id} has {nv} vertices")))
                    }
                    None => {
                        let targets = &targets[3 * k * pos..3 * k * (pos + 1)];
                        by_server.entry(server).or_default().push(Mover { pos, cloth: c.inner.clone(), id, token, targets });
                    }
                },
                Err(e) => results[pos] = Err(e),
            }
        }
        if !wait {
            if let Some(e) = results.iter().find_map(|r| r.as_ref().err()) {
                return Err(e.clone()); // nothing is sent when a cloth cannot be moved
            }
        }
        for (server, movers) in by_server {
            let ((ma, mi), _) = inner.server_info(&server)?;
            if (ma, mi) >= (1, 4) {
                movers.iter().for_each(|m| m.cloth.note_pins(indices, m.targets));
                send_blocks(inner, &server, &movers, indices, wait, &mut results)?;
                continue;
            }
            // a 1.3 (or older) server ignores `moves`: the same moves as batch items
            let mut batch = Batch::default();
            for m in &movers {
                let pins = Pins { indices: indices.to_vec(), targets: m.targets.to_vec() };
                batch.items.push((m.cloth.clone(), Control { pins: Some(pins), ..Default::default() }));
            }
            if let Some(out) = cloth::send_batch(inner, batch, wait)? {
                for (m, r) in movers.iter().zip(out) {
                    results[m.pos] = r;
                }
            }
        }
        Ok(wait.then(|| results.into_iter().map(|r| r.map(|a| a.tick)).collect()))
    }
}

/// A control that a moves block can carry: pin targets at distinct indices and nothing else.
fn pins_only(c: &Control) -> Option<&Pins> {
    let p = c.pins.as_ref().filter(|p| !p.indices.is_empty() && p.targets.len() == 3 * p.indices.len())?;
    let others = c.colliders.is_some() || c.gravity.is_some() || c.wind.is_some() || c.material != Material::default()
        || c.features.is_some() || c.features_add.is_some() || c.features_remove.is_some() || c.iterations.is_some()
        || c.substeps.is_some() || c.chebyshev_rho.is_some() || c.state.is_some() || c.quality.is_some() || c.reset;
    let mut sorted = p.indices.clone();
    sorted.sort_unstable();
    (!others && sorted.windows(2).all(|w| w[0] != w[1])).then_some(p)
}

/// Of a batch's (already validated and recorded) items for `server`, a 1.4 server: send the
/// largest set (two or more) of pins-only items sharing one index list, one per cloth not
/// otherwise in the batch, as a moves block; they are removed from `items`, their outcomes
/// written to `results`.
pub(crate) fn take_block(inner: &Arc<Inner>, server: &str, items: &mut Vec<(usize, Arc<ClothInner>, Control)>, wait: bool,
                         results: &mut [Result<Applied>]) -> Result<()> {
    if items.len() < 2 {
        return Ok(());
    }
    let mut per_cloth: HashMap<u64, usize> = HashMap::new();
    for (_, c, _) in items.iter() {
        *per_cloth.entry(c.handle).or_default() += 1;
    }
    let mut groups: HashMap<&[u32], Vec<usize>> = HashMap::new();
    for (j, (_, c, ctl)) in items.iter().enumerate() {
        if let Some(p) = pins_only(ctl).filter(|_| per_cloth[&c.handle] == 1) {
            groups.entry(p.indices.as_slice()).or_default().push(j);
        }
    }
    let Some((indices, chosen)) = groups.into_iter().max_by_key(|(idx, js)| (js.len(), std::cmp::Reverse(idx.to_vec()))) else {
        return Ok(());
    };
    if chosen.len() < 2 {
        return Ok(());
    }
    let indices = indices.to_vec();
    let mut block = Vec::with_capacity(chosen.len());
    for j in chosen.into_iter().rev() {
        block.push(items.remove(j));
    }
    block.reverse();
    let movers: Vec<Mover<'_>> = block
        .iter()
        .map(|(pos, c, ctl)| Mover {
            pos: *pos,
            cloth: c.clone(),
            id: ctl.cloth.clone(),
            token: ctl.token.clone(),
            targets: &ctl.pins.as_ref().expect("pins-only").targets,
        })
        .collect();
    send_blocks(inner, server, &movers, &indices, wait, results)
}

/// Send `movers` (cloths of `server`, a 1.4 server) as blocks of at most `MAX_BATCH_MOVES`,
/// all validated before any is sent. `wait`: their outcomes go to `results[pos]`.
fn send_blocks(inner: &Arc<Inner>, server: &str, movers: &[Mover<'_>], indices: &[u32], wait: bool,
               results: &mut [Result<Applied>]) -> Result<()> {
    let lim = inner.limits(server);
    let blocks: Vec<(&[Mover<'_>], Moves)> = movers
        .chunks(MAX_BATCH_MOVES)
        .map(|ch| {
            let mv = Moves {
                cloths: ch.iter().map(|m| m.id.clone()).collect(),
                tokens: ch.iter().map(|m| m.token.clone()).collect(),
                indices: indices.to_vec(),
                targets: ch.iter().flat_map(|m| m.targets.iter().copied()).collect(),
            };
            (ch, mv)
        })
        .collect();
    for (_, mv) in &blocks {
        mv.validate(&lim)?;
    }
    for (ch, mv) in blocks {
        let rid = inner.next_rid();
        let payload = ControlBatch { rid, client: inner.client_id.clone(), items: Vec::new() }.encode_with_moves(Some(&mv));
        if wait {
            match inner.request(server, "control_batch", payload).and_then(|m| outcomes(&m, ch.len(), rid)) {
                Ok(outs) => {
                    for (m, o) in ch.iter().zip(outs) {
                        if o.as_ref().is_err_and(|e| e.code == ErrorCode::NotFound) {
                            failover::cloth_not_found(inner, &m.cloth, &m.id);
                        }
                        results[m.pos] = o;
                    }
                }
                Err(e) => ch.iter().for_each(|m| results[m.pos] = Err(e.clone())),
            }
            continue;
        }
        let watch: Vec<(u64, Weak<ClothInner>, String)> =
            ch.iter().map(|m| (m.cloth.handle, Arc::downgrade(&m.cloth), m.id.clone())).collect();
        let on_ok = move |inner: &Arc<Inner>, m: Map| match outcomes(&m, watch.len(), rid) {
            Ok(outs) => {
                for ((h, c, id), o) in watch.iter().zip(outs) {
                    let Err(error) = o else { continue };
                    if let (ErrorCode::NotFound, Some(c)) = (error.code, c.upgrade()) {
                        failover::cloth_not_found(inner, &c, id);
                    }
                    inner.push_event(Event::RequestFailed { handle: Some(*h), cloth: id.clone(), request: 0, error });
                }
            }
            Err(error) => inner.push_event(Event::RequestFailed { handle: None, cloth: String::new(), request: 0, error }),
        };
        inner.send(server, "control_batch", payload, None, Some(Box::new(on_ok)), None)?;
    }
    Ok(())
}

/// Each move's outcome from a batch reply to a block of `n` moves: applied from `moves_tick`, or
/// refused (`moves_failed`). A reply without the 1.4 fields, or naming a position beyond the
/// block, is `internal`.
fn outcomes(m: &Map, n: usize, rid: u64) -> Result<Vec<Result<Applied>>> {
    let rep = MovesReply::from_map(m)?.ok_or_else(|| {
        Error::new(ErrorCode::Internal, "the server answered a moves block without moves_tick (not 1.4)").with_rid(rid)
    })?;
    let mut out: Vec<Result<Applied>> = vec![Ok(Applied { tick: rep.moves_tick, features: None }); n];
    for f in &rep.moves_failed {
        let slot = out.get_mut(f.position).ok_or_else(|| {
            Error::new(ErrorCode::Internal, format!("moves_failed names position {} of {n}", f.position)).with_rid(rid)
        })?;
        *slot = Err(f.to_error(rid));
    }
    Ok(out)
}
