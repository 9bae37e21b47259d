"""Shaded 3-D pictures of cloths for ``drape demo``, drawn with Pillow: an orthographic camera,
triangles and collider balls sorted back to front (painter's algorithm) and lit by one
directional light with ambient, a floor grid, a title; frames written as PNG and as an animated
GIF with one palette shared by all frames.

The geometry (camera, depth order, shading) is numpy; Pillow draws the polygons, pastes the lit
ball sprites and encodes the files. Pillow is imported inside the functions (the ``tools``
extra).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from functools import lru_cache
from pathlib import Path
from typing import Any

import numpy as np

Colour = tuple[int, int, int]


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
LIGHT = np.array([-0.35, 0.55, 0.76]) / np.linalg.norm([-0.35, 0.55, 0.76])  # in view space
AMBIENT = 0.3
COLLIDER: Colour = (165, 160, 150)
FLOOR: Colour = (238, 238, 234)
FLOOR_GRID: Colour = (205, 205, 200)
FLOOR_EDGE: Colour = (150, 150, 145)


class Camera:
    """Orthographic projection fitting the world box ``bounds`` into the pixel rectangle ``rect``."""

    def __init__(self, view: str, bounds: np.ndarray, rect: tuple[float, float, float, float]) -> None:
        if view not in VIEWS:
            raise ValueError(f"view must be one of {sorted(VIEWS)}, got {view!r}")
        self.R = VIEWS[view]
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

    def view(self, p: Any) -> np.ndarray:
        return np.asarray(p, np.float64) @ self.R.T

    def screen(self, v: np.ndarray) -> np.ndarray:
        """View coordinates (..., 3) to pixels (..., 2)."""
        return np.stack(
            [self.cx + (v[..., 0] - self.uc) * self.scale, self.cy - (v[..., 1] - self.vc) * self.scale], axis=-1
        )


def fit_bounds(points: Sequence[np.ndarray], margin: float = 0.05) -> np.ndarray:
    """The axis-aligned box around the finite ``points`` (arrays of (n, 3)), with a margin."""
    p = np.vstack([np.asarray(x, np.float64).reshape(-1, 3) for x in points]) if points else np.zeros((0, 3))
    p = p[np.isfinite(p).all(axis=1)]
    if not len(p):
        return np.array([[-1.0, -1.0, -1.0], [1.0, 1.0, 1.0]])
    lo, hi = p.min(0), p.max(0)
    ext = max(float((hi - lo).max()), 1e-6)
    return np.array([lo - margin * ext, hi + margin * ext])


def _rgb(c: Sequence[int]) -> Colour:
    return int(c[0]), int(c[1]), int(c[2])


def shade(colour: Sequence[int], intensity: np.ndarray) -> np.ndarray:
    """``colour`` scaled by each intensity in [0, 1], as uint8 (n, 3)."""
    base = np.asarray(colour, np.float64)[:3]
    return np.clip(base[None, :] * np.asarray(intensity, np.float64)[:, None], 0, 255).astype(np.uint8)


@lru_cache(maxsize=256)
def _ball_sprite(r_px: int, colour: Colour) -> Any:
    """A lit ball of radius ``r_px`` pixels as an RGBA image (per-pixel Lambert with ambient,
    anti-aliased rim)."""
    from PIL import Image

    n = 2 * r_px + 3
    yy, xx = np.mgrid[0:n, 0:n].astype(np.float64)
    nx = (xx - (n - 1) / 2) / r_px
    ny = -(yy - (n - 1) / 2) / r_px
    d = np.sqrt(nx**2 + ny**2)
    nz = np.sqrt(np.clip(1 - d**2, 0, 1))
    lam = np.clip(nx * LIGHT[0] + ny * LIGHT[1] + nz * LIGHT[2], 0, 1)
    rgb = shade(colour, (AMBIENT + (1 - AMBIENT) * lam).ravel()).reshape(n, n, 3)
    alpha = (np.clip((1.0 - d) * r_px + 0.5, 0, 1) * 255).astype(np.uint8)
    return Image.fromarray(np.dstack([rgb, alpha]), "RGBA")


def _font(px: int) -> Any:
    from PIL import ImageFont

    try:
        return ImageFont.load_default(size=px)
    except (TypeError, OSError):  # Pillow without FreeType: the fixed bitmap font
        return ImageFont.load_default()


def _draw_floor(draw: Any, cam: Camera, bounds: np.ndarray, y: float, width: int) -> None:
    lo, hi = bounds
    corners = np.array([[lo[0], y, lo[2]], [hi[0], y, lo[2]], [hi[0], y, hi[2]], [lo[0], y, hi[2]]])
    sc = cam.screen(cam.view(corners))
    draw.polygon([tuple(p) for p in sc.tolist()], fill=FLOOR)
    ext = float(max(hi[0] - lo[0], hi[2] - lo[2]))
    step = 10 ** math.floor(math.log10(ext / 8)) if ext > 0 else 1.0
    step *= next(m for m in (1, 2, 5, 10) if ext / (step * m) <= 8)
    segs = [[[x, y, lo[2]], [x, y, hi[2]]] for x in np.arange(math.ceil(lo[0] / step) * step, hi[0] + 1e-9, step)]
    segs += [[[lo[0], y, z], [hi[0], y, z]] for z in np.arange(math.ceil(lo[2] / step) * step, hi[2] + 1e-9, step)]
    for a, b in cam.screen(cam.view(np.array(segs))).tolist() if segs else []:
        draw.line([tuple(a), tuple(b)], fill=FLOOR_GRID, width=width)
    draw.line([tuple(p) for p in sc.tolist()] + [tuple(sc[0].tolist())], fill=FLOOR_EDGE, width=width)


def render_scene(
    size: tuple[int, int],
    cloths: Sequence[tuple[Any, Any, Sequence[int]]],
    *,
    view: str = "iso",
    bounds: Any = None,
    title: str | None = None,
    spheres: Sequence[Sequence[Any]] = (),
    capsules: Sequence[Sequence[Any]] = (),
    floor: bool = True,
    supersample: int = 2,
) -> np.ndarray:
    """Render cloths ``(positions (n, 3), triangles (m, 3), colour)`` with colliders.

    ``spheres`` are ``(centre, radius[, colour])`` and ``capsules`` ``(p0, p1, radius[, colour])``
    (drawn as balls along the axis); they are depth-sorted with the cloth triangles. ``bounds``
    ``((xmin, ymin, zmin), (xmax, ymax, zmax))`` fixes the camera (steady animation frames); None
    fits the scene. The floor is the plane at the bottom of the bounds. ``supersample`` renders
    larger and scales down (smooth edges). Triangles with non-finite corners are skipped.
    Returns a uint8 (height, width, 3) array."""
    from PIL import Image, ImageDraw

    w, h = int(size[0]), int(size[1])
    if w < 1 or h < 1:
        raise ValueError(f"image size must be at least 1x1, got {w}x{h}")
    k = max(1, int(supersample))
    cl = []
    for pos, tris, colour in cloths:
        p = np.asarray(pos, np.float64).reshape(-1, 3)
        t = np.asarray(tris, np.int64).reshape(-1, 3)
        if len(t) and (t.min() < 0 or t.max() >= len(p)):
            raise ValueError(f"triangle indices out of range for {len(p)} positions")
        cl.append((p, t, _rgb(colour)))
    if bounds is None:
        pts = [p for p, _, _ in cl] + [np.array([np.subtract(s[0], s[1]), np.add(s[0], s[1])]) for s in spheres]
        pts += [np.array([np.subtract(c[0], c[2]), np.add(c[1], c[2])]) for c in capsules]
        b = fit_bounds(pts)
    else:
        b = np.asarray(bounds, np.float64).reshape(2, 3)
    title_px = max(12, round(min(w, h) / 25)) if title else 0
    top = (title_px + 12) if title else 0
    pad = 6
    cam = Camera(view, b, (pad * k, (top + pad) * k, (w - 1 - pad) * k, (h - 1 - pad) * k))
    img = Image.new("RGB", (w * k, h * k), (255, 255, 255))
    draw = ImageDraw.Draw(img)
    if floor:
        _draw_floor(draw, cam, b, float(b[0][1]), k)

    # every primitive gets a depth (view z: larger is nearer); draw far to near
    scr, col, dep = [], [], []
    for p, t, colour in cl:
        if not len(t):
            continue
        v = cam.view(p)[t]
        v = v[np.isfinite(v).all(axis=(1, 2))]
        nrm = np.cross(v[:, 1] - v[:, 0], v[:, 2] - v[:, 0])
        ln = np.linalg.norm(nrm, axis=1)
        lam = np.abs(nrm @ LIGHT) / np.where(ln > 0, ln, 1)  # two-sided cloth
        scr.append(cam.screen(v))
        col.append(shade(colour, AMBIENT + (1 - AMBIENT) * lam))
        dep.append(v[:, :, 2].mean(axis=1))
    balls: list[tuple[np.ndarray, float, Colour]] = []
    for s in spheres:
        balls.append((cam.view(s[0]), float(s[1]), _rgb(s[2]) if len(s) > 2 else COLLIDER))
    for c in capsules:
        a, bb, r = cam.view(c[0]), cam.view(c[1]), float(c[2])
        colour = _rgb(c[3]) if len(c) > 3 else COLLIDER
        n = int(min(400, max(2, math.ceil(np.linalg.norm((bb - a)[:2]) * cam.scale / max(0.15 * r * cam.scale, 0.5)))))
        balls += [(a + f * (bb - a), r, colour) for f in np.linspace(0, 1, n)]
    ts = np.concatenate(scr) if scr else np.zeros((0, 3, 2))
    tc = np.concatenate(col) if col else np.zeros((0, 3), np.uint8)
    td = np.concatenate(dep) if dep else np.zeros(0)
    bd = np.array([bl[0][2] for bl in balls]) if balls else np.zeros(0)
    order = np.argsort(np.concatenate([td, bd]), kind="stable")
    tri_pts, tri_col = ts.tolist(), tc.tolist()
    nt = len(td)
    for i in order.tolist():
        if i < nt:
            poly = [tuple(q) for q in tri_pts[i]]
            c = tuple(tri_col[i])
            draw.polygon(poly, fill=c, outline=c)  # the outline closes hairline seams
        else:
            centre, r, colour = balls[i - nt]
            sx, sy = cam.screen(centre).tolist()
            rp = max(1, round(r * cam.scale))
            sprite = _ball_sprite(rp, colour)
            img.paste(sprite, (round(sx) - rp - 1, round(sy) - rp - 1), sprite)
    if k > 1:
        img = img.resize((w, h), Image.Resampling.LANCZOS)
    if title:
        d = ImageDraw.Draw(img)
        d.text((w / 2, 6), title, fill=(20, 20, 20), font=_font(title_px), anchor="mt")
    return np.asarray(img, np.uint8).copy()


def write_png(path: str | Path, rgb: np.ndarray) -> Path:
    """Write a uint8 (H, W, 3) image as PNG."""
    from PIL import Image

    p = Path(path)
    p.parent.mkdir(parents=True, exist_ok=True)
    Image.fromarray(np.ascontiguousarray(rgb, np.uint8), "RGB").save(p, optimize=True)
    return p


def write_gif(
    path: str | Path, frames: Sequence[np.ndarray], fps: float = 15.0, colours: int = 128, dither: bool = False
) -> Path:
    """Write uint8 (H, W, 3) frames as a looping GIF. One palette of ``colours`` colours, made
    from a few frames spread over the animation, is used for every frame (no flicker); frames
    are mapped to it without dithering unless ``dither`` (dithering triples the file size)."""
    from PIL import Image

    if not len(frames):
        raise ValueError("a GIF needs at least one frame")
    imgs = [Image.fromarray(np.ascontiguousarray(f, np.uint8), "RGB") for f in frames]
    picks = np.linspace(0, len(imgs) - 1, min(len(imgs), 6)).round().astype(int)
    w, h = imgs[0].size
    sheet = Image.new("RGB", (w, h * len(picks)))
    for j, i in enumerate(picks.tolist()):
        sheet.paste(imgs[i], (0, j * h))
    palette = sheet.quantize(colors=colours, method=Image.Quantize.MEDIANCUT)
    mode = Image.Dither.FLOYDSTEINBERG if dither else Image.Dither.NONE
    pal = [im.quantize(palette=palette, dither=mode) for im in imgs]
    p = Path(path)
    p.parent.mkdir(parents=True, exist_ok=True)
    pal[0].save(p, save_all=True, append_images=pal[1:], duration=round(1000 / fps), loop=0, optimize=False, disposal=1)
    return p
