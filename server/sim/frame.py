"""The contiguous Frame a World's step is read back into: every cloth's positions (and normals)
back to back in one (N, 3) float32 host array, its Layout (where each cloth's rows are), the
pooled host buffers frames are read into (reused, at least the last two kept intact, a held one
never), and the PendingFrame of a readback still in flight. world.py re-exports these names."""

from __future__ import annotations

from collections.abc import Callable, Iterator, Mapping
from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True, eq=False)
class Layout:
    """Where each cloth sits in a frame; rebuilt only when cloths come, go or switch normals."""

    version: int
    handles: np.ndarray  # (k,) int64, frame order
    offsets: np.ndarray  # (k + 1,) int64 row offsets
    normals: np.ndarray  # (k,) bool: the cloth's state carries normals
    index: Mapping[int, int]  # handle -> frame index

    @property
    def n_rows(self) -> int:
        return int(self.offsets[-1])


class HostBuffer:
    """One reusable host array pair (positions, normals) a frame is read back into."""

    def __init__(self, alloc: Callable[[int], np.ndarray]) -> None:
        self._alloc = alloc
        self.xyz = np.zeros((0, 3), np.float32)
        self.nrm = np.zeros((0, 3), np.float32)
        self.held = False

    def ensure(self, rows: int, normals: bool) -> None:
        if len(self.xyz) < rows:
            self.xyz = self._alloc(max(rows, 2 * len(self.xyz)))
        if normals and len(self.nrm) < rows:
            self.nrm = self._alloc(max(rows, 2 * len(self.nrm)))


class FramePool:
    """Host buffers for frames: the least recently used one not held and not among the last
    two handed out is reused; a new one is made only while more are held (bounded by the
    consumer, e.g. the service's publisher holds at most two)."""

    def __init__(self, alloc: Callable[[int], np.ndarray] | None = None) -> None:
        self.alloc = alloc or (lambda rows: np.zeros((rows, 3), np.float32))
        self.buffers: list[HostBuffer] = []

    def acquire(self, rows: int, normals: bool) -> HostBuffer:
        recent = self.buffers[-2:]
        buf = next((b for b in self.buffers if not b.held and b not in recent), None)
        if buf is None:
            buf = HostBuffer(self.alloc)
        else:
            self.buffers.remove(buf)
        self.buffers.append(buf)  # most recently used last
        buf.ensure(rows, normals)
        return buf


class _Rows(Mapping):
    """``frame.positions[h]`` / ``frame.normals[h]``: views of the frame's contiguous rows."""

    def __init__(self, frame: Frame, data: np.ndarray | None, mask: np.ndarray | None) -> None:
        self._f, self._data, self._mask = frame, data, mask

    def _i(self, handle: int) -> int:
        i = self._f.layout.index.get(handle)
        if i is None or self._data is None or (self._mask is not None and not self._mask[i]):
            raise KeyError(handle)
        return i

    def __getitem__(self, handle: int) -> np.ndarray:
        i = self._i(handle)
        off = self._f.layout.offsets
        return self._data[off[i] : off[i + 1]]  # type: ignore[index]

    def __contains__(self, handle: object) -> bool:
        try:
            self._i(handle)  # type: ignore[arg-type]
            return True
        except KeyError:
            return False

    def __iter__(self) -> Iterator[int]:
        hs = self._f.layout.handles
        if self._data is None:
            return iter(())
        return iter(hs.tolist() if self._mask is None else hs[self._mask].tolist())

    def __len__(self) -> int:
        if self._data is None:
            return 0
        return len(self._f.layout.handles) if self._mask is None else int(self._mask.sum())


class Frame:
    """Host copy of every cloth's state after a step: ``xyz`` (N, 3) float32, C-contiguous,
    cloth ``i`` (``layout.handles[i]``) in rows ``layout.offsets[i]:layout.offsets[i + 1]``;
    ``nxyz`` the same for normals (rows of cloths without normals are unspecified), or None.
    ``positions[h]`` / ``normals[h]`` are views of those rows by handle."""

    def __init__(
        self, step: int, layout: Layout, xyz: np.ndarray, nxyz: np.ndarray | None, buffer: HostBuffer | None = None
    ) -> None:
        self.step = step
        self.layout = layout
        self.xyz = xyz
        self.nxyz = nxyz
        self._buffer = buffer

    @property
    def handles(self) -> np.ndarray:
        return self.layout.handles

    @property
    def offsets(self) -> np.ndarray:
        return self.layout.offsets

    @property
    def positions(self) -> Mapping[int, np.ndarray]:
        return _Rows(self, self.xyz, None)

    @property
    def normals(self) -> Mapping[int, np.ndarray]:
        return _Rows(self, self.nxyz, self.layout.normals)

    def rows(self, handle: int) -> slice:
        i = self.layout.index[handle]
        return slice(int(self.layout.offsets[i]), int(self.layout.offsets[i + 1]))

    def finite(self, handle: int) -> bool:
        return bool(np.isfinite(self.positions[handle]).all())

    def nonfinite(self) -> np.ndarray:
        """Frame indices of the cloths with a non-finite position (or normal, where they carry
        normals): one pass over the frame, a reduceat only when something is wrong."""
        lay = self.layout
        if not len(lay.handles):
            return np.zeros(0, np.int64)
        bad = np.zeros(len(lay.handles), bool)
        for data, mask in ((self.xyz, None), (self.nxyz if lay.normals.any() else None, lay.normals)):
            if data is None:
                continue
            ok = np.isfinite(data)
            if ok.all():
                continue
            rows_ok = ok.all(axis=1)
            cloth_ok = np.logical_and.reduceat(rows_ok, lay.offsets[:-1])
            bad |= ~cloth_ok if mask is None else (~cloth_ok & mask)
        return np.flatnonzero(bad)

    def hold(self) -> Frame:
        """Keep this frame's buffer from being reused until ``release``."""
        if self._buffer is not None:
            self._buffer.held = True
        return self

    def release(self) -> None:
        if self._buffer is not None:
            self._buffer.held = False
            self._buffer = None


class PendingFrame:
    """A frame whose readback may still be in flight: ``wait()`` returns it."""

    def __init__(
        self, frame: Frame, wait: Callable[[], None] | None = None, device_s: Callable[[], float | None] | None = None
    ) -> None:
        self._frame, self._wait, self._device_s = frame, wait, device_s

    def wait(self) -> Frame:
        if self._wait is not None:
            self._wait()
            self._wait = None
        return self._frame

    @property
    def device_s(self) -> float | None:
        """Device time from the start of the step to the end of the readback (after wait)."""
        return self._device_s() if self._device_s is not None else None
