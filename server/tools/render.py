"""Shaded 3-D pictures of cloths for ``drape demo``: a small numpy rasteriser with a depth buffer,
per-pixel normals and shadows, with Pillow for the text and the files.

Every primitive becomes triangles with per-vertex normals and colours (``drawmeshes``). One
pass finds each pixel's nearest triangle and its barycentric coordinates (``raster``); normals,
colours and world positions are interpolated there and lit per pixel: a key light (with shadows
from a shadow map, soft by percentage-closer filtering), a fill light, sky and ground ambient,
specular highlights and light through thin cloth, in linear colour. The floor is the plane at
the bottom of the bounds, traced per pixel (tiles, shadows, faded into the background). The
camera is orthographic (fitting a box: ``front``, ``side``, ``top``, ``iso``) or perspective
(:meth:`Camera.look_at`). Frames are drawn ``supersample`` times larger and scaled down (smooth
edges). Colours and vectors: ``rendermath``; the PNG and GIF files: ``imagefiles``. Pillow is
imported inside the functions (the ``tools`` extra).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from .drawmeshes import Mesh, capsule_mesh, cloth_mesh, sphere_mesh
from .raster import ShadowMap, Taps, rasterise
from .rendermath import Colour, linear, rgb, srgb, unit


def _rot_x(a: float) -> np.ndarray:
    c, s = math.cos(a), math.sin(a)
    return np.array([[1, 0, 0], [0, c, -s], [0, s, c]])


def _rot_y(a: float) -> np.ndarray:
    c, s = math.cos(a), math.sin(a)
    return np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]])


#: World to view rotations; rows are the screen's right, up and toward-the-viewer axes.
VIEWS: dict[str, np.ndarray] = {
    "front": np.eye(3),
    "side": np.array([[0.0, 0, -1], [0, 1, 0], [1, 0, 0]]),
    "top": np.array([[1.0, 0, 0], [0, 0, -1], [0, 1, 0]]),
    "iso": _rot_x(math.radians(25)) @ _rot_y(math.radians(-35)),  # yaw 35 deg, pitch 25 deg down
}
COLLIDER: Colour = (165, 160, 150)


@dataclass(frozen=True)
class Lighting:
    """The lights, in world space (directions point toward the light), and the surroundings."""

    key: tuple[float, float, float] = (-0.45, 0.8, 0.55)  # the sun: casts the shadows
    key_colour: tuple[float, float, float] = (1.0, 0.96, 0.9)
    key_strength: float = 1.8
    fill: tuple[float, float, float] = (0.6, 0.25, 0.5)
    fill_colour: tuple[float, float, float] = (0.55, 0.65, 0.85)
    fill_strength: float = 0.35
    sky: tuple[float, float, float] = (0.32, 0.36, 0.45)  # ambient from above
    ground: tuple[float, float, float] = (0.16, 0.14, 0.12)  # ambient from below
    translucency: float = 0.35  # of the key light through a thin cloth lit from behind
    background_top: Colour = (206, 214, 226)
    background_bottom: Colour = (244, 242, 236)
    floor: Colour = (226, 222, 212)
    floor_alt: Colour = (214, 209, 198)  # the other tiles
    floor_tile: float = 0.5  # metres
    shadow: float = 0.72  # how much of the key light a shadow takes
    exposure: float = 1.0

    def key_dir(self) -> np.ndarray:
        return unit(np.asarray(self.key, np.float64))


DEFAULT_LIGHTING = Lighting()


class Camera:
    """Orthographic projection fitting the world box ``bounds`` into the pixel rectangle ``rect``
    (``view``: one of VIEWS), or a perspective camera from :meth:`look_at`.

    :meth:`project` gives pixel coordinates and a depth (larger is farther); :meth:`rays` the
    ray through pixel centres; :meth:`to_eye` the unit vector from world points to the eye."""

    def __init__(self, view: str, bounds: Any, rect: tuple[float, float, float, float]) -> None:
        if view not in VIEWS:
            raise ValueError(f"view must be one of {sorted(VIEWS)}, got {view!r}")
        self.R = VIEWS[view]
        self.perspective = False
        self.eye = np.zeros(3)
        lo, hi = np.asarray(bounds, np.float64).reshape(2, 3)
        corners = np.array([[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1]) for z in (lo[2], hi[2])])
        v = corners @ self.R.T
        (umin, vmin), (umax, vmax) = v[:, :2].min(0), v[:, :2].max(0)
        x0, y0, x1, y1 = rect
        su = (x1 - x0) / (umax - umin) if umax - umin > 1e-12 else math.inf
        sv = (y1 - y0) / (vmax - vmin) if vmax - vmin > 1e-12 else math.inf
        self.scale = min(su, sv) if math.isfinite(min(su, sv)) else 1.0
        self.uc, self.vc = (umin + umax) / 2, (vmin + vmax) / 2
        self.cx, self.cy = (x0 + x1) / 2, (y0 + y1) / 2

    @classmethod
    def look_at(cls, eye: Sequence[float], target: Sequence[float], fov_deg: float, size: tuple[int, int]) -> Camera:
        """A perspective camera at ``eye`` looking at ``target`` (y up), ``fov_deg`` vertical
        field of view, for an image of ``size`` (w, h) pixels."""
        cam = cls.__new__(cls)
        e, t = np.asarray(eye, np.float64), np.asarray(target, np.float64)
        back = unit(e - t)
        right = unit(np.cross([0.0, 1.0, 0.0], back))
        up = np.cross(back, right)
        cam.R = np.array([right, up, back])
        cam.perspective = True
        cam.eye = e
        cam.scale = (size[1] / 2) / math.tan(math.radians(fov_deg) / 2)  # pixels per unit at depth 1
        cam.uc = cam.vc = 0.0
        cam.cx, cam.cy = size[0] / 2, size[1] / 2
        return cam

    def scaled(self, k: float) -> Camera:
        """The same camera for an image ``k`` times larger."""
        cam = Camera.__new__(Camera)
        cam.__dict__.update(self.__dict__)
        cam.scale, cam.cx, cam.cy = self.scale * k, self.cx * k, self.cy * k
        return cam

    def view(self, p: Any) -> np.ndarray:
        return (np.asarray(p, np.float64) - self.eye) @ self.R.T

    def project(self, p: Any) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """World points (..., 3) to pixel x, y and depth (larger is farther)."""
        v = self.view(p)
        if self.perspective:
            d = -v[..., 2]
            inv = 1.0 / np.where(d > 1e-6, d, np.nan)
            return self.cx + v[..., 0] * inv * self.scale, self.cy - v[..., 1] * inv * self.scale, d
        return self.cx + (v[..., 0] - self.uc) * self.scale, self.cy - (v[..., 1] - self.vc) * self.scale, -v[..., 2]

    def rays(self, px: np.ndarray, py: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Origins and unit directions (k, 3) of the rays through pixel positions ``px``, ``py``."""
        u = (px - self.cx) / self.scale
        v = -(py - self.cy) / self.scale
        if self.perspective:
            d = unit(np.stack([u, v, -np.ones_like(u)], -1)) @ self.R
            return np.broadcast_to(self.eye, d.shape), d
        o = np.stack([u + self.uc, v + self.vc, np.zeros_like(u)], -1) @ self.R
        return o, np.broadcast_to(-self.R[2], o.shape)

    def to_eye(self, p: np.ndarray) -> np.ndarray:
        if self.perspective:
            return unit(self.eye - p)
        return np.broadcast_to(self.R[2], p.shape)


