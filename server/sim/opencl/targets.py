"""The OpenCL world's pin targets (a mixin of CLWorld): every target sent before a step is
gathered on the host and scattered on the device in one upload and one launch.

``set_pin_targets`` and its many/block forms only append (rows, targets) to a pending list;
``_upload_targets`` (called by the world's flush before a step, and before a reset or a removal
so no target lands in a reused range) keeps, of a row given several, only the latest, writes
one index and one value array and launches ``scatter_targets`` once.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

from .buffers import DevArray

if TYPE_CHECKING:
    from ..world import Cloth
    from .buffers import RangeAllocator
    from .clworld import ClothSlot
    from .device import Device


class PinTargets:
    """Needs ``dev``, ``rec`` (handle -> slot with ``vbase``), ``vert`` (the vertex allocator),
    ``target`` and ``_base_options`` from the world."""

    # declared for the type checker only (CLWorld.__init__ sets them)
    dev: Device
    rec: dict[int, ClothSlot]
    vert: RangeAllocator
    target: DevArray
    _base_options: list[str]

    def _init_targets(self) -> None:
        q = self.dev
        self._pending_targets: list[tuple[np.ndarray, np.ndarray]] = []
        self._vbase_of = np.full(64, -1, np.int64)  # by handle: set_pin_targets_block's rows
        self._seen = np.zeros(0, bool)  # _upload_targets: rows already given a later target
        self._scatter_idx = DevArray(q, np.int32, 1, 1024)
        self._scatter_val = DevArray(q, np.float32, 4, 1024)

    def _note_vbase(self, handle: int, vbase: int) -> None:
        """A cloth's first vertex row (-1: removed), for the block form's vectorised rows."""
        if handle >= len(self._vbase_of):
            grown = np.full(max(handle + 1, 2 * len(self._vbase_of)), -1, np.int64)
            grown[: len(self._vbase_of)] = self._vbase_of
            self._vbase_of = grown
        self._vbase_of[handle] = vbase

    def _set_targets(self, cloth: Cloth, idx: np.ndarray, targets: np.ndarray) -> None:
        # gathered and scattered on the device in one launch before the next step (_flush)
        if len(idx):
            self._pending_targets.append((idx + self.rec[cloth.handle].vbase, targets))

    def _set_targets_many(self, handles: list[int], indices: list[np.ndarray], targets: list[np.ndarray]) -> None:
        rec = self.rec
        vb = np.fromiter((rec[h].vbase for h in handles), np.int64, len(handles))
        counts = np.fromiter((len(i) for i in indices), np.int64, len(indices))
        rows = np.concatenate(indices).astype(np.int64) + np.repeat(vb, counts)
        self._pending_targets.append((rows, np.concatenate(targets).reshape(-1, 3)))

    def _set_targets_block(self, handles: np.ndarray, idx: np.ndarray, targets: np.ndarray) -> None:
        rows = (self._vbase_of[handles][:, None] + idx[None, :]).reshape(-1)
        self._pending_targets.append((rows, targets.reshape(-1, 3)))

    def _latest_targets(self) -> list[tuple[np.ndarray, np.ndarray]]:
        """The pending targets with, of a row given several, only the last (later calls win:
        the device's scatter has no order). Entries newest first, one mask over the rows."""
        pending = self._pending_targets
        if len(pending) < 2:
            return pending
        if len(self._seen) < self.vert.capacity:
            self._seen = np.zeros(self.vert.capacity, bool)
        seen, out = self._seen, []
        for rows, t in reversed(pending):
            fresh = ~seen[rows]
            seen[rows] = True
            out.append((rows, t) if fresh.all() else (rows[fresh], np.asarray(t).reshape(-1, 3)[fresh]))
        for rows, _ in pending:
            seen[rows] = False
        return out

    def _upload_targets(self) -> None:
        latest = self._latest_targets()
        idx = np.concatenate([i for i, _ in latest]).astype(np.int32)
        val = np.zeros((len(idx), 4), np.float32)
        val[:, :3] = np.concatenate([np.asarray(t).reshape(-1, 3) for _, t in latest])
        self._pending_targets.clear()
        if not len(idx):
            return
        if self._scatter_idx.capacity < len(idx):
            self._scatter_idx.resize(2 * len(idx))
            self._scatter_val.resize(2 * len(idx))
        self._scatter_idx.write(0, idx)
        self._scatter_val.write(0, val)
        k = self.dev.kernel(self._base_options, "scatter_targets")
        n = len(idx)
        k(
            self.dev.queue,
            (-(-n // 64) * 64,),
            (64,),
            np.int32(n),
            self._scatter_idx.buf,
            self._scatter_val.buf,
            self.target.buf,
        )
