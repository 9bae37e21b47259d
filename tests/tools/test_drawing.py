"""The tools' drawing: matplotlib charts and the Pillow cloth renderer, checked by opening what
they write with Pillow (format, size, mode, frame count) and looking at the pixels."""

from __future__ import annotations

import numpy as np
import pytest
from PIL import Image

from drape.server.sim.fabric import grid_mesh
from drape.server.tools import imagefiles, plots, render


def _grid(cols: int = 12, rows: int = 9) -> tuple[np.ndarray, np.ndarray]:
    v, t = grid_mesh(cols, rows, width=1.0, height=0.8, orientation="vertical")
    return np.asarray(v, np.float32), np.asarray(t, np.int32)


def _png(path) -> np.ndarray:
    with Image.open(path) as im:
        assert im.format == "PNG"
        return np.asarray(im.convert("RGB"))


def test_histogram_line_and_scatter_plots(tmp_path, rng):
    v = rng.gamma(2.0, 1.0, 5000)
    p = plots.histogram(
        tmp_path / "h.png",
        np.append(v, np.nan),
        bins=40,
        title="latency",
        xlabel="ms",
        markers={"p50": float(np.median(v)), "p99": float(np.percentile(v, 99))},
    )
    img = _png(p)
    assert img.shape == (500, 800, 3)
    # the bars are tab:blue (31, 119, 180); the p99 line tab:orange
    assert np.count_nonzero(np.abs(img.astype(int) - (31, 119, 180)).sum(-1) < 30) > 2000
    assert np.count_nonzero(np.abs(img.astype(int) - (255, 127, 14)).sum(-1) < 40) > 50
    xs = np.arange(20.0)
    p = plots.line_plot(
        tmp_path / "l.png",
        {"a": (xs, xs**2), "budget": (xs, np.full(20, 50.0))},
        dashed=("budget",),
        logy=True,
        size=(640, 400),
    )
    assert _png(p).shape == (400, 640, 3)
    p = plots.scatter_plot(
        tmp_path / "s.png",
        {"one": ([1, 2, 3], [3, 2, 1]), "two": ([1, 10], [5, np.inf])},
        logx=True,
        logy=True,
        highlight=([1, 3], [3, 1]),
        highlight_label="front",
    )
    img = _png(p)
    assert img.shape == (640, 1000, 3) and img.std() > 5
    with pytest.raises(ValueError, match="differ in length"):
        plots.line_plot(tmp_path / "x.png", {"bad": ([1, 2], [1])})


def test_render_scene_draws_shaded_cloth_and_colliders():
    v, t = _grid()
    bounds = ((-0.5, -1.2, -0.5), (1.8, 0.3, 0.5))
    img = render.render_scene(
        (320, 200), [(v, t, (200, 60, 50))], view="front", bounds=bounds, floor=False, spheres=[((1.4, -0.4, 0.0), 0.2)]
    )
    assert img.shape == (200, 320, 3) and img.dtype == np.uint8
    red = (img[..., 0] > 100) & (img[..., 1] < 80) & (img[..., 2] < 80)
    grey = (np.abs(img[..., 0].astype(int) - img[..., 2]) < 20) & (img[..., 0] > 60) & (img[..., 0] < 230)
    assert red.sum() > 2000, "the cloth is drawn"
    assert grey.sum() > 200, "the sphere is drawn"
    # seen from the front, orthographic: the cloth (1.0 wide) left of the ball (0.4 wide), to scale
    red_cols, grey_cols = np.nonzero(red.any(axis=0))[0], np.nonzero(grey.any(axis=0))[0]
    assert red_cols[-1] < grey_cols[0]
    assert (red_cols[-1] - red_cols[0] + 1) / (grey_cols[-1] - grey_cols[0] + 1) == pytest.approx(2.5, rel=0.1)
    # a title is written across the top, in dark grey
    titled = render.render_scene((320, 200), [(v, t, (200, 60, 50))], view="front", bounds=bounds, title="Drape")
    assert (titled[:20].min(axis=2) < 100).sum() > 20 and (img[:20].min(axis=2) < 100).sum() == 0
    # the iso view with a floor differs, and non-finite vertices are skipped, not drawn
    v2 = v.copy()
    v2[5] = np.nan
    iso = render.render_scene((320, 200), [(v2, t, (70, 110, 200))], view="iso", bounds=bounds)
    assert not np.array_equal(iso, img)
    assert (iso[..., 2].astype(int) - iso[..., 0] > 50).sum() > 500


def test_render_scene_refuses_bad_input():
    v, t = _grid(4, 4)
    with pytest.raises(ValueError, match="out of range"):
        render.render_scene((64, 64), [(v, t + 100, (1, 2, 3))])
    with pytest.raises(ValueError, match="view must be one of"):
        render.render_scene((64, 64), [(v, t, (1, 2, 3))], view="nadir")
    with pytest.raises(ValueError, match="at least 1x1"):
        render.render_scene((0, 64), [(v, t, (1, 2, 3))])


