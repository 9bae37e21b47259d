"""Every request and reply as a dataclass (PROTOCOL.md sections 4-8), and the feature-set rule
of a control (:func:`resolve_features`). A request equals another when their wire maps
(wiremaps.py) are equal."""

from __future__ import annotations

from dataclasses import dataclass, field, fields
from typing import Any

import numpy as np

from .errors import DrapeError, ProtocolError, error_for
from .requestfields import CONTROL_FIELDS, SUBMIT_FIELDS
from .vocabulary import (
    FEATURE_NAMES,
    Collider,
    GridSpec,
    LinkSpec,
    MeshCollider,
    MeshSpec,
    PinMoves,
    PinUpdate,
    ResumeState,
    StateOptions,
    Vec3,
    _empty_u32,
)
from .wiremaps import control_batch_to_map, control_to_map, scene_to_map, submit_to_map


@dataclass(eq=False)
class SubmitRequest:
    """Add a cloth. Exactly one of ``grid`` and ``mesh``. ``None`` means "server default"."""

    client: str
    grid: GridSpec | None = None
    mesh: MeshSpec | None = None
    pinned: np.ndarray = field(default_factory=_empty_u32)
    links: LinkSpec | None = None
    material: dict[str, Any] = field(default_factory=dict)  # only the fields given
    features: tuple[str, ...] = ()
    gravity: Vec3 | None = None
    wind: Vec3 | None = None
    iterations: int | None = None
    substeps: int | None = None
    chebyshev_rho: float | None = None
    colliders: tuple[Collider, ...] | None = None
    state: StateOptions | None = None
    quality: str | None = None  # 1.1: a QUALITY_PRESETS name; sets iterations, substeps, xpbd, tethers
    rid: int = 0
    resume: ResumeState | None = None  # 1.3: start from this state instead of the rest pose
    scene: str | None = None  # 1.7: collide with the scene's other cloths and its colliders
    mesh_collider: MeshCollider | None = None  # 1.8: the cloth's own mesh collider (a new mesh)

    @property
    def n_vertices(self) -> int:
        if self.grid is not None:
            return self.grid.cols * self.grid.rows
        assert self.mesh is not None
        return len(self.mesh.vertices)

    def __eq__(self, other: object) -> bool:
        return isinstance(other, SubmitRequest) and submit_to_map(self) == submit_to_map(other)


@dataclass(eq=False)
class ControlRequest:
    """Change a cloth from the next tick on. Every field but cloth and token is optional."""

    cloth: str
    token: str
    pins: PinUpdate | None = None
    colliders: tuple[Collider, ...] | None = None  # replaces the set; () clears it
    gravity: Vec3 | None = None
    wind: Vec3 | None = None
    material: dict[str, Any] = field(default_factory=dict)  # merged over the current material
    features: tuple[str, ...] | None = None  # replaces the feature set (prefer features_add / features_remove)
    iterations: int | None = None
    substeps: int | None = None
    chebyshev_rho: float | None = None
    state: StateOptions | None = None
    reset: bool = False  # back to the rest pose with zero velocity
    quality: str | None = None  # 1.1: the preset the client wants from now on
    rid: int = 0
    features_add: tuple[str, ...] | None = None  # 1.2: switched on, the others kept
    features_remove: tuple[str, ...] | None = None  # 1.2: switched off, the others kept
    mesh_collider: MeshCollider | None = None  # 1.8: set, re-pose, move or remove the cloth's mesh

    def __eq__(self, other: object) -> bool:
        return isinstance(other, ControlRequest) and control_to_map(self) == control_to_map(other)


# The requests declare the field table's names (requestfields.CONTROL_FIELDS) as typed attributes.
assert {f.name for f in fields(ControlRequest)} == {"cloth", "token", "rid", *(f.name for f in CONTROL_FIELDS)}, (
    "ControlRequest must declare requestfields.CONTROL_FIELDS"
)
assert {f.name for f in SUBMIT_FIELDS} <= {f.name for f in fields(SubmitRequest)}, (
    "SubmitRequest must declare requestfields.SUBMIT_FIELDS"
)


@dataclass
class RemoveRequest:
    cloth: str
    token: str
    rid: int = 0


@dataclass
class InfoRequest:
    rid: int = 0


@dataclass(eq=False)
class SceneRequest:
    """1.7: a scene's colliders and members, sent by its owner (PROTOCOL.md 5.3). ``None``
    leaves a field as it is."""

    client: str
    scene: str
    colliders: tuple[Collider, ...] | None = None  # replaces the scene's colliders; () clears them
    members: tuple[str, ...] | None = None  # replaces who else may put cloths in ("*": anyone); () nobody
    rid: int = 0
    mesh_collider: MeshCollider | None = None  # 1.8: set, re-pose, move or remove the scene's mesh

    def __eq__(self, other: object) -> bool:
        return isinstance(other, SceneRequest) and scene_to_map(self) == scene_to_map(other)


