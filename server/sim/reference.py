"""CPU reference solver in numpy (float64 by default): the ground truth of the tests.

One step of one cloth, in this order (the OpenCL kernels in kernels/cloth.cl do the same):

    h = dt / substeps;  damping per substep = 1 - (1 - kDP) ** (1 / substeps)
    for each substep s:
        [wind]       normals and areas from the current positions
        free:        v += g * h + dv_aero;   x_prev = x;   x += v * h
                     (dv_aero: drag and lift over the substep, at most the relative wind speed)
        pinned:      x += (target - x) / (substeps - s)        (reaches the target on the last)
        [xpbd]       lambda = 0
        [tethers]    free vertex no further than tether_length * limit from each of its anchors
                     (one per pin island, tethers.py), before the links as NvCloth does (serial,
                     coloured: the work-group and pack solvers)
        iterations:  every link, colour by colour (Gauss-Seidel in colour order), with the
                     talk's PBD equation   k = kst (rl^2 - L) / ((im0 + im1) (rl^2 + L))
                     or XPBD               dl = (-C - a~ l) / (im0 + im1 + a~),  a~ = compliance / h^2
                     [tethers] first the long-range links, colour by colour: unilateral and hard,
                     a link no longer than rest * limit (k = (rest * limit / len - 1) / (im0 + im1)
                     where that is negative)
        [tethers]    the tethers again (every mode: the device's coloured and Jacobi solvers
                     apply them here only)
        [colliders]  push out of spheres, capsules, planes (interpolated over substeps), friction;
                     spheres and capsules first along the substep's motion (continuous: no tunnelling)
        [self_collision]  vertices further apart than the thickness at rest pushed apart to it,
                     SELF_COLLISION_PASSES Jacobi passes (collision.py; the work-group solver's),
                     after the colliders (whose friction would take back their separation), then
                     [colliders] the push-out again at the end pose, without friction
        all:         v = (x - x_prev) / h * (1 - damping)

``mode="serial"`` visits links one at a time in fabric order exactly like the talk's CPU loop;
``mode="coloured"`` does each colour as one numpy operation (links of a colour share no vertex,
so it is the same computation; ``mode="batches"`` is the same colour batches with the device's
coloured solver's tethers: after the links, no long-range links); ``mode="jacobi"`` mirrors the
OpenCL vertex solver (corrections from the previous iterate, averaged per vertex and
over-relaxed by ``JACOBI_OMEGA``; like the device's Jacobi and coloured solvers, tethers after
the links and no long-range links).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from .collision import self_collide
from .fabric import Fabric, vertex_masses
from .params import (
    CCD_SLOP,
    CCD_STEPS,
    COLLIDER_CAPSULE,
    COLLIDER_PLANE,
    ClothParams,
)
from .shared import EPS_DENOM, EPS_LEN2, JACOBI_OMEGA, vertex_normals  # noqa: F401 (re-exported)


@dataclass
class ClothState:
    """Mutable state of one cloth instance."""

    x: np.ndarray  # (n, 3)
    v: np.ndarray  # (n, 3)
    invm: np.ndarray  # (n,)
    target: np.ndarray  # (n, 3): where pinned vertices are at the end of the next step
    colliders: np.ndarray = field(default_factory=lambda: np.zeros((0, 2, 4)))  # at step end
    colliders_prev: np.ndarray = field(default_factory=lambda: np.zeros((0, 2, 4)))  # at step start
    normals: np.ndarray | None = None  # (n, 3), filled when features ask for normals

    @classmethod
    def initial(cls, fabric: Fabric, params: ClothParams, dtype=np.float64, positions=None) -> ClothState:
        x = np.array(fabric.rest_positions if positions is None else positions, dtype=dtype)
        masses = vertex_masses(fabric, params.material.mass)
        invm = np.where(fabric.pinned, 0.0, 1.0 / masses).astype(dtype)
        return cls(x=x, v=np.zeros_like(x), invm=invm, target=x.copy())

    def set_colliders(self, packed: np.ndarray) -> None:
        """New collider poses for the end of the next step; the previous ones become its start."""
        packed = np.asarray(packed, self.x.dtype).reshape(-1, 2, 4)
        if len(packed) != len(self.colliders):
            self.colliders_prev = packed.copy()
        else:
            self.colliders_prev = self.colliders
        self.colliders = packed.copy()


def link_stiffness(fabric: Fabric, params: ClothParams) -> np.ndarray:
    return np.asarray(params.material.stiffness, np.float64)[fabric.link_type]


def link_compliance(fabric: Fabric, params: ClothParams) -> np.ndarray:
    return np.asarray(params.material.compliance, np.float64)[fabric.link_type]


def step(state: ClothState, fabric: Fabric, params: ClothParams, dt: float, mode: str = "coloured") -> None:
    """Advance one cloth by dt in place."""
    if mode not in ("serial", "coloured", "batches", "jacobi"):
        raise ValueError(f"unknown reference mode {mode!r}")
    # the tethers go before and after the links with the long-range links between (work-group and
    # pack solvers: serial, coloured), or only after the links (device's coloured batches, Jacobi)
    early = mode in ("serial", "coloured")
    f = params.features
    m = params.material
    x, v, invm = state.x, state.v, state.invm
    dtype = x.dtype
    S = params.substeps
    h = dt / S
    damp = 1.0 - (1.0 - m.damping) ** (1.0 / S)
    free = invm > 0
    pinned = ~free
    g = np.asarray(params.gravity, dtype)
    kst = link_stiffness(fabric, params).astype(dtype)
    comp = link_compliance(fabric, params).astype(dtype)
    lam = np.zeros(fabric.n_links, dtype)
    for s in range(S):
        acc = np.broadcast_to(g, x.shape)
        if f.needs_normals:
            normals, area = vertex_normals(x, fabric)
            state.normals = normals
        if f.wind:  # from the velocity before this substep's gravity, as the kernels do
            v[free] += aero_dv(
                v, normals, area, invm, h, np.asarray(params.wind, dtype), m.drag, m.lift, m.air_density
            )[free]
        v[free] += acc[free] * h
        x_prev = x.copy()
        x[free] += v[free] * h
        x[pinned] += (state.target[pinned] - x[pinned]) / (S - s)
        lam[:] = 0.0
        alpha = comp / (h * h)
        if f.tethers and early:
            apply_tethers(x, fabric, m.tether_limit)
        x_before = x.copy()  # x^(k-1) for Chebyshev
        for it in range(params.iterations):
            if mode == "serial":
                if f.tethers:
                    _long_range(x, invm, fabric, m.tether_limit, serial=True)
                _links_serial(x, invm, fabric, kst, alpha, lam, f.xpbd)
            elif mode in ("coloured", "batches"):
                if f.tethers and early:
                    _long_range(x, invm, fabric, m.tether_limit)
                for c in range(fabric.n_colours):
                    sl = slice(int(fabric.colour_offsets[c]), int(fabric.colour_offsets[c + 1]))
                    _links_vectorised(x, invm, fabric, sl, kst, alpha, lam, f.xpbd)
            else:
                x_k = x.copy()
                _links_jacobi(x, invm, fabric, kst, alpha, lam, f.xpbd)
                omega = chebyshev_omega(params.chebyshev_rho, it)
                if omega != 1.0:
                    x[free] = omega * (x[free] - x_before[free]) + x_before[free]
                x_before = x_k
        if f.tethers:  # after the links: in every mode (serial, coloured: again)
            apply_tethers(x, fabric, m.tether_limit)
        if f.colliders and len(state.colliders):
            t0, t1 = s / S, (s + 1) / S
            c_prev = _lerp_colliders(state.colliders_prev, state.colliders, t0)
            c_now = _lerp_colliders(state.colliders_prev, state.colliders, t1)
            collide(x, x_prev, invm, c_prev, c_now, m.friction)
        if f.self_collision:  # after the colliders' friction, which would take back its separation
            self_collide(x, invm, fabric.rest_positions, m.thickness, m.contact_stiffness)
            if f.colliders and len(state.colliders):  # and out of the colliders again, without friction
                collide(x, x.copy(), invm, c_now, c_now, 0.0)
        v[:] = (x - x_prev) / h * (1.0 - damp)
    if f.needs_normals:
        state.normals, _ = vertex_normals(x, fabric)


def chebyshev_omega(rho: float, it: int) -> float:
    """Chebyshev weight of Jacobi iteration ``it`` (0-based): 1, 2/(2-rho^2), 4/(4-rho^2 w)..."""
    if rho <= 0.0 or it == 0:
        return 1.0
    w = 2.0 / (2.0 - rho * rho)
    for _ in range(it - 1):
        w = 4.0 / (4.0 - rho * rho * w)
    return w


# ---------------------------------------------------------------------------------------------
# Links


def _pbd_pair(x0, x1, im0, im1, rl, kst):
    """Vectorised PBD correction factors k (..., ) for pairs; zero where undefined."""
    d = x1 - x0
    L = np.einsum("...i,...i->...", d, d)
    rl2 = rl * rl
    w = im0 + im1
    denom = w * (rl2 + L)
    ok = denom > EPS_DENOM
    k = np.where(ok, kst * (rl2 - L) / np.where(ok, denom, 1.0), 0.0)
    return d, k


def _xpbd_pair(x0, x1, im0, im1, rl, alpha, lam):
    d = x1 - x0
    L = np.einsum("...i,...i->...", d, d)
    ok = L > EPS_LEN2
    length = np.sqrt(np.where(ok, L, 1.0))
    n = d / length[..., None]
    C = length - rl
    denom = im0 + im1 + alpha
    ok &= (denom > EPS_DENOM) & np.isfinite(alpha)  # infinite compliance: infinitely soft
    dl = np.where(ok, (-C - alpha * lam) / np.where(denom > EPS_DENOM, denom, 1.0), 0.0)
    return n, dl


def _links_vectorised(x, invm, fabric, sl, kst, alpha, lam, xpbd):
    a = fabric.links[sl, 0]
    b = fabric.links[sl, 1]
    im0, im1 = invm[a], invm[b]
    rl = fabric.rest_length[sl].astype(x.dtype)
    if xpbd:
        n, dl = _xpbd_pair(x[a], x[b], im0, im1, rl, alpha[sl], lam[sl])
        lam[sl] += dl
        x[a] -= n * (im0 * dl)[:, None]
        x[b] += n * (im1 * dl)[:, None]
    else:
        d, k = _pbd_pair(x[a], x[b], im0, im1, rl, kst[sl])
        x[a] -= d * (k * im0)[:, None]
        x[b] += d * (k * im1)[:, None]


def _links_serial(x, invm, fabric, kst, alpha, lam, xpbd):
    """The talk's CPU loop, one link at a time, in place."""
    links = fabric.links
    rest = fabric.rest_length
    for i in range(fabric.n_links):
        a, b = links[i]
        im0, im1 = invm[a], invm[b]
        if xpbd:
            n, dl = _xpbd_pair(x[a], x[b], im0, im1, rest[i], alpha[i], lam[i])
            lam[i] += dl
            x[a] -= n * (im0 * dl)
            x[b] += n * (im1 * dl)
        else:
            d, k = _pbd_pair(x[a], x[b], im0, im1, rest[i], kst[i])
            x[a] -= d * (k * im0)
            x[b] += d * (k * im1)


