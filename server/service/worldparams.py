"""From validated protocol requests to what the World takes: cloth parameters (one helper for
submit and control), packed colliders, feature sets after a control."""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from drape.client import protocol as P

from ..sim import quality
from ..sim.params import Capsule, ClothParams, Features, Material, Plane, Sphere, pack_colliders
from .config import ServerConfig


def pack(colliders: tuple[P.Collider, ...] | None, rid: int) -> np.ndarray:
    out: list[Sphere | Capsule | Plane] = []
    for c in colliders or ():
        if isinstance(c, P.Sphere):
            out.append(Sphere(c.center, c.radius))
        elif isinstance(c, P.Capsule):
            out.append(Capsule(c.p0, c.p1, c.radius))
        else:
            out.append(Plane(c.normal, c.offset))
    try:
        return pack_colliders(out)
    except ValueError as e:
        raise P.ProtocolError(P.ERR_INVALID_VALUE, f"colliders: {e}", rid) from None


def features_after(req: P.ControlRequest, p: ClothParams) -> set[str]:
    """The cloth's feature names once ``req`` is applied (the protocol's own rule)."""
    return set(P.resolve_features(frozenset(p.features.names()), req))


def changes_params(req: P.ControlRequest, p: ClothParams) -> bool:
    """Whether a control changes the cloth's parameters (the common per-tick control, pins and
    colliders of a cloth whose colliders feature is on, changes none)."""
    return bool(
        req.material
        or req.features is not None
        or req.gravity is not None
        or req.wind is not None
        or req.iterations is not None
        or req.substeps is not None
        or req.chebyshev_rho is not None
        or req.quality is not None
        or getattr(req, "features_add", None)
        or getattr(req, "features_remove", None)
        or (req.colliders and not p.features.colliders)
        or (req.state is not None and req.state.normals is not None and req.state.normals != p.features.normals)
    )


def pins_only(req: P.ControlRequest) -> bool:
    """Whether a control carries pin targets and nothing else."""
    return bool(
        req.pins is not None
        and len(req.pins.indices)
        and req.colliders is None
        and req.gravity is None
        and req.wind is None
        and not req.material
        and req.features is None
        and req.iterations is None
        and req.substeps is None
        and req.chebyshev_rho is None
        and req.state is None
        and not req.reset
        and req.quality is None
        and not getattr(req, "features_add", None)
        and not getattr(req, "features_remove", None)
    )


def params_with(
    base: ClothParams, req: P.SubmitRequest | P.ControlRequest, material: Material, features: set[str]
) -> ClothParams:
    """``base`` with the solver fields a submit or control request gives (absent ones kept)."""
    return base.with_(
        material=material,
        features=Features.from_names(sorted(features)),
        gravity=req.gravity if req.gravity is not None else base.gravity,
        wind=req.wind if req.wind is not None else base.wind,
        iterations=req.iterations if req.iterations is not None else base.iterations,
        substeps=req.substeps if req.substeps is not None else base.substeps,
        chebyshev_rho=req.chebyshev_rho if req.chebyshev_rho is not None else base.chebyshev_rho,
    )


def params_from_submit(req: P.SubmitRequest) -> ClothParams:
    feats = set(req.features)
    if req.colliders:
        feats.add("colliders")
    if req.state is not None and req.state.normals:
        feats.add("normals")
    try:
        params = params_with(ClothParams(), req, Material(**req.material), feats)
        params.validate()
    except (TypeError, ValueError) as e:
        raise P.ProtocolError(P.ERR_INVALID_VALUE, f"cloth parameters: {e}", req.rid) from None
    return params


def params_after_control(req: P.ControlRequest, p: ClothParams) -> ClothParams:
    """The parameters once ``req`` is applied (raises ValueError when they are invalid)."""
    material = replace(p.material, **req.material) if req.material else p.material
    new = params_with(p, req, material, features_after(req, p))
    new.validate()
    return new


def with_preset(config: ServerConfig, params: ClothParams, name: str, rid: int) -> ClothParams:
    """``params`` with quality preset ``name`` at this server's tick rate, within its limits."""
    out = quality.apply_preset(params, name, config.tick_rate)
    if out.substeps > config.max_substeps or out.iterations > config.max_iterations:
        raise P.LimitExceeded(
            P.ERR_LIMIT_EXCEEDED,
            f"quality {name!r} needs {out.substeps} substeps x "
            f"{out.iterations} iterations; this server allows {config.max_substeps} x "
            f"{config.max_iterations}",
            rid,
        )
    return out
