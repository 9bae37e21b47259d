"""Commands from the Zenoh callbacks (and the cook worker) to the tick thread, and the bounded
per-tick intake that carries them.

Two lanes, both bounded by ``max_pending_requests`` (a full lane answers ``busy``, counted in
the stats' errors):

- **structural** commands (add, remove, call), first in first out, at most
  ``MAX_STRUCTURAL_PER_TICK`` applied per tick;
- **controls**, coalesced per cloth: a control for a cloth that already has one pending this
  tick is merged into it (latest value wins field by field, pin targets by index, material by
  key), so however many controls a cloth gets in one tick the World sees one change. Controls
  whose merge would not equal applying them one after the other (either changes the feature
  set, pins after a reset, a cleared collider list after a new one) are not merged: the later
  one waits for the next tick's slot. Every request still gets its reply (the tick from which
  its change holds);
  a batch control's items join the same per-cloth slots and the batch is answered once all of
  its items are applied. The lane holds at most one slot per cloth and at most
  ``max_pending_requests`` waiting replies;
- **moves blocks** (protocol 1.4, PROTOCOL.md 5.1.1): a batch control's ``moves``, checked by the
  handler (server/service/requests/moves.py), wait as one :class:`MoveBlock` each, counted with the
  controls' waiting replies, and are all applied in the next tick after its controls, in
  arrival order (a later block wins where two set the same vertex), with one vectorised World
  call each. They are never merged or deferred.
"""

from __future__ import annotations

import logging
import queue
import threading
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field, replace
from functools import partial
from typing import Any

import numpy as np
import zenoh

from drape.client import protocol as P
from drape.client.protocol.requestfields import CONTROL_FIELDS, any_given

from ..sim.world import World
from .registry import ClothRecord
from .replies import Reply, send, undeclare  # noqa: F401 (re-exported)

log = logging.getLogger(__name__)

MAX_STRUCTURAL_PER_TICK = 256


@dataclass(eq=False)
class Add:
    record: ClothRecord
    params: Any  # ClothParams: handed to the World, which owns them from then on
    colliders: np.ndarray | None
    query: zenoh.Query
    rid: int
    positions: np.ndarray | None = None  # 1.3 resume: the state the cloth starts at
    velocities: np.ndarray | None = None
    mesh: P.MeshCollider | None = None  # 1.8: the cloth's own mesh collider


@dataclass(eq=False)
class SceneColliders:
    """1.7: a scene's colliders, for every cloth of it from the next tick on; the reply waits."""

    scene: str
    colliders: np.ndarray | None  # None: left as they are
    query: zenoh.Query
    reply: P.SceneReply  # its tick set when applied
    mesh: P.MeshCollider | None = None  # 1.8: the scene's mesh collider set, moved or removed


@dataclass(eq=False)
class Remove:
    record: ClothRecord
    query: zenoh.Query
    rid: int


@dataclass(eq=False)
class Call:
    fn: Callable[[World], Any]
    done: threading.Event = field(default_factory=threading.Event)
    result: Any = None
    error: BaseException | None = None


@dataclass(eq=False)
class BatchControl:
    """A batch control's reply, filled item by item (items refused on arrival already are) and,
    with moves (1.4), by its block: the moves refused and the tick the others hold from."""

    query: zenoh.Query
    rid: int
    results: list[P.BatchItemResult | None]
    pending: int = 0  # items (and the moves block) still to apply
    features: bool = False  # a 1.2 request: applied results carry the cloth's feature set
    moves_failed: list[tuple[int, str, str]] | None = None  # 1.4: the request had moves; refused ones
    moves_tick: int | None = None  # 1.4: when its moves block was applied

    def reply(self, tick: int) -> Reply:
        """The batch's reply (encoded on the replying thread)."""
        moves_tick = None
        if self.moves_failed is not None:
            moves_tick = tick if self.moves_tick is None else self.moves_tick
            self.moves_failed.sort()
        rep = P.ControlBatchReply(tick, self.results, self.rid, moves_tick, self.moves_failed)  # type: ignore[arg-type]
        return Reply(self.query, partial(P.encode_control_batch_reply, rep))

    def one_done(self, tick: int) -> Reply | None:
        """An item or the moves block is settled: the reply once nothing is pending."""
        self.pending -= 1
        return self.reply(tick) if self.pending == 0 else None


@dataclass(eq=False)
class MoveBlock:
    """A batch control's ``moves`` (1.4) after the handler's checks, for one vectorised World
    call: distinct live handles owned by the batch client, indices pinned in each cloth."""

    handles: np.ndarray  # (m,) int64
    positions: np.ndarray  # (m,) int64: each handle's position in the request's block
    cloths: list[str]  # the request's cloth ids (by position, for messages)
    indices: np.ndarray  # (k,) int64
    targets: np.ndarray  # (m, k, 3) float32
    waiter: BatchControl
    #: earlier requests' blocks of exactly the same moves (same cloths and indices) that this one
    #: replaced in the intake before their tick (latest wins): answered with this block's tick
    superseded: list[BatchControl] = field(default_factory=list)