def _links_jacobi(x, invm, fabric, kst, alpha, lam, xpbd):
    """All links from the same iterate; per-vertex average of corrections, over-relaxed."""
    a = fabric.links[:, 0]
    b = fabric.links[:, 1]
    im0, im1 = invm[a], invm[b]
    rl = fabric.rest_length.astype(x.dtype)
    if xpbd:
        n, dl = _xpbd_pair(x[a], x[b], im0, im1, rl, alpha, lam)
        lam += dl
        d0 = -n * (im0 * dl)[:, None]
        d1 = n * (im1 * dl)[:, None]
    else:
        d, k = _pbd_pair(x[a], x[b], im0, im1, rl, kst)
        d0 = -d * (k * im0)[:, None]
        d1 = d * (k * im1)[:, None]
    acc = np.zeros_like(x)
    np.add.at(acc, a, d0)
    np.add.at(acc, b, d1)
    deg = np.diff(fabric.jacobi_offsets)[np.argsort(fabric.jacobi_order)]
    scale = np.where(deg > 0, JACOBI_OMEGA / np.maximum(deg, 1), 0.0)
    x += acc * scale[:, None]


def _long_range(x, invm, fabric, limit, serial=False):
    """The long-range links (Fabric.long_range), colour by colour (or one at a time): unilateral
    and hard, each no longer than its rest length times ``limit``."""
    lk, rest, offsets = fabric.long_range()
    ranges = (
        [(i, i + 1) for i in range(len(lk))]
        if serial
        else [(int(offsets[c]), int(offsets[c + 1])) for c in range(len(offsets) - 1)]
    )
    rl_all = rest.astype(x.dtype) * limit
    for lo, hi in ranges:
        a, b = lk[lo:hi, 0], lk[lo:hi, 1]
        im0, im1 = invm[a], invm[b]
        d = x[b] - x[a]
        L = np.einsum("ij,ij->i", d, d)
        w = im0 + im1
        ok = (L > EPS_LEN2) & (w > EPS_DENOM)
        k = np.where(ok, (rl_all[lo:hi] / np.sqrt(np.where(ok, L, 1.0)) - 1.0) / np.where(ok, w, 1.0), 0.0)
        k = np.minimum(k, 0.0)  # unilateral: only pulls the ends together
        x[a] -= d * (k * im0)[:, None]
        x[b] += d * (k * im1)[:, None]


