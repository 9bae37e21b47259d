"""Drape client SDK: submit cloths to a Drape server over Zenoh and receive their state.

Imports numpy, msgpack and Zenoh only (never drape.server or OpenCL). The wire protocol itself
is drape.client.protocol (numpy + msgpack only).
"""
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
    Plane,
    ProtocolError,
    Sphere,
    Unavailable,
)
from .sdk import ClothHandle, DrapeClient, zenoh_config

__all__ = [
    "PROTOCOL_VERSION",
    "Busy",
    "Capsule",
    "ClothHandle",
    "ClothState",
    "DrapeClient",
    "DrapeError",
    "Forbidden",
    "InternalError",
    "LimitExceeded",
    "LinkSpec",
    "NotFound",
    "Plane",
    "ProtocolError",
    "Sphere",
    "Unavailable",
    "zenoh_config",
]
