"""DrapeClient's controls of many cloths at once (a mixin of :class:`drape.client.sdk.DrapeClient`):
``batch()`` (protocol 1.1 batch control, :class:`.controls.ControlBatch`) and ``move_pins_many``
(one 1.4 ``moves`` block when it can, :mod:`.moves`), the path both take to the servers
(``_send_controls``, :mod:`.sending`) and what a server's version allows of them (its batch size,
features deltas).
"""

from __future__ import annotations

from collections.abc import Iterable, Sequence
from typing import TYPE_CHECKING, Any, cast

import numpy as np

from . import protocol as P
from .controls import ControlBatch, ErrorCallback
from .protocol import DrapeError
from .sending import send_controls

if TYPE_CHECKING:
    from .handle import ClothHandle
    from .sdk import DrapeClient


class BatchingMixin:
    """DrapeClient's methods for controls of many cloths (its session, servers and requests are in
    sdk.py). Their ``self`` is the DrapeClient they are mixed into: mypy wants a mixin's self type
    to be a supertype of the mixin, hence each ``type: ignore[misc]``."""

    def batch(  # type: ignore[misc]
        self: DrapeClient, *, wait: bool = False, on_error: ErrorCallback | None = None, timeout: float | None = None
    ) -> ControlBatch:
        """Collect controls of many of this client's cloths and send them as one batch control
        request when the ``with`` block ends (or on ``send()``): the per-tick call of a game
        loop with many cloths. ``wait=False``: the reply is not waited for; refused items are
        counted in ``send_errors`` and handed to ``on_error``. ``wait=True``: ``results`` holds
        each item's first tick, and BatchError is raised if any item was refused."""
        return ControlBatch(self, wait=wait, on_error=on_error, timeout=timeout)

    def move_pins_many(  # type: ignore[misc]
        self: DrapeClient,
        handles: Sequence[ClothHandle],
        indices: Sequence[int] | np.ndarray | Sequence[Sequence[int]],
        targets: Sequence[Any] | np.ndarray,
        *,
        colliders: Sequence[Sequence[Any] | None] | None = None,
        wait: bool = False,
        on_error: ErrorCallback | None = None,
    ) -> list[int | DrapeError] | None:
        """Move the pins of many cloths in one message: ``indices`` the same for every cloth
        (a sequence of ints) or one sequence per cloth; ``targets[j]`` the (k, 3) targets of
        ``handles[j]`` (one (n, k, 3) array is best); ``colliders[j]`` (optional) the colliders of
        ``handles[j]`` (None: unchanged). Shared indices and no colliders, to a 1.4 server: one
        ``moves`` block (PROTOCOL.md 5.1.1), with no Python loop over the cloths (client/moves.py).
        ``wait=True``: each cloth's first tick; BatchError (with every outcome) if any was refused."""
        if len(targets) != len(handles):
            raise ValueError(f"{len(handles)} cloths but {len(targets)} target arrays")
        try:
            shared = np.asarray(indices).ndim == 1  # one index list for every cloth
        except ValueError:  # ragged: one list per cloth
            shared = False
        if shared and colliders is None:
            from .moves import moves_of

            return moves_of(self).send(handles, np.asarray(indices), np.asarray(targets), wait, on_error)
        b = self.batch(wait=wait, on_error=on_error)
        for j, h in enumerate(handles):
            idx = cast("Sequence[int] | np.ndarray", indices if shared else indices[j])
            b.move_pins(h, idx, targets[j], colliders=None if colliders is None else colliders[j])
        return b.send()

    def _server_batch_limit(self: DrapeClient) -> int:  # type: ignore[misc]
        """Items per batch request the server takes; 0 when it speaks 1.0 (no batch control)."""
        if self.server_version < (1, 1):
            return 0
        return max(1, self._max_batch_items)

    def _require_features_delta(self: DrapeClient, reqs: Iterable[P.ControlRequest]) -> None:  # type: ignore[misc]
        """features_add / features_remove need a 1.2 server: an older one ignores unknown keys, so
        the change would be silently lost. Raises ProtocolError before anything is sent."""
        if any(r.features_add is not None or r.features_remove is not None for r in reqs) and self.server_version < (
            1,
            2,
        ):
            raise P.ProtocolError(
                P.ERR_INVALID_VALUE,
                "features_add / features_remove need a protocol 1.2 server; "
                f"this one speaks {self.server_version[0]}.{self.server_version[1]}: send the "
                "whole set with features= instead",
            )

    def _send_controls(  # type: ignore[misc]
        self: DrapeClient,
        items: list[tuple[ClothHandle, P.ControlRequest]],
        wait: bool,
        on_error: ErrorCallback | None,
        timeout: float | None,
    ) -> list[int | DrapeError] | None:
        """Send controls of this client's cloths (client/sending.py)."""
        return send_controls(self, items, wait, on_error, timeout)
