"""The service's only fabric cache: fabrics by a digest of the submission's geometry, shared by
every cloth of the same geometry (so the World's device arena holds each once), reference
counted, and the last ``RETAIN`` unused ones kept for resubmissions, at most ``RETAIN_BYTES`` of
them (a 32k-vertex mesh's fabric, with its tethers and long-range links, is tens of MB: kept, it
was memory a removed mesh never gave back, issue 26). The cook thread acquires (cooking what is
new, :func:`cook_fabric`), the tick thread releases when a cloth goes; the store is lock-protected."""

from __future__ import annotations

import hashlib
import threading
from collections import OrderedDict
from collections.abc import Callable

import numpy as np

from drape.client import protocol as P

from ...sim.fabric import Fabric, cook_grid, cook_mesh
from ...sim.params import LinkOptions

RETAIN = 64  # unused fabrics kept for resubmission
RETAIN_BYTES = 16 << 20  # ... of at most this many bytes of arrays together


def fabric_bytes(f: Fabric) -> int:
    """The bytes of a fabric's arrays, its tethers and long-range links included once computed."""
    arrays = [v for v in vars(f).values() if isinstance(v, np.ndarray)]
    arrays += [a for a in (*f._tethers, *f._long_range) if isinstance(a, np.ndarray)]
    return sum(a.nbytes for a in arrays)


class FabricStore:
    """Cooked fabrics by request digest, reference counted (thread-safe)."""

    def __init__(self, retain: int = RETAIN, retain_bytes: int = RETAIN_BYTES) -> None:
        self._lock = threading.Lock()
        self._live: dict[str, tuple[Fabric, int]] = {}
        self._spare: OrderedDict[str, Fabric] = OrderedDict()
        self._spare_bytes: dict[str, int] = {}
        self._digest: dict[int, str] = {}  # id(fabric) -> digest
        self.retain, self.retain_bytes = retain, retain_bytes
        self.cooked = 0  # fabrics cooked (not found live or spare)

    @staticmethod
    def digest(req: P.SubmitRequest, links: LinkOptions, pinned: np.ndarray) -> str:
        h = hashlib.sha1()
        h.update(repr((req.grid, links)).encode())
        h.update(pinned.tobytes())
        if req.mesh is not None:
            h.update(req.mesh.vertices.tobytes())
            h.update(req.mesh.triangles.tobytes())
        return h.hexdigest()

    def acquire(self, key: str, cook: Callable[[], Fabric]) -> Fabric:
        with self._lock:
            have = self._live.get(key)
            if have is not None:
                self._live[key] = (have[0], have[1] + 1)
                return have[0]
            fab = self._spare.pop(key, None)
            self._spare_bytes.pop(key, None)
        if fab is None:
            fab = cook()  # outside the lock: cooking a big mesh takes a while
            with self._lock:
                self.cooked += 1
        with self._lock:
            have = self._live.get(key)
            if have is not None:  # cooked twice at once: keep the first
                self._live[key] = (have[0], have[1] + 1)
                return have[0]
            self._live[key] = (fab, 1)
            self._digest[id(fab)] = key
            return fab

    def release(self, fabric: Fabric) -> None:
        with self._lock:
            key = self._digest.get(id(fabric))
            have = self._live.get(key) if key is not None else None
            if have is None:
                return
            if have[1] > 1:
                self._live[key] = (have[0], have[1] - 1)  # type: ignore[index]
                return
            del self._live[key]  # type: ignore[arg-type]
            del self._digest[id(fabric)]
            size = fabric_bytes(fabric)
            if size > self.retain_bytes:  # not kept at the cost of every smaller one
                return
            self._spare[key] = fabric  # type: ignore[index]
            self._spare_bytes[key] = size  # type: ignore[index]
            while len(self._spare) > self.retain or sum(self._spare_bytes.values()) > self.retain_bytes:
                self._spare_bytes.pop(self._spare.popitem(last=False)[0], None)

    @property
    def spare_bytes(self) -> int:
        with self._lock:
            return sum(self._spare_bytes.values())

    def __len__(self) -> int:
        return len(self._live)


def cook_fabric(req: P.SubmitRequest, links: LinkOptions, pinned: np.ndarray) -> Fabric:
    if req.grid is not None:
        g = req.grid
        return cook_grid(g.cols, g.rows, g.width, g.height, links, pinned.tolist(), g.orientation, g.origin)
    assert req.mesh is not None
    return cook_mesh(req.mesh.vertices.astype(np.float64), req.mesh.triangles.astype(np.int64), links, pinned.tolist())