# ---------------------------------------------------------------------------------------------
# Features


def apply_tethers(x: np.ndarray, fabric: Fabric, limit: float) -> None:
    """Each free vertex no further than its tether length times ``limit`` from each of its
    anchors, slot by slot (a vertex's tethers in order; anchors are pinned, so vertices do not
    interact)."""
    anchor = fabric.tether_anchor
    for s in range(anchor.shape[1]):
        idx = np.flatnonzero(anchor[:, s] >= 0)
        if len(idx) == 0:
            continue
        a = anchor[idx, s]
        d = x[idx] - x[a]
        dist = np.linalg.norm(d, axis=1)
        lim = fabric.tether_length[idx, s] * limit
        over = dist > lim
        if np.any(over):
            i = idx[over]
            x[i] = x[a[over]] + d[over] * (lim[over] / dist[over])[:, None]


def _lerp_colliders(c0: np.ndarray, c1: np.ndarray, t: float) -> np.ndarray:
    out = c0 + (c1 - c0) * t
    out[:, 1, 3] = c1[:, 1, 3]  # the type does not interpolate
    return out


def collide(x, x_prev, invm, c_prev, c_now, friction):
    """Push free vertices out of each collider in order, then Coulomb-like friction against the
    collider's own motion over the substep."""
    free = invm > 0
    for c in range(len(c_now)):
        kind = int(round(float(c_now[c, 1, 3])))
        if kind == COLLIDER_PLANE:
            n = c_now[c, 0, :3]
            n = n / max(np.linalg.norm(n), 1e-30)
            off = c_now[c, 0, 3]
            dist = x @ n - off
            inside = free & (dist < 0)
            if not np.any(inside):
                continue
            pen = -dist[inside]
            nn = np.broadcast_to(n, (int(inside.sum()), 3))
            cdisp = n * (off - c_prev[c, 0, 3])
            x[inside] += nn * pen[:, None]
            _friction(x, x_prev, inside, nn, pen, np.broadcast_to(cdisp, nn.shape), friction)
            continue
        r = c_now[c, 0, 3]
        p0, p1 = c_now[c, 0, :3], c_now[c, 1, :3]
        q0, q1 = c_prev[c, 0, :3], c_prev[c, 1, :3]
        cap = kind == COLLIDER_CAPSULE
        if r > 0:
            _continuous(x, x_prev, free, q0, q1, p0, p1, r, cap, friction)
        centre, t = _axis_point(x, p0, p1, cap)
        d = x - centre
        dist2 = np.einsum("ij,ij->i", d, d)
        inside = free & (dist2 < r * r)
        if not np.any(inside):
            continue
        di = d[inside]
        dist = np.sqrt(dist2[inside])
        nn = _unit_or_up(di, dist)
        pen = r - dist
        x[inside] = centre[inside] + nn * r
        ti = t[inside][:, None]
        cdisp = (p0 + ti * (p1 - p0)) - (q0 + ti * (q1 - q0))
        _friction(x, x_prev, inside, nn, pen, cdisp, friction)


