"""The OpenCL world's pin targets (a part the CLWorld owns): every target sent before a step is
gathered on the host and scattered on the device in one upload and one launch.

``set_pin_targets`` and its many/block forms only append (rows, targets) to a pending list;
:meth:`PinTargets.upload` (called by the world's flush before a step, and before a reset or a
removal so no target lands in a reused range) keeps, of a row given several, only the latest,
writes one index and one value array and launches ``scatter_targets`` once.
"""

from __future__ import annotations

import numpy as np

from .buffers import ClothSlot, DevArray, DeviceMemory
from .device import Device


class PinTargets:
    """The pending targets of the next step, uploaded and scattered into ``mem.target`` at once."""

    def __init__(self, dev: Device, mem: DeviceMemory, rec: dict[int, ClothSlot], base_options: list[str]) -> None:
        self.dev, self.mem, self.rec, self.base_options = dev, mem, rec, base_options
        self.pending: list[tuple[np.ndarray, np.ndarray]] = []
        self._vbase_of = np.full(64, -1, np.int64)  # by handle: set_pin_targets_block's rows
        self._seen = np.zeros(0, bool)  # upload: rows already given a later target
        self._scatter_idx = DevArray(dev, np.int32, 1, 1024)
        self._scatter_val = DevArray(dev, np.float32, 4, 1024)

    def note_vbase(self, handle: int, vbase: int) -> None:
        """A cloth's first vertex row (-1: removed), for the block form's vectorised rows."""
        if handle >= len(self._vbase_of):
            grown = np.full(max(handle + 1, 2 * len(self._vbase_of)), -1, np.int64)
            grown[: len(self._vbase_of)] = self._vbase_of
            self._vbase_of = grown
        self._vbase_of[handle] = vbase

    def add(self, handle: int, idx: np.ndarray, targets: np.ndarray) -> None:
        # gathered and scattered on the device in one launch before the next step (the world's flush)
        if len(idx):
            self.pending.append((idx + self.rec[handle].vbase, targets))

    def add_many(self, handles: list[int], indices: list[np.ndarray], targets: list[np.ndarray]) -> None:
        rec = self.rec
        vb = np.fromiter((rec[h].vbase for h in handles), np.int64, len(handles))
        counts = np.fromiter((len(i) for i in indices), np.int64, len(indices))
        rows = np.concatenate(indices).astype(np.int64) + np.repeat(vb, counts)
        self.pending.append((rows, np.concatenate(targets).reshape(-1, 3)))

    def add_block(self, handles: np.ndarray, idx: np.ndarray, targets: np.ndarray) -> None:
        rows = (self._vbase_of[handles][:, None] + idx[None, :]).reshape(-1)
        self.pending.append((rows, targets.reshape(-1, 3)))

    def _latest_targets(self) -> list[tuple[np.ndarray, np.ndarray]]:
        """The pending targets with, of a row given several, only the last (later calls win:
        the device's scatter has no order). Entries newest first, one mask over the rows."""
        pending = self.pending
        if len(pending) < 2:
            return pending
        if len(self._seen) < self.mem.vert.capacity:
            self._seen = np.zeros(self.mem.vert.capacity, bool)
        seen, out = self._seen, []
        for rows, t in reversed(pending):
            fresh = ~seen[rows]
            seen[rows] = True
            out.append((rows, t) if fresh.all() else (rows[fresh], np.asarray(t).reshape(-1, 3)[fresh]))
        for rows, _ in pending:
            seen[rows] = False
        return out

    def upload(self) -> None:
        latest = self._latest_targets()
        idx = np.concatenate([i for i, _ in latest]).astype(np.int32)
        val = np.zeros((len(idx), 4), np.float32)
        val[:, :3] = np.concatenate([np.asarray(t).reshape(-1, 3) for _, t in latest])
        self.pending.clear()
        if not len(idx):
            return
        if self._scatter_idx.capacity < len(idx):
            self._scatter_idx.resize(2 * len(idx))
            self._scatter_val.resize(2 * len(idx))
        self._scatter_idx.write(0, idx, blocking=False)
        self._scatter_val.write(0, val, blocking=False)
        k = self.dev.kernel(self.base_options, "scatter_targets")
        n = len(idx)
        k(
            self.dev.queue,
            (-(-n // 64) * 64,),
            (64,),
            np.int32(n),
            self._scatter_idx.buf,
            self._scatter_val.buf,
            self.mem.target.buf,
        )