def test_png_is_lossless_and_gif_keeps_every_frame(tmp_path):
    v, t = _grid()
    frames = []
    for k in range(6):
        w = v.copy()
        w[:, 2] += 0.1 * k * np.sin(3 * w[:, 0])
        frames.append(
            render.render_scene((160, 100), [(w, t, (120, 60, 160))], bounds=((-0.2, -1, -0.5), (1.2, 0.2, 0.5)))
        )
    p = imagefiles.write_png(tmp_path / "f.png", frames[3])
    assert np.array_equal(_png(p), frames[3])
    g = imagefiles.write_gif(tmp_path / "a.gif", frames, fps=10)
    with Image.open(g) as im:
        assert im.format == "GIF" and im.size == (160, 100) and im.n_frames == 6
        assert im.info["duration"] == 100 and im.info["loop"] == 0
        im.seek(5)
        last = np.asarray(im.convert("RGB")).astype(int)
    # one shared palette of 128 colours, no dithering: close to the frame
    assert np.abs(last - frames[5]).mean() < 6
    with pytest.raises(ValueError, match="at least one frame"):
        imagefiles.write_gif(tmp_path / "none.gif", [])


def test_a_ball_through_a_cloth_meets_it_along_their_intersection():
    """A depth buffer, not a painter's order: a ball whose centre is 0.1 behind a cloth of 0.2
    radius shows the disc of its front cap only (radius sqrt(0.2^2 - 0.1^2): 75 % of its area),
    cut by a circle, not drawn whole or hidden whole."""
    v, t = _grid(24, 18)
    v[:, 0] -= 0.5
    v[:, 1] += 0.4  # the cloth spans x -0.5..0.5, y -0.4..0.4, at z = 0
    bounds = ((-0.6, -0.5, -0.5), (0.6, 0.5, 0.5))
    size = (240, 200)

    def ball_pixels(z: float, cloth: bool) -> int:
        img = render.render_scene(
            size,
            [(v, t, (40, 60, 200))] if cloth else [],
            view="front",
            bounds=bounds,
            floor=False,
            spheres=[((0.0, 0.0, z), 0.2, (200, 200, 40))],
        )
        rgb = img.astype(int)
        return int(((rgb[..., 0] > 60) & (rgb[..., 0] - rgb[..., 2] > 60)).sum())  # yellow, lit or not

    whole = ball_pixels(-0.1, cloth=False)
    assert whole > 1000
    assert ball_pixels(-0.1, cloth=True) / whole == pytest.approx(0.75, abs=0.06)
    assert ball_pixels(0.25, cloth=True) / whole == pytest.approx(1.0, abs=0.02)  # all in front
    assert ball_pixels(-0.25, cloth=True) == 0  # all behind


def test_smooth_shading_has_no_steps_at_the_triangle_edges():
    """A cloth bent into a quarter cylinder about the vertical axis, 7 columns (15 degrees a
    column), seen from the front: per-vertex normals interpolated per pixel change the shade a
    little from pixel to pixel. The same triangles each with vertices of their own (one normal a
    triangle: flat shading) step at every column."""
    cols, rows = 7, 9
    v, t = _grid(cols, rows)
    a = np.radians(-45 + 90 * (np.arange(len(v)) % cols) / (cols - 1))
    v[:, 0], v[:, 2] = np.sin(a), np.cos(a) - 1
    bounds = ((-0.8, -1.0, -1), (0.8, 0.1, 0.1))

    def steps(pos: np.ndarray, tris: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        img = render.render_scene((400, 300), [(pos, tris, (180, 180, 180))], view="front", bounds=bounds, floor=False)
        grey = img.astype(int).mean(axis=2)
        row = grey[150]
        inside = np.nonzero(row < 240)[0]  # the cloth on this row (the background is near white)
        assert len(inside) > 150 and row[inside].max() - row[inside].min() > 20  # lit unevenly, as it should be
        column = grey[40:260, 200]  # down the middle
        down = column[np.nonzero(column < 240)[0][3:-3]]
        return np.abs(np.diff(row[inside[0] + 3 : inside[-1] - 3])), np.abs(np.diff(down))

    across, down = steps(v, t)
    assert across.max() <= 3, f"a step of {across.max()} grey levels between neighbouring pixels"
    assert down.max() <= 1  # the same normal all the way down: no diagonal stripes
    flat_across, _ = steps(v[t].reshape(-1, 3), np.arange(3 * len(t)).reshape(-1, 3))
    assert flat_across.max() >= 8, "the flat-shaded control does step"
