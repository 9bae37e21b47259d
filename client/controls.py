"""Pure control building of the Python SDK (no I/O, no session): the conversions of the SDK's
friendly arguments (pins, settings, colliders, links, vectors) into protocol values, what a
"pins only" control is (the one a 1.4 ``moves`` block carries), a batch reply folded into one
outcome per item, and the error of a refused batch (:class:`BatchError`)."""

from __future__ import annotations

from collections.abc import Iterable, Mapping, Sequence
from dataclasses import fields, is_dataclass
from typing import Any

import numpy as np

from . import protocol as P
from .protocol import DrapeError


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


def item_outcomes(cloths: Sequence[str], rep: P.ControlBatchReply, rid: int) -> list[int | DrapeError]:
    """A batch reply to items of ``cloths`` (their ids, in order) as one outcome per item: the tick
    it applies from, or its DrapeError."""
    if len(rep.results) != len(cloths):
        raise DrapeError(P.ERR_INTERNAL, f"batch reply has {len(rep.results)} results for {len(cloths)} items", rid)
    out: list[int | DrapeError] = []
    for cloth, r in zip(cloths, rep.results, strict=True):
        if r.ok:
            out.append(rep.tick if r.tick is None else r.tick)
        else:
            out.append(P.error_for(r.code, f"cloth {cloth}: {r.message}", rid))
    return out


def pins_only(r: P.ControlRequest) -> bool:
    """A control with pin targets (distinct indices) and nothing else: what a moves block carries
    (the fields' table says which are pins: :func:`drape.client.protocol.requestfields.pins_only`)."""
    if not P.pins_only(r) or r.pins is None or not len(r.pins.indices):
        return False
    return len(np.unique(r.pins.indices)) == len(r.pins.indices)


def features_delta(reqs: Iterable[P.ControlRequest]) -> bool:
    """Whether any of ``reqs`` switches single features (features_add / features_remove: 1.2)."""
    return any(r.features_add is not None or r.features_remove is not None for r in reqs)


def pin_changes(
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
        out["colliders"] = tuple(collider(c) for c in colliders)
    return out


def set_changes(
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
    add = feature_names(features_add)
    remove = feature_names(features_remove)
    if add and remove and set(add) & set(remove):
        raise ValueError(f"feature(s) {sorted(set(add) & set(remove))} both added and removed")
    return dict(
        features_add=add,
        features_remove=remove,
        gravity=vec3(gravity),
        wind=vec3(wind),
        material=P.material_to_map(material) if material is not None else {},
        features=tuple(features) if features is not None else None,
        iterations=iterations,
        substeps=substeps,
        chebyshev_rho=chebyshev_rho,
        state=state,
        reset=reset,
        quality=quality,
    )


def feature_names(names: Iterable[str] | None) -> tuple[str, ...] | None:
    if names is None:
        return None
    out = (names,) if isinstance(names, str) else tuple(names)
    bad = [n for n in out if n not in P.FEATURE_NAMES]
    if bad:
        raise ValueError(f"unknown feature(s) {bad}; known: {list(P.FEATURE_NAMES)}")
    return out


def vec3(v: Sequence[float] | None) -> P.Vec3 | None:
    if v is None:
        return None
    t = tuple(float(x) for x in v)
    if len(t) != 3:
        raise ValueError(f"expected 3 numbers, got {len(t)}")
    return t  # type: ignore[return-value]


def links_of(links: Any) -> P.LinkSpec | None:
    if links is None or isinstance(links, P.LinkSpec):
        return links
    if isinstance(links, Mapping):
        return P.LinkSpec(**links)
    if is_dataclass(links):
        return P.LinkSpec(**{f.name: bool(getattr(links, f.name)) for f in fields(links)})
    raise TypeError(f"links must be a LinkSpec, a mapping or a dataclass, got {type(links).__name__}")


def collider(c: Any) -> P.Collider:
    """``c`` as a protocol collider (one already, a wire map or an object with a shape's fields):
    the shapes' table decides (:func:`drape.client.protocol.as_collider`)."""
    return P.as_collider(c)


__all__ = [
    "BatchError",
    "collider",
    "feature_names",
    "features_delta",
    "item_outcomes",
    "links_of",
    "pin_changes",
    "pins_only",
    "set_changes",
    "vec3",
]