def fit_bounds(points: Sequence[np.ndarray], margin: float = 0.05) -> np.ndarray:
    """The axis-aligned box around the finite ``points`` (arrays of (n, 3)), with a margin."""
    p = np.vstack([np.asarray(x, np.float64).reshape(-1, 3) for x in points]) if points else np.zeros((0, 3))
    p = p[np.isfinite(p).all(axis=1)]
    if not len(p):
        return np.array([[-1.0, -1.0, -1.0], [1.0, 1.0, 1.0]])
    lo, hi = p.min(0), p.max(0)
    ext = max(float((hi - lo).max()), 1e-6)
    return np.array([lo - margin * ext, hi + margin * ext])


def _background(h: int, w: int, light: Lighting) -> np.ndarray:
    top, bottom = linear(light.background_top), linear(light.background_bottom)
    f = np.linspace(0.0, 1.0, h)[:, None, None]
    return np.broadcast_to(top * (1 - f) + bottom * f, (h, w, 3)).astype(np.float32, order="C")


@dataclass
class _FloorLayer:
    """What does not change from frame to frame: the background with the lit floor (linear),
    and per floor pixel its index, world point and the colour a full shadow takes away."""

    image: np.ndarray
    pix: np.ndarray
    points: np.ndarray
    shadow: np.ndarray
    taps: Taps | None = None  # the points prepared for shadow lookups in a fixed map frame
    taps_key: Any = None


