"""Controls of the Python SDK that do not need a session: the batch of many cloths' controls
(:class:`ControlBatch`, protocol 1.1), its error (:class:`BatchError`), and the conversions of
the SDK's friendly arguments (pins, settings, colliders, links, vectors) into protocol values."""

from __future__ import annotations

from collections.abc import Callable, Iterable, Mapping, Sequence
from dataclasses import fields, is_dataclass
from typing import TYPE_CHECKING, Any

import numpy as np

from . import protocol as P
from .protocol import DrapeError

if TYPE_CHECKING:
    from .handle import ClothHandle
    from .sdk import DrapeClient

ErrorCallback = Callable[[DrapeError], None]


class BatchError(DrapeError):
    """Raised by a waited-for batch (``client.batch(wait=True)``) when some of its items were
    refused: ``results`` holds, per item in order, the tick it applies from or its DrapeError."""

    def __init__(self, results: list[int | DrapeError]) -> None:
        errors = [r for r in results if isinstance(r, DrapeError)]
        first = errors[0]
        super().__init__(
            first.code, f"{len(errors)} of {len(results)} batch items refused; first: {first.message}", first.rid
        )
        self.results = results


class ControlBatch:
    """Controls of many of one client's cloths, sent as one batch control request (protocol
    1.1; to a 1.0 server as one control each). Use as a context manager (sent when the block
    ends without an exception) or call ``send()``. Every method takes the ClothHandle first
    and the same arguments as the ClothHandle method of the same name."""

    def __init__(
        self,
        client: DrapeClient,
        *,
        wait: bool = False,
        on_error: ErrorCallback | None = None,
        timeout: float | None = None,
    ) -> None:
        self.client = client
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
        if handle.client is not self.client:
            raise ValueError(f"cloth {handle.id} belongs to another DrapeClient")
        handle._check_open()
        handle._note_controls(changes)
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
        return self.add(handle, **_pin_changes(indices, targets, colliders))

    def set_colliders(self, handle: ClothHandle, colliders: Sequence[Any]) -> ControlBatch:
        return self.add(handle, colliders=tuple(_collider(c) for c in colliders))

    def set(
        self,
        handle: ClothHandle,
        *,
        gravity: Sequence[float] | None = None,
        wind: Sequence[float] | None = None,
        material: Mapping[str, Any] | Any = None,
        features: Iterable[str] | None = None,
        iterations: int | None = None,
        substeps: int | None = None,
        chebyshev_rho: float | None = None,
        normals: bool | None = None,
        encoding: str | None = None,
        reset: bool = False,
        quality: str | None = None,
        features_add: Iterable[str] | None = None,
        features_remove: Iterable[str] | None = None,
        step: float | None = None,
    ) -> ControlBatch:
        """As ClothHandle.set, for one item of the batch (``features_add`` / ``features_remove``: 1.2)."""
        return self.add(
            handle,
            **_set_changes(
                gravity,
                wind,
                material,
                features,
                iterations,
                substeps,
                chebyshev_rho,
                normals,
                encoding,
                reset,
                quality,
                features_add,
                features_remove,
                step,
            ),
        )

    def reset(self, handle: ClothHandle) -> ControlBatch:
        return self.add(handle, reset=True)

    def send(self) -> list[int | DrapeError] | None:
        """Send the collected items (once). ``wait=True``: returns each item's first tick, raising
        BatchError (with every item's outcome) if any was refused; otherwise None."""
        if self.sent:
            raise RuntimeError("this batch was already sent")
        self.sent = True
        results = self.client._send_controls(self.items, self.wait, self.on_error, self.timeout)
        self.results = results
        if results is not None and any(isinstance(r, DrapeError) for r in results):
            raise BatchError(results)
        return results

    def __enter__(self) -> ControlBatch:
        return self

    def __exit__(self, exc_type: Any, *exc: object) -> None:
        if exc_type is None and not self.sent:
            self.send()