@dataclass
class SceneReply:
    """1.7: ``tick``, the first tick whose states reflect the scene's new colliders; the scene's
    owner, its cloths on this server and its members after the change."""

    tick: int
    owner: str
    cloths: int
    members: tuple[str, ...] = ()
    rid: int = 0


@dataclass
class SubmitReply:
    cloth: str
    token: str
    key: str  # the cloth's own state key (where its state is published unless bundled)
    vertices: int
    tick: int  # the first tick whose state includes the cloth
    rid: int = 0
    bundle_key: str | None = None  # 1.1: set when the state goes in the client's bundle on this key instead


@dataclass
class ControlReply:
    tick: int  # the first tick whose state reflects the change
    rid: int = 0
    features: tuple[str, ...] | None = None  # 1.2: the cloth's feature set after the change


@dataclass
class RemoveReply:
    tick: int  # the last tick published for the cloth; nothing later is ever published
    rid: int = 0


@dataclass
class ErrorReply:
    code: str
    message: str
    rid: int = 0

    def exception(self) -> DrapeError:
        return error_for(self.code, self.message, self.rid)


@dataclass(eq=False)
class ControlBatchRequest:
    """1.1: controls of many cloths of one client in one request. Each item is a control
    (cloth, token and any control field); the items' own ``rid`` is not sent. 1.4: ``moves``, the
    pin moves of many cloths as one block (PROTOCOL.md 5.1.1); ``items`` may then be empty."""

    client: str
    items: list[ControlRequest] = field(default_factory=list)
    rid: int = 0
    moves: PinMoves | None = None

    def __eq__(self, other: object) -> bool:
        return isinstance(other, ControlBatchRequest) and control_batch_to_map(self) == control_batch_to_map(other)


@dataclass(eq=False)
class DecodedControlBatch:
    """A batch control as a server reads it: the envelope was valid; each item is either its
    validated ControlRequest or the ProtocolError that rejects that item alone."""

    client: str
    items: list[ControlRequest | ProtocolError]
    rid: int = 0
    moves: PinMoves | None = None  # 1.4: validated on the bytes alone (ownership is the server's)


@dataclass
class BatchItemResult:
    """The outcome of one batch item: ``tick`` when applied, else an error ``code`` and ``message``."""

    tick: int | None = None
    code: str = ""
    message: str = ""
    features: tuple[str, ...] | None = None  # 1.2: the cloth's feature set after an applied item

    @property
    def ok(self) -> bool:
        return not self.code

    def exception(self, rid: int = 0) -> DrapeError | None:
        return None if self.ok else error_for(self.code, self.message, rid)


@dataclass
class ControlBatchReply:
    """``tick``: the first tick whose states reflect the applied items (and moves); one result per
    item, in order. 1.4, when the request had ``moves``: ``moves_tick``, the first tick whose states
    reflect the applied moves, and ``moves_failed``, one ``(position, code, message)`` per refused
    move, by position in the block (None from a server older than 1.4 or without moves)."""

    tick: int
    results: list[BatchItemResult] = field(default_factory=list)
    rid: int = 0
    moves_tick: int | None = None
    moves_failed: list[tuple[int, str, str]] | None = None

    @property
    def failed(self) -> int:
        return sum(1 for r in self.results if not r.ok)


def resolve_features(current: frozenset[str], req: ControlRequest) -> frozenset[str]:
    """The feature set a cloth has after the control ``req``, from its set ``current`` (PROTOCOL.md
    section 5, "Features"). In this order:

    1. ``features`` (when given) replaces the set; otherwise ``current`` is kept;
    2. ``features_add`` (1.2) switches its names on, then ``features_remove`` (1.2) switches its
       names off (a name in both is refused by the decoder);
    3. a non-empty ``colliders`` list switches ``colliders`` on (``[]`` clears the list and leaves
       the feature as it is);
    4. ``state.normals`` switches ``normals`` on (true) or off (false).

    A ``quality`` preset is applied by the server afterwards: it sets ``xpbd`` and ``tethers`` as
    the preset says (every preset of 1.2 switches both on). Pure: validation is the decoder's job."""
    feats = set(current if req.features is None else req.features)
    feats.update(req.features_add or ())
    feats.difference_update(req.features_remove or ())
    if req.colliders:
        feats.add("colliders")
    if req.state is not None and req.state.normals is not None:
        (feats.add if req.state.normals else feats.discard)("normals")
    unknown = feats.difference(FEATURE_NAMES)
    if unknown:
        raise ValueError(f"unknown feature(s) {sorted(unknown)}; known: {list(FEATURE_NAMES)}")
    return frozenset(feats)


def feature_list(features: frozenset[str] | set[str] | tuple[str, ...]) -> tuple[str, ...]:
    """A feature set in the protocol's canonical order (FEATURE_NAMES), as replies carry it."""
    return tuple(f for f in FEATURE_NAMES if f in features)
