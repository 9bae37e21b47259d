"""The drawing's visibility passes (server/tools/render.py): the rasteriser (each pixel's
nearest triangle, a depth buffer: a ball pushed into a cloth meets it along the true
intersection, never a painter's-algorithm edge, and its barycentric coordinates) and the key
light's shadow map (soft by percentage-closer filtering)."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from .drawmeshes import Mesh
from .rendermath import unit


def rasterise(
    sx: np.ndarray, sy: np.ndarray, depth: np.ndarray, w: int, h: int, chunk: int = 4_000_000
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The nearest triangle at each pixel centre of a ``w`` x ``h`` image.

    ``sx``, ``sy``, ``depth``: (m, 3) each, the corners' pixel coordinates and depths (larger is
    farther). Returns the depth buffer (h * w, inf where empty), the triangle index (-1 where
    empty) and the barycentric weights of corners 1 and 2 there."""
    zbuf = np.full(h * w, np.inf)
    tri = np.full(h * w, -1, np.int64)
    b1 = np.zeros(h * w)
    b2 = np.zeros(h * w)
    if not len(sx):
        return zbuf, tri, b1, b2
    x0, x1, x2 = sx.T
    y0, y1, y2 = sy.T
    area = (x1 - x0) * (y2 - y0) - (x2 - x0) * (y1 - y0)
    ok = np.isfinite(area) & (np.abs(area) > 1e-9) & np.isfinite(depth).all(axis=1)
    with np.errstate(invalid="ignore"):
        xmin = np.ceil(np.nan_to_num(sx.min(1)) - 0.5).clip(0, w).astype(np.int64)
        xmax = np.floor(np.nan_to_num(sx.max(1)) - 0.5).clip(-1, w - 1).astype(np.int64)
        ymin = np.ceil(np.nan_to_num(sy.min(1)) - 0.5).clip(0, h).astype(np.int64)
        ymax = np.floor(np.nan_to_num(sy.max(1)) - 0.5).clip(-1, h - 1).astype(np.int64)
    bw, bh = xmax - xmin + 1, ymax - ymin + 1
    cnt = np.where(ok & (bw > 0) & (bh > 0), bw * bh, 0)
    idx = np.nonzero(cnt)[0]
    if not len(idx):
        return zbuf, tri, b1, b2
    # chunks of triangles of at most ``chunk`` candidate pixels (one huge triangle is one chunk)
    csum = np.cumsum(cnt[idx])
    bounds = np.searchsorted(csum, np.arange(chunk, int(csum[-1]) + chunk, chunk), side="right")
    cands = []
    start = 0
    for stop in [*bounds.tolist(), len(idx)]:
        if stop <= start:
            continue
        sel = idx[start:stop]
        start = stop
        c = cnt[sel]
        t = np.repeat(sel, c)
        off = np.arange(int(c.sum())) - np.repeat(np.cumsum(c) - c, c)
        px = xmin[t] + off % bw[t]
        py = ymin[t] + off // bw[t]
        X, Y = px + 0.5 - x0[t], py + 0.5 - y0[t]
        ar = area[t]
        w1 = (X * (y2 - y0)[t] - (x2 - x0)[t] * Y) / ar
        w2 = ((x1 - x0)[t] * Y - X * (y1 - y0)[t]) / ar
        inside = (w1 >= -1e-6) & (w2 >= -1e-6) & (w1 + w2 <= 1 + 1e-6)
        t, px, py, w1, w2 = t[inside], px[inside], py[inside], w1[inside], w2[inside]
        d = depth[t]
        z = d[:, 0] + w1 * (d[:, 1] - d[:, 0]) + w2 * (d[:, 2] - d[:, 0])
        pix = py * w + px
        np.minimum.at(zbuf, pix, z)
        cands.append((pix, z, t, w1, w2))
    for pix, z, t, w1, w2 in cands:
        win = z <= zbuf[pix]
        p = pix[win]
        tri[p], b1[p], b2[p] = t[win], w1[win], w2[win]
    return zbuf, tri, b1, b2


@dataclass
class Taps:
    """World points prepared for shadow lookups in one shadow map frame: which points fall in
    it, their texel index in the padded map, bilinear weights and depths."""

    near: np.ndarray
    index: np.ndarray
    fu: np.ndarray
    fv: np.ndarray
    depth: np.ndarray


