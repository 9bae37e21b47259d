"""Drape client SDK: submit cloths to a Drape server over Zenoh and receive their state.

``drape.client.protocol`` (the wire protocol) needs numpy and msgpack only; the SDK classes
(DrapeClient, ClothHandle, in ``drape.client.sdk``) and the Zenoh configuration shared with the
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
    from .sdk import BatchError, ClothHandle, ControlBatch, DrapeClient
    from .session import zenoh_config

_SDK = ("BatchError", "ClothHandle", "ControlBatch", "DrapeClient")


def __getattr__(name: str) -> Any:
    if name in _SDK:
        from . import sdk

        return getattr(sdk, name)
    if name == "zenoh_config":
        from .session import zenoh_config

        return zenoh_config
    raise AttributeError(f"module 'drape.client' has no attribute {name!r}")


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