@dataclass(eq=False)
class ControlSlot:
    """Every control for one cloth this tick, merged; who waits for the outcome."""

    record: ClothRecord
    req: P.ControlRequest
    colliders: np.ndarray | None
    # (query, (rid, reply with features)) or (BatchControl, item index)
    waiters: list[tuple[Any, Any]] = field(default_factory=list)
    merged: int = 1  # requests in this slot
    deferred: int = 0  # ticks it waited for its kernels to be built


@dataclass(eq=False)
class Prepare:
    """For the cook worker: build the kernels of a cloth's coming parameters."""

    fabric: Any
    params: Any


_gives_features = any_given(f for f in CONTROL_FIELDS if f.acts in ("features", "quality"))


def _touches_features(r: P.ControlRequest) -> bool:
    return _gives_features(r) or (r.state is not None and r.state.normals is not None)


def mergeable(a: P.ControlRequest, b: P.ControlRequest) -> bool:
    """Whether ``merge_controls(a, b)`` does exactly what ``a`` then ``b`` would."""
    if _touches_features(a) or _touches_features(b):
        return False
    if a.reset and b.pins is not None and len(b.pins.indices):  # pins after a reset are kept
        return False
    return not (a.colliders and b.colliders is not None and not b.colliders)  # [] keeps the feature a set


def _merge_pins(pa: P.PinUpdate | None, pb: P.PinUpdate | None) -> P.PinUpdate | None:
    if pb is None or not len(pb.indices):
        return pa
    if pa is None or not len(pa.indices):
        return pb
    idx = np.concatenate([pa.indices, pb.indices])
    tgt = np.concatenate([np.asarray(pa.targets).reshape(-1, 3), np.asarray(pb.targets).reshape(-1, 3)])
    rev = idx[::-1]
    _, first = np.unique(rev, return_index=True)  # last occurrence of each index wins
    keep = np.sort(len(idx) - 1 - first)
    return replace(pb, indices=idx[keep], targets=tgt[keep])


def _merge_state(sa: P.StateOptions | None, sb: P.StateOptions | None) -> P.StateOptions | None:
    if sa is None and sb is None:
        return None
    sa, sb = sa or P.StateOptions(), sb or P.StateOptions()
    return replace(sa, **{k: v for k, v in vars(sb).items() if v is not None})


def _merge_features(a: P.ControlRequest, b: P.ControlRequest) -> dict[str, Any]:
    """``features``, ``features_add`` and ``features_remove`` of ``a`` then ``b``."""
    if b.features is not None:
        return {"features": b.features, "features_add": b.features_add, "features_remove": b.features_remove}
    add_a, rem_a = set(a.features_add or ()), set(a.features_remove or ())
    add_b, rem_b = set(b.features_add or ()), set(b.features_remove or ())
    add, rem = (add_a - rem_b) | add_b, (rem_a - add_b) | rem_b
    return {
        "features": a.features,
        "features_add": tuple(sorted(add)) or None,
        "features_remove": tuple(sorted(rem)) or None,
    }


def _merge_mesh(va: P.MeshCollider | None, vb: P.MeshCollider | None) -> P.MeshCollider | None:
    """1.8: a rigid move ``vb`` after a new mesh or a re-pose ``va`` moves that one; else b's wins."""
    if va is None or vb is None:
        return vb if vb is not None else va
    if vb.vertices is None and not vb.remove and va.vertices is not None:
        return replace(va, position=vb.position, rotation=vb.rotation)
    return vb


#: requestfields.FIELD_MERGES -> a's and b's values of a field as one ("features": _merge_features).
_MERGES: dict[str, Callable[[Any, Any], Any]] = {
    "pins": _merge_pins,
    "latest": lambda va, vb: vb if vb is not None else va,
    "update": lambda va, vb: {**va, **vb},
    "either": lambda va, vb: va or vb,
    "keywise": _merge_state,
    "mesh": _merge_mesh,
}
assert {f.merge for f in CONTROL_FIELDS} <= {*_MERGES, "features"}, "a control field merges by an unknown rule"


def merge_controls(a: P.ControlRequest, b: P.ControlRequest) -> P.ControlRequest:
    """``a`` then ``b`` as one control: each field merged by its rule (requestfields.CONTROL_FIELDS)."""
    changes: dict[str, Any] = {"rid": b.rid, **_merge_features(a, b)}
    for f in CONTROL_FIELDS:
        if f.merge != "features":
            changes[f.name] = _MERGES[f.merge](getattr(a, f.name), getattr(b, f.name))
    return replace(b, **changes)