def _axis_point(x, a0, a1, cap: bool):
    """The point of a sphere's centre (a0) or a capsule's axis a0 -> a1 (per row or shared)
    closest to each row of x, and its parameter along the axis (colliders.cl's axis_point)."""
    if not cap:
        return np.broadcast_to(a0, x.shape), np.zeros(len(x), x.dtype)
    axis = a1 - a0
    aa = np.einsum("...j,...j->...", axis, axis)
    with np.errstate(divide="ignore", invalid="ignore"):
        t = np.where(
            aa > EPS_LEN2, np.clip(np.einsum("ij,ij->i", x - a0, np.broadcast_to(axis, x.shape)) / aa, 0, 1), 0
        )
    t = t.astype(x.dtype)
    return a0 + t[:, None] * axis, t


def _unit_or_up(d, dist):
    safe = dist > 1e-12
    return np.where(safe[:, None], d / np.where(safe, dist, 1.0)[:, None], np.array([0.0, 1.0, 0.0], d.dtype))


def _continuous(x, x_prev, free, q0, q1, p0, p1, r, cap: bool, mu) -> None:
    """No tunnelling through a sphere or capsule (colliders.cl): the first contact of each free
    vertex's motion x_prev -> x with the collider moving from (q0, q1) to (p0, p1) over the substep,
    by conservative advancement (CCD_STEPS steps at most, CCD_SLOP from the surface); where it
    is met before the substep's end (or the steps run out first), x goes back onto the plane
    tangent to the collider at that contact, carried to the end pose, with friction."""
    dx = x - x_prev
    L = np.linalg.norm(dx - (p0 - q0), axis=1)
    if cap:
        L = np.maximum(L, np.linalg.norm(dx - (p1 - q1), axis=1))
    tau = np.zeros(len(x), x.dtype)
    v = x_prev.copy()
    c, t = _axis_point(v, q0, q1, cap)
    c = np.array(c)
    f = np.linalg.norm(v - c, axis=1) - r
    active = free & (f >= CCD_SLOP)
    for _ in range(CCD_STEPS):
        if not active.any():
            break
        miss = active & ~(f <= L * (1 - tau))
        tau[miss] = 2
        active &= ~miss
        i = np.nonzero(active)[0]
        tau[i] += f[i] / L[i]
        v[i] = x_prev[i] + dx[i] * tau[i, None]
        ti = tau[i, None]
        c[i], t[i] = _axis_point(v[i], q0 + (p0 - q0) * ti, q1 + (p1 - q1) * ti, cap)
        f[i] = np.linalg.norm(v[i] - c[i], axis=1) - r
        active[i] = f[i] >= CCD_SLOP
    hit = free & (tau <= 1)
    if not hit.any():
        return
    d = v[hit] - c[hit]
    n = _unit_or_up(d, np.linalg.norm(d, axis=1))
    th = t[hit][:, None]
    ce = p0 + th * (p1 - p0)
    depth = np.einsum("ij,ij->i", ce + n * r - x[hit], n)
    push = depth > 0
    if not push.any():
        return
    rows = np.nonzero(hit)[0][push]
    mask = np.zeros(len(x), bool)
    mask[rows] = True
    x[rows] += n[push] * depth[push, None]
    _friction(x, x_prev, mask, n[push], depth[push], (ce - (q0 + th * (q1 - q0)))[push], mu)