def _item_outcomes(
    chunk: list[tuple[ClothHandle, P.ControlRequest]], rep: P.ControlBatchReply, rid: int
) -> list[int | DrapeError]:
    if len(rep.results) != len(chunk):
        raise DrapeError(P.ERR_INTERNAL, f"batch reply has {len(rep.results)} results for {len(chunk)} items", rid)
    out: list[int | DrapeError] = []
    for (h, _), r in zip(chunk, rep.results, strict=True):
        if r.ok:
            out.append(rep.tick if r.tick is None else r.tick)
        else:
            out.append(P.error_for(r.code, f"cloth {h.id}: {r.message}", rid))
    return out


def _pin_changes(
    indices: Sequence[int] | np.ndarray,
    targets: Sequence[Sequence[float]] | np.ndarray,
    colliders: Sequence[Any] | None,
) -> dict[str, Any]:
    idx = np.asarray(indices, np.int64).reshape(-1)
    tgt = np.asarray(targets, np.float32).reshape(-1, 3)
    if len(idx) != len(tgt):
        raise ValueError(f"{len(idx)} indices but {len(tgt)} targets")
    if idx.size and idx.min() < 0:
        raise ValueError("pin indices must be >= 0")
    out: dict[str, Any] = {"pins": P.PinUpdate(idx.astype(np.uint32), tgt)}
    if colliders is not None:
        out["colliders"] = tuple(_collider(c) for c in colliders)
    return out


def _set_changes(
    gravity: Sequence[float] | None,
    wind: Sequence[float] | None,
    material: Any,
    features: Iterable[str] | None,
    iterations: int | None,
    substeps: int | None,
    chebyshev_rho: float | None,
    normals: bool | None,
    encoding: str | None,
    reset: bool,
    quality: str | None = None,
    features_add: Iterable[str] | None = None,
    features_remove: Iterable[str] | None = None,
    step: float | None = None,
) -> dict[str, Any]:
    changed = normals is not None or encoding is not None or step is not None
    state = P.StateOptions(normals, encoding, None, step) if changed else None
    add = _feature_names(features_add)
    remove = _feature_names(features_remove)
    if add and remove and set(add) & set(remove):
        raise ValueError(f"feature(s) {sorted(set(add) & set(remove))} both added and removed")
    return dict(
        features_add=add,
        features_remove=remove,
        gravity=_vec3(gravity),
        wind=_vec3(wind),
        material=P.material_to_map(material) if material is not None else {},
        features=tuple(features) if features is not None else None,
        iterations=iterations,
        substeps=substeps,
        chebyshev_rho=chebyshev_rho,
        state=state,
        reset=reset,
        quality=quality,
    )


def _feature_names(names: Iterable[str] | None) -> tuple[str, ...] | None:
    if names is None:
        return None
    out = (names,) if isinstance(names, str) else tuple(names)
    bad = [n for n in out if n not in P.FEATURE_NAMES]
    if bad:
        raise ValueError(f"unknown feature(s) {bad}; known: {list(P.FEATURE_NAMES)}")
    return out


def _vec3(v: Sequence[float] | None) -> P.Vec3 | None:
    if v is None:
        return None
    t = tuple(float(x) for x in v)
    if len(t) != 3:
        raise ValueError(f"expected 3 numbers, got {len(t)}")
    return t  # type: ignore[return-value]


def _links(links: Any) -> P.LinkSpec | None:
    if links is None or isinstance(links, P.LinkSpec):
        return links
    if isinstance(links, Mapping):
        return P.LinkSpec(**links)
    if is_dataclass(links):
        return P.LinkSpec(**{f.name: bool(getattr(links, f.name)) for f in fields(links)})
    raise TypeError(f"links must be a LinkSpec, a mapping or a dataclass, got {type(links).__name__}")


def _collider(c: Any) -> P.Collider:
    if isinstance(c, (P.Sphere, P.Capsule, P.Plane)):
        return c
    m = P.collider_to_map(c)
    kind = m.get("type")
    if kind == "sphere":
        return P.Sphere(_vec3(m["center"]), float(m["radius"]))  # type: ignore[arg-type]
    if kind == "capsule":
        return P.Capsule(_vec3(m["p0"]), _vec3(m["p1"]), float(m["radius"]))  # type: ignore[arg-type]
    if kind == "plane":
        return P.Plane(_vec3(m["normal"]), float(m["offset"]))  # type: ignore[arg-type]
    raise TypeError(f"not a collider: {c!r}")