class Intake:
    """The bounded command intake of the tick thread (thread-safe)."""

    def __init__(self, max_pending: int) -> None:
        self.max_pending = max_pending
        self._structural: queue.Queue = queue.Queue(max_pending)
        self._lock = threading.Lock()
        self._gens: list[dict[str, ControlSlot]] = [{}]  # this tick's slots, then later ticks' ones
        self._blocks: list[MoveBlock] = []  # moves blocks (1.4), for the next tick, in arrival order
        self._waiting = 0
        self.coalesced = 0  # controls merged into a pending one (cumulative)

    # --- producers ---------------------------------------------------------------------------
    def put(self, cmd: Any, rid: int = 0) -> None:
        """Queue a structural command, or raise Busy."""
        try:
            self._structural.put_nowait(cmd)
        except queue.Full:
            raise P.Busy(P.ERR_BUSY, "server request queue is full, retry later", rid) from None

    def put_call(self, cmd: Call, timeout: float) -> None:
        self._structural.put(cmd, timeout=timeout)

    def put_controls(
        self,
        items: Sequence[tuple[ClothRecord, P.ControlRequest, np.ndarray | None, Any, int | tuple[int, bool]]],
        rid: int = 0,
        moves: MoveBlock | None = None,
    ) -> None:
        """Coalesce controls ``(record, request, packed colliders, waiter, tag)`` into the
        per-cloth slots, all or none (the tag: a batch's item index, or a single control's
        (rid, with features)), and queue the request's ``moves`` block (1.4) with them; raises
        Busy when the waiting replies would exceed the bound."""
        with self._lock:
            n = len(items) + (moves is not None)
            if self._waiting + n > self.max_pending:
                raise P.Busy(P.ERR_BUSY, "server request queue is full, retry later", rid)
            self._waiting += n
            if moves is not None:
                self._queue_block(moves)
            for rec, req, packed, waiter, tag in items:
                g = len(self._gens) - 1
                while g > 0 and rec.id not in self._gens[g]:
                    g -= 1
                slot = self._gens[g].get(rec.id)
                if slot is not None and not mergeable(slot.req, req):
                    g += 1
                    if g == len(self._gens):
                        self._gens.append({})
                    slot = None
                if slot is None:
                    self._gens[g][rec.id] = ControlSlot(rec, req, packed, [(waiter, tag)])
                    continue
                slot.req = merge_controls(slot.req, req)
                if req.colliders is not None:
                    slot.colliders = packed
                slot.waiters.append((waiter, tag))
                slot.merged += 1
                self.coalesced += 1

    # --- the tick thread -----------------------------------------------------------------------
    def take_structural(self) -> list[Any]:
        out = []
        for _ in range(MAX_STRUCTURAL_PER_TICK):
            try:
                out.append(self._structural.get_nowait())
            except queue.Empty:
                break
        return out

    def take_controls(self) -> list[ControlSlot]:
        """This tick's slots (at most one per cloth); later ones move up a tick."""
        with self._lock:
            gen = self._gens.pop(0)
            if not self._gens:
                self._gens.append({})
            slots = list(gen.values())
            self._waiting -= sum(len(s.waiters) for s in slots)
            return slots

    def _queue_block(self, new: MoveBlock) -> None:
        """Queue a moves block; one still waiting with the very same moves (the checker's cached
        handles array of the same client, the same indices) is replaced by it: the game's next
        pin positions supersede the last ones, so a slow tick applies one block per client, not
        every block sent meanwhile (counted as waiting until answered)."""
        for i in range(len(self._blocks) - 1, -1, -1):
            old = self._blocks[i]
            if old.handles is new.handles and np.array_equal(old.indices, new.indices):
                new.superseded.extend(old.superseded)
                new.superseded.append(old.waiter)
                del self._blocks[i]
                break
        self._blocks.append(new)

    def take_moves(self) -> list[MoveBlock]:
        """The moves blocks for this tick, in arrival order (applied after its controls)."""
        with self._lock:
            blocks, self._blocks = self._blocks, []
            self._waiting -= sum(1 + len(b.superseded) for b in blocks)
            return blocks

    def requeue(self, slots: list[ControlSlot]) -> None:
        """Slots taken this tick but not applied (their kernels are being built): first in line
        next tick, before anything that arrived for the same cloths meanwhile."""
        with self._lock:
            front = self._gens[0]
            if any(s.record.id in front for s in slots):
                front = {}
                self._gens.insert(0, front)
            for s in slots:
                front[s.record.id] = s
                self._waiting += len(s.waiters)

    def drain(self) -> tuple[list[Any], list[ControlSlot]]:
        """Everything still queued (shutdown): moves blocks come as structural commands."""
        out = []
        while True:
            try:
                out.append(self._structural.get_nowait())
            except queue.Empty:
                break
        slots: list[ControlSlot] = []
        with self._lock:
            for gen in self._gens:
                slots.extend(gen.values())
            self._gens = [{}]
            out.extend(self._blocks)
            self._blocks = []
            self._waiting = 0
        return out, slots