_FLOORS: dict[Any, _FloorLayer] = {}


def _floor_layer(
    cam: Camera, bounds: np.ndarray, h: int, w: int, light: Lighting, floor: bool, fade: bool, background: bool
) -> _FloorLayer:
    """The floor (the plane at the bottom of ``bounds``, over its x-z extent, its edge faded into
    the background with ``fade``) over the background, lit by the key light without shadows;
    cached by camera, bounds, size and lighting (animation frames share it)."""
    key = (
        cam.R.tobytes(),
        cam.eye.tobytes(),
        (cam.scale, cam.cx, cam.cy, cam.uc, cam.vc, cam.perspective),
        bounds.tobytes(),
        h,
        w,
        light,
        floor,
        fade,
        background,
    )
    if key in _FLOORS:
        return _FLOORS[key]
    img = _background(h, w, light) if background else np.ones((h, w, 3), np.float32)
    pix = np.zeros(0, np.int64)
    p = np.zeros((0, 3))
    delta = np.zeros((0, 3))
    if floor:
        pix = np.arange(h * w)
        o, d = cam.rays(pix % w + 0.5, pix // w + 0.5)
        y0 = float(bounds[0][1])
        with np.errstate(divide="ignore", invalid="ignore"):
            s = (y0 - o[:, 1]) / d[:, 1]
        hit = np.isfinite(s) & (s > 0)
        pix, s, o, d = pix[hit], s[hit], o[hit], d[hit]
        p = o + s[:, None] * d
        lo, hi = bounds[0], bounds[1]
        if fade:
            c = (lo + hi) / 2
            ext = np.array([hi[0] - lo[0], hi[2] - lo[2]]) / 2
            r = np.hypot((p[:, 0] - c[0]) / ext[0], (p[:, 2] - c[2]) / ext[1])
            alpha = np.clip((1.35 - r) / 0.55, 0, 1) ** 1.5
        else:
            inside = (p[:, 0] >= lo[0]) & (p[:, 0] <= hi[0]) & (p[:, 2] >= lo[2]) & (p[:, 2] <= hi[2])
            alpha = inside.astype(np.float64)
        keep = alpha > 0
        pix, p, alpha = pix[keep], p[keep], alpha[keep, None]
        tile = light.floor_tile
        odd = ((np.floor(p[:, 0] / tile) + np.floor(p[:, 2] / tile)) % 2).astype(bool)
        base = np.where(odd[:, None], linear(light.floor_alt), linear(light.floor))
        sun = light.key_strength * max(light.key_dir()[1], 0.0) * 0.42 * np.asarray(light.key_colour)
        col = base * (np.asarray(light.sky) + sun)
        flat = img.reshape(-1, 3)
        flat[pix] = flat[pix] * (1 - alpha) + col * alpha
        delta = alpha * base * sun * light.shadow
    layer = _FloorLayer(img, pix, p, delta)
    if len(_FLOORS) > 4:
        _FLOORS.clear()
    _FLOORS[key] = layer
    return layer


def _shade_meshes(
    img: np.ndarray,
    meshes: Sequence[Mesh],
    cam: Camera,
    light: Lighting,
    shadow: ShadowMap | None,
) -> np.ndarray:
    """Draw ``meshes`` into ``img`` (linear, h x w x 3); returns where something was drawn."""
    h, w = img.shape[:2]
    drawn = [m for m in meshes if len(m.triangles)]
    if not drawn:
        return np.zeros((h, w), bool)
    off = np.cumsum([0] + [len(m.positions) for m in drawn])[:-1]
    P = np.concatenate([m.positions for m in drawn])
    N = np.concatenate([m.normals for m in drawn]).astype(np.float32)
    F = np.concatenate([m.front for m in drawn]).astype(np.float32)
    B = np.concatenate([m.back for m in drawn]).astype(np.float32)
    T = np.concatenate([m.triangles + o for m, o in zip(drawn, off, strict=True)])
    per_tri = np.repeat(np.arange(len(drawn)), [len(m.triangles) for m in drawn])
    two = np.array([m.two_sided for m in drawn])[per_tri]
    spec = np.array([m.specular for m in drawn])[per_tri]
    shin = np.array([m.shininess for m in drawn])[per_tri]
    sheen = np.array([m.sheen for m in drawn])[per_tri]
    sx, sy, depth = cam.project(P)
    zbuf, tri, b1, b2 = rasterise(sx[T], sy[T], depth[T], w, h)
    pix = np.nonzero(tri >= 0)[0]
    if not len(pix):
        return np.zeros((h, w), bool)
    t = tri[pix]
    c = T[t]
    w1, w2 = b1[pix, None].astype(np.float32), b2[pix, None].astype(np.float32)
    w0 = 1 - w1 - w2

    def interp(a: np.ndarray) -> np.ndarray:
        return w0 * a[c[:, 0]] + w1 * a[c[:, 1]] + w2 * a[c[:, 2]]

    p = interp(P)
    n = unit(interp(N))
    v = cam.to_eye(p)
    facing = (n * v).sum(1)
    flip = two[t] & (facing < 0)
    n = np.where(flip[:, None], -n, n)
    front, back = interp(F), interp(B)
    mesh_of = per_tri[t]
    for i, m in enumerate(drawn):  # textures: colours per pixel from interpolated uv
        if m.texture is None or m.uv is None or len(m.uv) != len(m.positions):
            continue
        sel = mesh_of == i
        uv = np.zeros((len(P), 2))
        uv[off[i] : off[i] + len(m.positions)] = m.uv
        front[sel], back[sel] = m.texture(_interp_sel(uv, c[sel], w0[sel], w1[sel], w2[sel]))
    base = np.where(flip[:, None], back, front)
    key = light.key_dir()
    ndl = n @ key
    lit = shadow.lit(p, 0.03) if shadow is not None else np.ones(len(p))
    sun = 1 - light.shadow * (1 - lit)
    diffuse = np.maximum(ndl, 0) + np.where(two[t], light.translucency * np.maximum(-ndl, 0), 0.0)
    fill = np.maximum(n @ unit(np.asarray(light.fill, np.float64)), 0)
    up = 0.5 + 0.5 * n[:, 1]
    amb = up[:, None] * np.asarray(light.sky) + (1 - up[:, None]) * np.asarray(light.ground)
    hv = unit(key + v)
    s = spec[t] * np.maximum((n * hv).sum(1), 0) ** shin[t] * (ndl > 0) * lit
    kc = np.asarray(light.key_colour)
    col = base * (
        amb
        + (light.key_strength * diffuse * sun)[:, None] * kc
        + (light.fill_strength * fill)[:, None] * np.asarray(light.fill_colour)
    )
    col += (light.key_strength * s)[:, None] * kc
    col *= 1 + (sheen[t] * (1 - np.abs(facing)) ** 2)[:, None]
    img.reshape(-1, 3)[pix] = col * light.exposure
    mask = np.zeros(h * w, bool)
    mask[pix] = True
    return mask.reshape(h, w)


def _interp_sel(a: np.ndarray, c: np.ndarray, w0: np.ndarray, w1: np.ndarray, w2: np.ndarray) -> np.ndarray:
    return w0 * a[c[:, 0]] + w1 * a[c[:, 1]] + w2 * a[c[:, 2]]


def _font(px: int) -> Any:
    from PIL import ImageFont

    try:
        return ImageFont.load_default(size=px)
    except (TypeError, OSError):  # Pillow without FreeType: the fixed bitmap font
        return ImageFont.load_default()


def draw_scene(
    size: tuple[int, int],
    meshes: Sequence[Mesh],
    cam: Camera,
    *,
    bounds: Any,
    floor: bool = True,
    fade_floor: bool = False,
    shadows: bool = True,
    shadow_region: bool = False,
    lighting: Lighting = DEFAULT_LIGHTING,
    background: bool = True,
    supersample: float = 2.0,
    title: str | None = None,
    caption: str | None = None,
) -> np.ndarray:
    """``meshes`` seen by ``cam`` (made for an image of ``size``), the floor at the bottom of
    ``bounds``; a uint8 (h, w, 3) image, drawn ``supersample`` times larger (1.5, 2...) and scaled
    down. ``shadow_region``: the shadow map covers ``bounds`` (the same texels every frame, the
    floor's lookups prepared once: animation frames) rather than the meshes. ``title`` is written
    at the top centre, ``caption`` at the bottom left."""
    from PIL import Image, ImageDraw

    w, h = int(size[0]), int(size[1])
    wk, hk = max(w, round(w * supersample)), max(h, round(h * supersample))
    camk = cam.scaled(wk / w)
    b = np.asarray(bounds, np.float64).reshape(2, 3)
    layer = _floor_layer(camk, b, hk, wk, lighting, floor, fade_floor, background)
    img = layer.image.copy()
    smap = ShadowMap(meshes, lighting.key_dir(), region=b if shadow_region else None) if shadows else None
    drawn = _shade_meshes(img, meshes, camk, lighting, smap).ravel()
    if smap is not None and len(layer.pix):
        if layer.taps is None or layer.taps_key != smap.key:  # the floor's points, once per map frame
            layer.taps, layer.taps_key = smap.taps(layer.points, 0.01), smap.key
        lit = smap.lookup(layer.taps, len(layer.pix))
        dark = np.nonzero((lit < 1) & ~drawn[layer.pix])[0]
        img.reshape(-1, 3)[layer.pix[dark]] -= layer.shadow[dark] * (1 - lit[dark, None])
    out = Image.fromarray(srgb(img), "RGB")
    if (wk, hk) != (w, h):
        out = out.resize((w, h), Image.Resampling.LANCZOS)
    d = ImageDraw.Draw(out)
    if title:
        px = max(12, round(min(w, h) / 25))
        d.text((w / 2, 6), title, fill=(30, 34, 42), font=_font(px), anchor="mt")
    if caption:
        px = max(10, round(min(w, h) / 34))
        d.text((8, h - 6), caption, fill=(70, 74, 82), font=_font(px), anchor="lb")
    return np.asarray(out, np.uint8).copy()


def render_scene(
    size: tuple[int, int],
    cloths: Sequence[tuple[Any, ...]],
    *,
    view: str = "iso",
    bounds: Any = None,
    title: str | None = None,
    spheres: Sequence[Sequence[Any]] = (),
    capsules: Sequence[Sequence[Any]] = (),
    floor: bool = True,
    supersample: int = 2,
    shadows: bool = False,
) -> np.ndarray:
    """Render cloths ``(positions (n, 3), triangles (m, 3), colour[, back colour])`` with
    colliders, seen orthographically from ``view``.

    ``spheres`` are ``(centre, radius[, colour])`` and ``capsules`` ``(p0, p1, radius[, colour])``.
    ``bounds`` ``((xmin, ymin, zmin), (xmax, ymax, zmax))`` fixes the camera (steady animation
    frames); None fits the scene. The floor is the plane at the bottom of the bounds.
    Triangles with non-finite corners are skipped. Returns a uint8 (height, width, 3) array."""
    w, h = int(size[0]), int(size[1])
    if w < 1 or h < 1:
        raise ValueError(f"image size must be at least 1x1, got {w}x{h}")
    if view not in VIEWS:
        raise ValueError(f"view must be one of {sorted(VIEWS)}, got {view!r}")
    meshes = [cloth_mesh(c[0], c[1], c[2], c[3] if len(c) > 3 else None) for c in cloths]
    if bounds is None:
        pts = [m.positions for m in meshes]
        pts += [np.array([np.subtract(s[0], s[1]), np.add(s[0], s[1])]) for s in spheres]
        pts += [np.array([np.subtract(c[0], c[2]), np.add(c[1], c[2])]) for c in capsules]
        b = fit_bounds(pts)
    else:
        b = np.asarray(bounds, np.float64).reshape(2, 3)
    meshes += [sphere_mesh(s[0], float(s[1]), rgb(s[2]) if len(s) > 2 else COLLIDER) for s in spheres]
    meshes += [capsule_mesh(c[0], c[1], float(c[2]), rgb(c[3]) if len(c) > 3 else COLLIDER) for c in capsules]
    top = (max(12, round(min(w, h) / 25)) + 12) if title else 0
    pad = 6
    cam = Camera(view, b, (pad, top + pad, w - 1 - pad, h - 1 - pad))
    return draw_scene(
        (w, h),
        meshes,
        cam,
        bounds=b,
        floor=floor,
        shadows=shadows,
        background=False,
        supersample=supersample,
        title=title,
    )