def _friction(x, x_prev, mask, n, pen, cdisp, mu):
    if mu <= 0:
        return
    rel = (x[mask] - x_prev[mask]) - cdisp
    tang = rel - n * np.einsum("ij,ij->i", rel, n)[:, None]
    tl = np.linalg.norm(tang, axis=1)
    corr = np.minimum(mu * pen, tl)
    ok = tl > 1e-12
    scale = np.where(ok, corr / np.where(ok, tl, 1.0), 0.0)
    x[mask] -= tang * scale[:, None]


def aero_dv(v, normals, area, invm, h, wind, drag, lift, rho):
    """Velocity change over a substep from Bullet's per-vertex aerodynamics, at most the
    relative wind speed (drag never carries a vertex past the wind's velocity)."""
    f = aero_force(v, normals, area, wind, drag, lift, rho)
    dv = f * (invm * h)[:, None]
    mag = np.linalg.norm(dv, axis=1)
    rl = np.linalg.norm(v - wind, axis=1)
    over = mag > rl
    dv[over] *= (rl[over] / mag[over])[:, None]
    return dv


def aero_force(v, normals, area, wind, drag, lift, rho):
    """Bullet's per-vertex aerodynamics: drag along the relative wind, lift across it."""
    r = v - wind
    rl = np.linalg.norm(r, axis=1)
    ok = rl > 1e-12
    rh = np.where(ok[:, None], r / np.where(ok, rl, 1.0)[:, None], 0.0)
    n = normals * np.where(np.einsum("ij,ij->i", normals, r) < 0, -1.0, 1.0)[:, None]
    c = np.einsum("ij,ij->i", n, rh)
    f = -0.5 * drag * rho * (rl * rl * area * c)[:, None] * rh
    lift_on = (c > 0) & (c < 0.9848)
    if lift > 0 and np.any(lift_on):
        s = np.sqrt(np.maximum(1.0 - c * c, 0.0))
        dirn = np.cross(np.cross(n, rh), rh)
        f += np.where(lift_on[:, None], 0.5 * lift * rho * (rl * area * s)[:, None] * dirn, 0.0)
    return f
