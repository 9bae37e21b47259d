"""Drape client SDK: submit cloths to a Drape server over Zenoh and receive their state.

``drape.client.protocol`` (the wire protocol) needs numpy and msgpack only; the SDK classes
(DrapeClient in ``drape.client.sdk``, the facade over the SDK's layers; ClothHandle, ControlBatch,
BatchError in the modules of their layers) and the Zenoh configuration shared with the
server (``zenoh_config``, in ``drape.client.session``) add Zenoh and are imported on first use, so
a tool that only encodes or decodes messages does not need Zenoh installed. Nothing here imports
drape.server or OpenCL.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

from .protocol import (
    PROTOCOL_VERSION,
    Busy,
    Capsule,
    ClothState,
    DrapeError,
    Forbidden,
    InternalError,
    LimitExceeded,
    LinkSpec,
    NotFound,
    Overloaded,
    Plane,
    ProtocolError,
    Sphere,
    Unavailable,
)

if TYPE_CHECKING:
    from .batching import ControlBatch
    from .controls import BatchError
    from .handle import ClothHandle
    from .sdk import DrapeClient
    from .session import zenoh_config

# the names imported on first use (they need Zenoh), and the module of each
_LAZY = {
    "BatchError": "controls",
    "ClothHandle": "handle",
    "ControlBatch": "batching",
    "DrapeClient": "sdk",
    "zenoh_config": "session",
}


def __getattr__(name: str) -> Any:
    module = _LAZY.get(name)
    if module is None:
        raise AttributeError(f"module 'drape.client' has no attribute {name!r}")
    from importlib import import_module

    return getattr(import_module(f".{module}", __name__), name)


__all__ = [
    "PROTOCOL_VERSION",
    "BatchError",
    "Busy",
    "Capsule",
    "ClothHandle",
    "ClothState",
    "ControlBatch",
    "DrapeClient",
    "DrapeError",
    "Forbidden",
    "InternalError",
    "LimitExceeded",
    "LinkSpec",
    "NotFound",
    "Overloaded",
    "Plane",
    "ProtocolError",
    "Sphere",
    "Unavailable",
    "zenoh_config",
]