class ShadowMap:
    """Depth from the key light (an orthographic view along it) over ``meshes``; :meth:`lit`
    tells how lit world points are (0 shadowed .. 1 lit), filtered over neighbouring texels.
    ``region`` (a world box): the map covers it, always the same texels (points prepared once
    with :meth:`taps` serve every frame); None: it covers the meshes."""

    def __init__(self, meshes: Sequence[Mesh], light: np.ndarray, res: int = 400, region: Any = None) -> None:
        back = unit(np.asarray(light, np.float64))
        right = unit(np.cross([0.0, 1.0, 0.0] if abs(back[1]) < 0.99 else [1.0, 0, 0], back))
        self.R = np.array([right, np.cross(back, right), back])
        cast = [m for m in meshes if m.shadows and len(m.triangles)]
        self.empty = not cast
        if cast:
            p = np.concatenate([m.positions for m in cast])
            off = np.cumsum([0] + [len(m.positions) for m in cast])[:-1]
            t = np.concatenate([m.triangles + o for m, o in zip(cast, off, strict=True)])
        else:
            p, t = np.zeros((1, 3)), np.zeros((0, 3), np.int64)
        v = p @ self.R.T
        if region is not None:
            lo3, hi3 = np.asarray(region, np.float64).reshape(2, 3)
            box = np.array([[x, y, z] for x in (lo3[0], hi3[0]) for y in (lo3[1], hi3[1]) for z in (lo3[2], hi3[2])])
            lo, hi = (box @ self.R.T)[:, :2].min(0), (box @ self.R.T)[:, :2].max(0)
        else:
            lo, hi = v[:, :2].min(0), v[:, :2].max(0)
        pad = 0.02 * float((hi - lo).max()) + 1e-6
        self.lo = lo - pad
        self.texel = float((hi - lo).max() + 2 * pad) / res
        self.w, self.h = (np.ceil((hi - lo + 2 * pad) / self.texel).astype(int) + 1).tolist()
        self.key = (self.R.tobytes(), self.lo.tobytes(), self.texel, self.w, self.h)
        sx, sy = self._uv(v)
        zbuf, _, _, _ = rasterise(sx[t], sy[t], -v[:, 2][t], self.w, self.h)
        self.z = zbuf.reshape(self.h, self.w)
        self.zp = np.pad(self.z, 2, constant_values=np.inf).ravel().astype(np.float32)  # no bounds checks

    def _uv(self, v: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        return (v[..., 0] - self.lo[0]) / self.texel, (v[..., 1] - self.lo[1]) / self.texel

    def taps(self, p: np.ndarray, bias: float) -> Taps:
        """Points ``p`` (k, 3) prepared for :meth:`lookup` (the same map frame: ``key``)."""
        v = p @ self.R.T
        u, w = self._uv(v)
        near = np.nonzero((u > -1) & (u < self.w + 1) & (w > -1) & (w < self.h + 1))[0]
        u, w = u[near] + 1.5, w[near] + 1.5
        iu, iv = np.floor(u), np.floor(w)
        stride = self.w + 4
        i = (iv.astype(np.int64) * stride + iu.astype(np.int64)).clip(0, self.zp.size - stride - 2)
        f32 = np.float32
        return Taps(near, i, (u - iu).astype(f32), (w - iv).astype(f32), (-v[near, 2] - bias).astype(f32))

    def lookup(self, taps: Taps, n: int) -> np.ndarray:
        """How lit the ``n`` prepared points are: percentage-closer filtering, the four nearest
        texels' depth tests weighted bilinearly."""
        out = np.ones(n, np.float32)
        if self.empty or not len(taps.near):
            return out
        z, i, d, fu = self.zp, taps.index, taps.depth, taps.fu
        stride = self.w + 4
        top = (d <= z[i]) + fu * ((d <= z[i + 1]).astype(np.float32) - (d <= z[i]))
        bottom = (d <= z[i + stride]) + fu * ((d <= z[i + stride + 1]).astype(np.float32) - (d <= z[i + stride]))
        out[taps.near] = top + taps.fv * (bottom - top)
        return out

    def lit(self, p: np.ndarray, bias: float) -> np.ndarray:
        if self.empty or not len(p):
            return np.ones(len(p), np.float32)
        return self.lookup(self.taps(p, bias), len(p))
