"""The tick path's device-encoded frames (config ``device_encode``, OpenCL worlds only).

Per tick, right after the step and on the same queue (no host round trip), one launch of
drape.server.sim.opencl.encode's ``encode_frame`` writes every publication's bytes (states and
bundles exactly as drape.client.protocol encodes them) into one packed device buffer, and one
copy brings it into pinned host memory. The :class:`~drape.server.sim.opencl.encode.FramePlan`
is rebuilt only when the publication roster changes (cloths come or go, change encoding,
normals or bundling: ``Roster.version``). The publisher then puts each publication's slice.

Non-finite cloths show as non-finite bounds in their headers (``DeviceEncoder.nonfinite``);
the tick thread resets them in the World and :meth:`DeviceFrames.reencode` writes the frame
again with their rest pose and the reset flag: the same bytes the host path publishes.
"""

from __future__ import annotations

import logging
import time

import numpy as np

from ..sim.fabric import Fabric
from ..sim.opencl.clworld import CLWorld
from ..sim.opencl.encode import ClothEntry, DeviceEncoder, EncodedFrame, FramePlan, Publication
from ..sim.opencl.frames import device_span
from ..sim.shared import vertex_normals
from ..sim.world import Frame, Layout, PendingFrame, World
from .publisher import Roster

log = logging.getLogger(__name__)


def device_world(world: World | None, enabled: bool) -> CLWorld | None:
    """The world when its frames are to be encoded on the device."""
    return world if enabled and isinstance(world, CLWorld) else None


class DeviceFrames:
    """One OpenCL world's encoder on the tick path."""

    def __init__(self, world: CLWorld) -> None:
        self.world = world
        self.encoder = DeviceEncoder(world.dev, stride=4)
        self._plan_version: tuple[int, int] | None = None
        self.plans = 0  # plans built (the tests count them)

    def _plan(self, roster: Roster, lay: Layout) -> None:
        if self._plan_version == roster.version and self.encoder.plan is not None:
            return
        w = self.world
        counts = np.diff(lay.offsets).tolist()
        cloths = [
            ClothEntry(cid, w.rec[h].vbase, n, enc, bool(nr))
            for cid, h, n, enc, nr in zip(
                roster.ids, lay.handles.tolist(), counts, roster.encodings, roster.normals.tolist(), strict=True
            )
        ]
        pubs = [Publication(key, tuple(idx), bundle) for _, key, idx, bundle in roster.publications()]
        self.encoder.set_plan(FramePlan.build(cloths, pubs))
        self._plan_version = roster.version
        self.plans += 1

    def encode(self, roster: Roster, lay: Layout, tick: int, time_ns: int, flags: np.ndarray) -> PendingFrame:
        """Enqueue this tick's frame right behind the step; ``wait()`` gives a Frame of the
        layout without host rows (the bytes are in :meth:`hold`)."""
        w = self.world
        self._plan(roster, lay)
        ev = self.encoder.encode(w.dev.queue, w.pos.buf, w.nrm.buf, tick, time_ns, flags)
        frame = Frame(w.steps, lay, np.zeros((0, 3), np.float32), None)
        return PendingFrame(frame, ev.wait, device_span(w._step_marker, ev))

    def hold(self) -> EncodedFrame:
        return self.encoder.hold()

    def nonfinite(self) -> np.ndarray:
        """Frame indices of the cloths whose last encoded positions were not finite."""
        return self.encoder.nonfinite()

    def reencode(
        self, old: EncodedFrame, tick: int, time_ns: int, flags: np.ndarray, reset: list[tuple[int, Fabric]]
    ) -> EncodedFrame:
        """The frame encoded again after the World reset some cloths (``reset``: (handle,
        fabric) of those carrying normals, whose rest normals are written first)."""
        w = self.world
        for h, fabric in reset:
            n = fabric.n_vertices
            nrm = np.zeros((n, 4), np.float32)
            nrm[:, :3] = vertex_normals(fabric.rest_positions, fabric)[0]
            w.nrm.write(w.rec[h].vbase, nrm)
        old.release()
        t = time.perf_counter()
        self.encoder.encode(w.dev.queue, w.pos.buf, w.nrm.buf, tick, time_ns, flags).wait()
        log.debug("frame of tick %d encoded again after resets in %.3f ms", tick, 1e3 * (time.perf_counter() - t))
        return self.encoder.hold()

    def close(self) -> None:
        self.encoder.close()
