"""What a tick publishes: the :class:`Roster`, plain data handed to ``World.fetch_async``.

Each cloth of a frame layout (frame order) with its id, its state key, its encoding and whether
its state carries normals; the cloths published on their own key (``singles``) and the bundles
(one per client that bundles, protocol 1.4). The service's tick thread builds one only when
cloths come, go or change how they are published (``version``), so per tick the World and the
publisher work per *publication* (a state or a bundle), never per cloth in Python.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field
from operator import attrgetter
from typing import Protocol

import numpy as np

from drape.client import protocol as P


class Published(Protocol):
    """What a roster reads of a cloth (the service's ClothRecord)."""

    id: str
    key: str
    encoding: str  # a protocol encoding name
    step: float
    bundle_key: str | None


@dataclass(eq=False)
class Roster:
    """How each cloth of a frame layout is published (frame order)."""

    version: tuple[int, int]  # (layout version, publication changes)
    ids: list[str]
    keys: list[str]
    encodings: list[int]  # protocol ids
    normals: np.ndarray  # (k,) bool
    singles: np.ndarray  # frame indices published on their own key
    bundles: list[tuple[str, np.ndarray]]  # (bundle key, frame indices)
    steps: list[float] = field(default_factory=list)  # 1.5, predictive cloths' grid steps (metres)
    _pubs: list[tuple[str, str, list[int], bool]] | None = None

    @classmethod
    def of(cls, version: tuple[int, int], records: Sequence[Published], normals: np.ndarray) -> Roster:
        """The roster of ``records`` in frame order (``normals`` (k,) bool, the layout's): one
        pass per field, bundles in the order of their first cloth."""
        ids = list(map(attrgetter("id"), records))
        bundles: dict[str, list[int]] = {}
        singles: list[int] = []
        for i, bk in enumerate(map(attrgetter("bundle_key"), records)):
            (bundles.setdefault(bk, []) if bk else singles).append(i)
        return cls(
            version,
            ids,
            list(map(attrgetter("key"), records)),
            list(map(P.ENCODING_IDS.__getitem__, map(attrgetter("encoding"), records))),
            normals.copy(),
            np.array(singles, np.int64),
            [(k, np.array(v, np.int64)) for k, v in bundles.items()],
            list(map(attrgetter("step"), records)),
        )

    @property
    def predictive(self) -> bool:
        """Whether a cloth of this roster is published with the predictive encoding (1.5): its
        states are coded against streams (statecodec.PredictiveStreams on the host path,
        opencl/devstreams.DeviceStreams on the device's)."""
        return P.ENC_PREDICTIVE in self.encodings

    def publications(self) -> list[tuple[str, str, list[int], bool]]:
        """(publisher ident: cloth id or bundle key, key, frame indices, bundle) per payload:
        the singles, then the bundles (the device-encoded frame's publication order)."""
        if self._pubs is None:
            self._pubs = [(self.ids[i], self.keys[i], [i], False) for i in self.singles.tolist()] + [
                (k, k, idx.tolist(), True) for k, idx in self.bundles
            ]
        return self._pubs
