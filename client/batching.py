"""A batch of many of one client's cloths' controls (:class:`ControlBatch`, protocol 1.1,
``DrapeClient.batch()``): collected with the ClothHandle methods' arguments, sent once through the
client's sending path (:class:`~.sending.ControlSender`, which picks the wire form by the cloths'
servers' versions)."""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any, Unpack

import numpy as np

from . import protocol as P
from .connection import ErrorCallback
from .controls import BatchError, SetOptions, collider, pin_changes, set_changes
from .handle import ClothHandle
from .protocol import DrapeError
from .sending import ControlSender


class ControlBatch:
    """Controls of many of one client's cloths, sent as one batch control request (protocol
    1.1; to a 1.0 server as one control each). Use as a context manager (sent when the block
    ends without an exception) or call ``send()``. Every method takes the ClothHandle first
    and the same arguments as the ClothHandle method of the same name."""

    def __init__(
        self,
        sender: ControlSender,
        owner: object,
        *,
        wait: bool = False,
        on_error: ErrorCallback | None = None,
        timeout: float | None = None,
    ) -> None:
        self.sender = sender
        self.owner = owner  # the client whose cloths it takes
        self.wait = wait
        self.on_error = on_error
        self.timeout = timeout
        self.items: list[tuple[ClothHandle, P.ControlRequest]] = []
        self.results: list[int | DrapeError] | None = None
        self.sent = False

    def __len__(self) -> int:
        return len(self.items)

    def add(self, handle: ClothHandle, **changes: Any) -> ControlBatch:
        """Any ControlRequest fields for ``handle``."""
        if handle.client is not self.owner:
            raise ValueError(f"cloth {handle.id} belongs to another DrapeClient")
        handle.check_open()
        handle.note_controls(changes)
        self.items.append((handle, P.ControlRequest(handle.id, handle.token, **changes)))
        return self

    def move_pins(
        self,
        handle: ClothHandle,
        indices: Sequence[int] | np.ndarray,
        targets: Sequence[Sequence[float]] | np.ndarray,
        *,
        colliders: Sequence[Any] | None = None,
    ) -> ControlBatch:
        return self.add(handle, **pin_changes(indices, targets, colliders))

    def set_colliders(self, handle: ClothHandle, colliders: Sequence[Any]) -> ControlBatch:
        return self.add(handle, colliders=tuple(collider(c) for c in colliders))

    def set(self, handle: ClothHandle, **options: Unpack[SetOptions]) -> ControlBatch:
        """As ClothHandle.set, for one item of the batch (``features_add`` / ``features_remove``: 1.2)."""
        return self.add(handle, **set_changes(**options))

    def reset(self, handle: ClothHandle) -> ControlBatch:
        return self.add(handle, reset=True)

    def send(self) -> list[int | DrapeError] | None:
        """Send the collected items (once). ``wait=True``: returns each item's first tick, raising
        BatchError (with every item's outcome) if any was refused; otherwise None."""
        if self.sent:
            raise RuntimeError("this batch was already sent")
        self.sent = True
        results = self.sender.controls(self.items, self.wait, self.on_error, self.timeout)
        self.results = results
        if results is not None and any(isinstance(r, DrapeError) for r in results):
            raise BatchError(results)
        return results

    def __enter__(self) -> ControlBatch:
        return self

    def __exit__(self, exc_type: Any, *exc: object) -> None:
        if exc_type is None and not self.sent:
            self.send()


__all__ = ["ControlBatch"]
