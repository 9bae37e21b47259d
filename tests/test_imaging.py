"""Tests of server/imaging.py: PNG and GIF writers checked with decoders written here (zlib for
PNG, an independent LZW decoder for GIF), the font, the canvas, plots and the cloth renderer."""

from __future__ import annotations

import importlib.util
import struct
import sys
import zlib
from pathlib import Path

import numpy as np
import pytest

try:
    from drape.server.tools import imaging as im
except ImportError:  # not installed: load the module straight from the source tree
    _path = Path(__file__).resolve().parents[1] / "server" / "imaging.py"
    _spec = importlib.util.spec_from_file_location("drape_imaging_under_test", _path)
    im = importlib.util.module_from_spec(_spec)
    sys.modules[_spec.name] = im
    _spec.loader.exec_module(im)


# ----------------------------------------------------------------------------------------------
# A small PNG decoder (8-bit RGB/RGBA, filter type 0), checking every CRC.


def png_chunks(data: bytes) -> list[tuple[bytes, bytes]]:
    assert data[:8] == b"\x89PNG\r\n\x1a\n", "bad PNG signature"
    out, pos = [], 8
    while pos < len(data):
        (n,) = struct.unpack(">I", data[pos : pos + 4])
        tag = data[pos + 4 : pos + 8]
        body = data[pos + 8 : pos + 8 + n]
        (crc,) = struct.unpack(">I", data[pos + 8 + n : pos + 12 + n])
        assert crc == zlib.crc32(tag + body) & 0xFFFFFFFF, f"bad CRC in {tag!r}"
        out.append((tag, body))
        pos += 12 + n
    assert pos == len(data)
    return out


def decode_png(data: bytes) -> np.ndarray:
    chunks = png_chunks(data)
    assert chunks[0][0] == b"IHDR" and chunks[-1] == (b"IEND", b"")
    w, h, depth, ctype, comp, filt, interlace = struct.unpack(">IIBBBBB", chunks[0][1])
    assert (depth, comp, filt, interlace) == (8, 0, 0, 0)
    channels = {2: 3, 6: 4}[ctype]
    raw = zlib.decompress(b"".join(body for tag, body in chunks if tag == b"IDAT"))
    stride = 1 + w * channels
    assert len(raw) == h * stride
    rows = np.frombuffer(raw, np.uint8).reshape(h, stride)
    assert (rows[:, 0] == 0).all(), "only filter type 0 is expected"
    return rows[:, 1:].reshape(h, w, channels)


# ----------------------------------------------------------------------------------------------
# A GIF decoder, written independently of the encoder: byte-string LZW table, frames composed
# with transparency and "do not dispose".


def lzw_decode(data: bytes, min_size: int) -> tuple[bytes, int]:
    """Decode a GIF LZW stream; returns the pixels and the number of clear codes seen."""
    clear, eoi = 1 << min_size, (1 << min_size) + 1
    bitpos, nbits = 0, len(data) * 8
    value = int.from_bytes(data, "little")
    size = min_size + 1
    table: list[bytes] = []
    prev: bytes | None = None
    out = bytearray()
    clears = 0

    def reset() -> None:
        nonlocal table, size, prev
        table = [bytes([i]) for i in range(clear)] + [b"", b""]
        size, prev = min_size + 1, None

    reset()
    while True:
        assert bitpos + size <= nbits, "stream ended without an end code"
        code = (value >> bitpos) & ((1 << size) - 1)
        bitpos += size
        if code == clear:
            clears += 1
            reset()
            continue
        if code == eoi:
            break
        if prev is None:
            entry = table[code]
        else:
            if code < len(table):
                entry = table[code]
            else:
                assert code == len(table), f"code {code} beyond table {len(table)}"
                entry = prev + prev[:1]
            if len(table) < 4096:
                table.append(prev + entry[:1])
                if len(table) == (1 << size) and size < 12:
                    size += 1
        out += entry
        prev = entry
    return bytes(out), clears


def decode_gif(data: bytes) -> dict:
    assert data[:6] == b"GIF89a"
    w, h, packed, _bg, _aspect = struct.unpack("<HHBBB", data[6:13])
    pos = 13
    assert packed & 0x80, "expected a global colour table"
    n_colors = 2 ** ((packed & 7) + 1)
    palette = np.frombuffer(data[pos : pos + 3 * n_colors], np.uint8).reshape(-1, 3)
    pos += 3 * n_colors
    screen = np.zeros((h, w, 3), np.uint8)
    frames, delays, clears = [], [], []
    loop = None
    gce = {"transparent": None, "delay": 0, "disposal": 0}

    def read_blocks(p: int) -> tuple[bytes, int]:
        out = bytearray()
        while data[p]:
            out += data[p + 1 : p + 1 + data[p]]
            p += 1 + data[p]
        return bytes(out), p + 1

    while True:
        tag = data[pos]
        if tag == 0x3B:
            break
        if tag == 0x21:
            label = data[pos + 1]
            body, pos = read_blocks(pos + 2)
            if label == 0xF9:
                flags, delay, tindex = struct.unpack("<BHB", body[:4])
                gce = {"transparent": tindex if flags & 1 else None, "delay": delay, "disposal": (flags >> 2) & 7}
            elif label == 0xFF and body[:11] == b"NETSCAPE2.0":
                loop = struct.unpack("<H", body[12:14])[0]  # sub-blocks joined: id, 0x01, count
            continue
        assert tag == 0x2C, f"unexpected block 0x{tag:02x}"
        x0, y0, fw, fh, fpacked = struct.unpack("<HHHHB", data[pos + 1 : pos + 10])
        assert fpacked == 0, "no local tables or interlace expected"
        assert x0 + fw <= w and y0 + fh <= h
        min_size = data[pos + 10]
        stream, pos = read_blocks(pos + 11)
        pixels, n_clear = lzw_decode(stream, min_size)
        assert len(pixels) == fw * fh
        idx = np.frombuffer(pixels, np.uint8).reshape(fh, fw)
        region = screen[y0 : y0 + fh, x0 : x0 + fw]
        opaque = np.ones_like(idx, bool) if gce["transparent"] is None else idx != gce["transparent"]
        region[opaque] = palette[idx[opaque]]
        assert gce["disposal"] in (0, 1)
        frames.append(screen.copy())
        delays.append(gce["delay"])
        clears.append(n_clear)
    return {"size": (w, h), "frames": frames, "delays": delays, "loop": loop, "clears": clears, "palette": palette}


def test_lzw_round_trip_edge_cases():
    """Lengths and alphabets that land the code-width changes, the end code and table resets
    on every boundary."""
    rng = np.random.default_rng(0)
    cases = [b"", b"\x00", b"\x07" * 5000, bytes(range(256)) * 40]
    cases += [
        rng.integers(0, k, n, dtype=np.uint8).tobytes() for k in (2, 3, 17, 256) for n in (1, 2, 3, 255, 256, 257, 700)
    ]
    cases += [rng.integers(0, 256, n, dtype=np.uint8).tobytes() for n in range(240, 300)]
    cases += [rng.integers(0, 256, 9000, dtype=np.uint8).tobytes()]  # several 12-bit resets
    for data in cases:
        out, clears = lzw_decode(im._lzw_encode(data, 8), 8)
        assert out == data
    assert clears >= 3


# ----------------------------------------------------------------------------------------------
# PNG


@pytest.mark.parametrize("channels", [3, 4])
def test_png_round_trip(tmp_path, channels):
    rng = np.random.default_rng(1)
    img = rng.integers(0, 256, (37, 53, channels), dtype=np.uint8)
    path = im.write_png(tmp_path / "sub" / "a.png", img)
    data = path.read_bytes()
    assert [tag for tag, _ in png_chunks(data)] == [b"IHDR", b"IDAT", b"IEND"]
    np.testing.assert_array_equal(decode_png(data), img)
    assert im.encode_png(img) == data


def test_png_crc_and_inputs():
    data = im.encode_png(np.zeros((2, 3, 3), np.uint8))
    # flip one bit of the IDAT payload: the CRC check must notice
    bad = bytearray(data)
    bad[8 + 25 + 8 + 2] ^= 1
    with pytest.raises(AssertionError, match="CRC"):
        png_chunks(bytes(bad))
    grey = np.arange(12, dtype=np.uint8).reshape(3, 4)
    np.testing.assert_array_equal(decode_png(im.encode_png(grey))[:, :, 1], grey)
    c = im.Canvas(5, 4)
    np.testing.assert_array_equal(decode_png(im.encode_png(c)), np.full((4, 5, 3), 255))
    with pytest.raises(ValueError):
        im.encode_png(np.zeros((4, 4, 3), np.float32))
    with pytest.raises(ValueError):
        im.encode_png(np.zeros((4, 4, 2), np.uint8))
    with pytest.raises(ValueError):
        im.encode_png(np.zeros((0, 4, 3), np.uint8))


# ----------------------------------------------------------------------------------------------
# GIF

STEPS = np.array([255 / 5, 255 / 6, 255 / 5])  # palette cube spacing per channel


def _test_frames() -> list[np.ndarray]:
    h, w = 48, 64
    yy, xx = np.mgrid[0:h, 0:w]
    frames = []
    for k in range(6):
        f = np.stack([xx * 4, yy * 5, (xx + yy + 20 * k) % 256], axis=-1).astype(np.uint8)
        f[10:20, 5 + 6 * k : 15 + 6 * k] = (250, 30, 40)  # a moving square
        frames.append(f)
    frames.append(frames[-1].copy())  # an unchanged frame
    return frames


@pytest.mark.parametrize("dither", [False, True])
def test_gif_round_trip(tmp_path, dither):
    frames = _test_frames()
    path = im.write_gif(tmp_path / "a.gif", frames, fps=20, dither=dither)
    g = decode_gif(path.read_bytes())
    assert g["size"] == (64, 48)
    assert len(g["frames"]) == len(frames)
    assert g["loop"] == 0  # forever
    assert g["delays"] == [5] * len(frames)
    limit = np.ceil(STEPS if dither else STEPS / 2)  # one palette step, or half of one
    for src, got in zip(frames, g["frames"]):
        np.testing.assert_array_equal(got, im.GIF_PALETTE[im.quantize(src, dither)])
        err = np.abs(got.astype(int) - src.astype(int)).max(axis=(0, 1))
        assert (err <= limit).all(), err
    # a flat colour keeps its average (dithering mixes neighbouring palette entries)
    square = g["frames"][0][10:18, 6:14].reshape(-1, 3).mean(axis=0)
    assert (np.abs(square - (250, 30, 40)) <= STEPS / 2).all(), square


def test_gif_noise_uses_table_resets_and_options():
    rng = np.random.default_rng(2)
    frames = [rng.integers(0, 256, (90, 120, 3), dtype=np.uint8) for _ in range(2)]
    g = decode_gif(im.encode_gif(frames, fps=30, loop=False, dither=False))
    assert g["loop"] is None
    assert max(g["clears"]) > 1  # the 4096-entry table filled and was reset mid-frame
    for src, got in zip(frames, g["frames"]):
        np.testing.assert_array_equal(got, im.GIF_PALETTE[im.quantize(src, False)])
    assert sum(g["delays"]) == round(100 * 2 / 30) and min(g["delays"]) >= 2
    one = decode_gif(im.encode_gif([np.zeros((1, 1, 3), np.uint8)]))
    assert one["size"] == (1, 1) and len(one["frames"]) == 1
    with pytest.raises(ValueError):
        im.encode_gif([])
    with pytest.raises(ValueError):
        im.encode_gif([np.zeros((4, 4, 3), np.uint8), np.zeros((4, 5, 3), np.uint8)])


def test_palette_and_quantize():
    assert im.GIF_PALETTE.shape == (256, 3) and im.GIF_PALETTE.dtype == np.uint8
    assert len({tuple(c) for c in im.GIF_PALETTE[:252]}) == 252
    q = im.quantize(np.array([[[255, 255, 255], [0, 0, 0], [255, 0, 0]]], np.uint8))
    np.testing.assert_array_equal(im.GIF_PALETTE[q[0]], [[255, 255, 255], [0, 0, 0], [255, 0, 0]])
    assert q.max() < im.TRANSPARENT_INDEX


# ----------------------------------------------------------------------------------------------
# Font and canvas

WHITE = np.array([255, 255, 255])


def ink(a: np.ndarray) -> np.ndarray:
    return (a != 255).any(axis=-1)


def test_font_covers_printable_ascii():
    for code in range(32, 127):
        g = im.FONT[chr(code)]
        assert g.shape == (im.GLYPH_HEIGHT, im.GLYPH_WIDTH)
        assert g.any() == (code != 32), chr(code)
    digits = {im.FONT[d].tobytes() for d in "0123456789"}
    letters = {im.FONT[ch].tobytes() for ch in "ABCDEFGHIJKLMNOPQRSTUVWXYZabcdefghijklmnopqrstuvwxyz"}
    assert len(digits) == 10 and len(letters) == 52


def test_draw_text():
    c = im.Canvas(120, 40)
    x0, y0, x1, y1 = im.draw_text(c, 3, 4, "p99 = 1.5ms", (200, 0, 0))
    m = ink(c.array)
    assert m.any() and not m[:, :x0].any() and not m[:y0].any() and not m[:, x1:].any() and not m[y1:].any()
    assert (c.array[m] == (200, 0, 0)).all()
    assert (x1 - x0, y1 - y0) == im.text_size("p99 = 1.5ms")
    w1, h1 = im.text_size("Hi")
    assert im.text_size("Hi", 3) == (3 * w1, 3 * h1)
    arr = np.full((30, 30, 3), 255, np.uint8)
    im.draw_text(arr, 15, 15, "\u00b5?", 0, anchor="mc")  # non-ASCII draws as '?'
    assert ink(arr).any()
    big = im.Canvas(40, 120)
    x0, y0, x1, y1 = big.text(2, 60, "vertical", scale=2, anchor="tc", angle=90)
    assert y1 - y0 > x1 - x0 and ink(big.array).any()
    c2 = im.Canvas(10, 10)
    c2.text(-50, -50, "clipped away", 0)
    c2.text(5, 5, "clipped", 0)  # partly off the canvas: no error
    assert ink(c2.array).any()


def test_canvas_primitives():
    c = im.Canvas(50, 40)
    assert c.array.shape == (40, 50, 3) and (c.array == 255).all()
    c.line(2, 3, 40, 30, (0, 0, 255))
    assert tuple(c.array[3, 2]) == (0, 0, 255) and tuple(c.array[30, 40]) == (0, 0, 255)
    assert ink(c.array).sum() == 39  # one pixel per step along the major axis
    c.line(-1e6, -1e6, 1e6, 1e6, 0, width=3)  # far outside: clipped, not rasterised
    c.line(0, 0, np.nan, 5, 0)  # ignored
    c.rect(1, 1, 10, 10, (0, 200, 0))
    assert tuple(c.array[1, 5]) == (0, 200, 0) and tuple(c.array[3, 8]) == (255, 255, 255)
    c.fill_rect(20, 20, 24, 22, (9, 9, 9))
    assert (c.array[20:23, 20:25] == 9).all()
    c.dot(40, 10, 3, (1, 2, 3))
    assert tuple(c.array[10, 40]) == (1, 2, 3) and tuple(c.array[10, 43]) == (1, 2, 3)
    c.circle(10, 30, 5, (4, 5, 6))
    assert tuple(c.array[30, 15]) == (4, 5, 6) and tuple(c.array[30, 10]) != (4, 5, 6)
    c.polyline([(0, 39), (10, 35), (20, 39)], (7, 7, 7), width=2)
    assert (c.array == 7).all(axis=-1).sum() > 20
    c.markers(np.array([30.0, np.nan]), np.array([30.0, 1.0]), (8, 8, 8), "^", 3)
    assert tuple(c.array[30, 30]) == (8, 8, 8)


def test_triangle_fill_and_painter():
    c = im.Canvas(40, 40)
    c.triangle_fill((5, 5), (35, 5), (5, 35), (255, 0, 0))
    assert tuple(c.array[10, 10]) == (255, 0, 0)
    assert tuple(c.array[34, 34]) == (255, 255, 255)
    # two triangles sharing a diagonal cover the whole square, no cracks
    c = im.Canvas(40, 40)
    tris = np.array([[(0, 0), (39, 0), (39, 39)], [(0, 0), (39, 39), (0, 39)]], float) + 0.3
    c.triangles_fill(tris, np.array([[10, 10, 10], [20, 20, 20]]))
    assert not (c.array[1:, 1:] == 255).all(axis=-1).any()
    # later triangles win
    c.triangle_fill((-100, -100), (200, -100), (-100, 200), (1, 1, 1))
    assert (c.array == 1).all()
    c.triangle_fill((0, 0), (10, 10), (20, 20), (2, 2, 2))  # degenerate: nothing
    assert (c.array == 1).all()
    with c.clip(0, 0, 9, 9):
        c.fill_rect(0, 0, 39, 39, (3, 3, 3))
    assert (c.array[:10, :10] == 3).all() and (c.array[10:] == 1).all()


# ----------------------------------------------------------------------------------------------
# Plots


def plot_ok(path: Path, size=(800, 500), min_ink: float = 0.01) -> np.ndarray:
    img = decode_png(path.read_bytes())
    assert img.shape == (size[1], size[0], 3)
    assert ink(img).mean() > min_ink  # more than a blank page
    return img


def has_color(img: np.ndarray, color) -> int:
    return int((img == np.array(color)).all(axis=-1).sum())


def test_nice_ticks():
    t, step = im.nice_ticks(0.0, 1.0, 5)
    np.testing.assert_allclose(t, [0, 0.2, 0.4, 0.6, 0.8, 1.0])
    t, step = im.nice_ticks(-3.7, 1234.5, 6)
    assert step == 250 and t[0] == 0 and t[-1] == 1000
    for lo, hi in [(0.001, 0.0042), (17, 93), (-1e6, 3e6), (5, 5.0001)]:
        t, step = im.nice_ticks(lo, hi)
        m = step / 10 ** np.floor(np.log10(step))
        assert min(abs(m - k) for k in (1, 2, 2.5, 5, 10)) < 1e-9
        assert lo - 1e-12 <= t[0] and t[-1] <= hi + 1e-12 and len(t) >= 2


def test_line_plot(tmp_path):
    x = np.linspace(0, 10, 30)
    img = im.line_plot(tmp_path / "l.png", {"sin": (x, np.sin(x)), "cos": (x, np.cos(x))}, "Waves", "x [s]", "y")
    png = plot_ok(tmp_path / "l.png")
    np.testing.assert_array_equal(img, png)
    assert has_color(png, im.PALETTE[0]) > 200 and has_color(png, im.PALETTE[1]) > 200
    n = np.array([10, 100, 1000, 10000])
    bad = np.array([np.nan, -1.0, 0.0, np.inf])
    im.line_plot(
        tmp_path / "log.png",
        {"a": (n, n * 1e-3), "b": (n, bad), "c": (n, n**0.5)},
        "Log",
        "n",
        "ms",
        logx=True,
        logy=True,
    )
    png = plot_ok(tmp_path / "log.png")
    assert has_color(png, im.PALETTE[0]) > 100 and has_color(png, im.PALETTE[2]) > 100
    im.line_plot(tmp_path / "nan.png", {"nan": ([1, 2, np.nan, 4], [1, np.nan, 3, 4])}, "NaN", "x", "y")
    assert has_color(plot_ok(tmp_path / "nan.png"), im.PALETTE[0]) > 20
    im.line_plot(tmp_path / "ys.png", {"only ys": [3, 1, 2]}, "ys only")
    plot_ok(tmp_path / "ys.png")


def test_empty_plots_say_no_data(tmp_path):
    grey = (150, 150, 150)  # the "no data" text
    for name, call in {
        "line": lambda p: im.line_plot(p, {}, "Empty", "x", "y"),
        "line_nan": lambda p: im.line_plot(p, {"a": ([1, 2], [np.nan, np.nan])}, "All NaN", "x", "y"),
        "log_nonpos": lambda p: im.line_plot(p, {"a": ([1, 2], [0, -1])}, "Log", logy=True),
        "scatter": lambda p: im.scatter_plot(p, {"a": ([], [])}, "Empty", highlight=([], [])),
        "hist": lambda p: im.histogram(p, [np.nan, np.inf], title="Empty", markers={"p50": np.nan}),
        "hist_none": lambda p: im.histogram(p, [], title="Empty"),
    }.items():
        call(tmp_path / f"{name}.png")
        png = plot_ok(tmp_path / f"{name}.png", min_ink=0.004)  # frame, title and "no data"
        assert has_color(png, grey) > 50, name
        assert has_color(png, im.PALETTE[0]) == 0, name


def test_scatter_plot(tmp_path):
    rng = np.random.default_rng(4)
    pts = rng.random((100, 2)) * [100, 1] + [1, 0.01]
    front = ([90, 2, 30], [0.02, 0.9, 0.2])  # unsorted on purpose
    im.scatter_plot(
        tmp_path / "s.png",
        {"runs": (pts[:, 0], pts[:, 1]), "nan": ([np.nan], [1])},
        "Pareto",
        "cost",
        "error",
        highlight=front,
    )
    png = plot_ok(tmp_path / "s.png")
    assert has_color(png, im.PALETTE[0]) > 300 and has_color(png, (20, 20, 20)) > 100
    im.scatter_plot(
        tmp_path / "slog.png",
        {"runs": (pts[:, 0], pts[:, 1])},
        "log",
        "cost",
        "error",
        logx=True,
        logy=True,
        highlight=front,
    )
    assert has_color(plot_ok(tmp_path / "slog.png"), im.PALETTE[0]) > 300


def test_histogram(tmp_path):
    rng = np.random.default_rng(5)
    v = np.r_[rng.lognormal(0, 0.5, 2000), np.nan, -np.inf]
    im.histogram(
        tmp_path / "h.png", v, 40, "Latency", "ms", markers={"p50": np.median(v[:-2]), "p99": np.percentile(v[:-2], 99)}
    )
    png = plot_ok(tmp_path / "h.png")
    assert has_color(png, (31, 119, 180)) > 5000  # bars
    assert has_color(png, im.PALETTE[3]) > 50 and has_color(png, im.PALETTE[1]) > 50  # marker lines
    im.histogram(tmp_path / "same.png", [3.0] * 10, title="one value")
    assert has_color(plot_ok(tmp_path / "same.png"), (31, 119, 180)) > 1000


# ----------------------------------------------------------------------------------------------
# Cloth


def grid_mesh(n: int, size: float = 1.0, plane: str = "xz") -> tuple[np.ndarray, np.ndarray]:
    a, b = np.meshgrid(np.linspace(-size / 2, size / 2, n), np.linspace(-size / 2, size / 2, n))
    zero = np.zeros(n * n)
    pos = np.stack([a.ravel(), zero, b.ravel()] if plane == "xz" else [a.ravel(), b.ravel(), zero], axis=1)
    i, j = np.meshgrid(np.arange(n - 1), np.arange(n - 1))
    v = (j * n + i).ravel()
    tris = np.concatenate([np.stack([v, v + 1, v + n + 1], 1), np.stack([v, v + n + 1, v + n], 1)])
    return pos, tris


def shade_of(pixel: np.ndarray, color) -> float | None:
    """The factor k with pixel ~ k * color, or None when the pixel is no shade of color."""
    c = np.array(color, float)
    k = float(pixel @ c / (c @ c))
    return k if np.abs(pixel - k * c).max() <= 2 else None


@pytest.mark.parametrize("view,plane", [("iso", "xz"), ("top", "xz"), ("front", "xy"), ("side", "xy")])
def test_render_cloth_flat_grid(view, plane):
    pos, tris = grid_mesh(12, 1.0, plane)
    if view == "side":
        pos = pos[:, [2, 1, 0]]  # the grid in the yz plane faces the side camera
    color = (70, 110, 200)
    img = im.render_cloth((160, 120), pos, tris, view=view, color=color)
    assert img.shape == (120, 160, 3)
    k = shade_of(img[60, 80].astype(float), color)
    assert k is not None and im.AMBIENT - 0.01 <= k <= 1.0
    assert (img[0, 0] == 255).all()  # margin stays background


def test_render_cloth_on_canvas_and_edge_on():
    pos, tris = grid_mesh(6, 1.0, "xz")
    c = im.Canvas(80, 60)
    out = im.render_cloth(c, pos, tris, view="front", bounds=((-1, -1, -1), (1, 1, 1)))
    assert out is c.array
    assert ink(out).sum() < 0.05 * 80 * 60  # seen edge-on: almost nothing to see
    pos[3] = np.nan  # a blown-up vertex is skipped, not fatal
    im.render_cloth(c, pos, tris, view="iso")


def test_render_scene_painter_and_fixed_camera():
    near_pos, tris = grid_mesh(4, 1.0, "xy")
    far_pos = near_pos - [0, 0, 0.5]
    red, blue = (220, 30, 30), (30, 30, 220)
    bounds = ((-1, -1, -1), (1, 1, 1))
    # whichever order they are passed in, the nearer cloth (larger z, front view) covers the other
    for cloths in ([(near_pos, tris, red), (far_pos, tris, blue)], [(far_pos, tris, blue), (near_pos, tris, red)]):
        img = im.render_scene((100, 100), cloths, view="front", bounds=bounds, floor=False)
        assert shade_of(img[50, 50].astype(float), red) is not None
    # fixed bounds fix the camera: moving a cloth does not move the other
    a = im.render_scene((100, 100), [(far_pos, tris, blue)], "iso", bounds, floor=False)
    b = im.render_scene(
        (100, 100), [(far_pos, tris, blue), (near_pos + [5, 0, 0], tris, red)], "iso", bounds, floor=False
    )
    np.testing.assert_array_equal(a, b)


def test_render_scene_with_colliders_and_title(tmp_path):
    pos, tris = grid_mesh(10, 2.0, "xz")
    pos[:, 1] = 0.6 - 0.3 * (pos[:, 0] ** 2 + pos[:, 2] ** 2)
    img = im.render_scene(
        (240, 180),
        [(pos, tris, (70, 110, 200)), (pos + [0, 0.3, 0], tris, (200, 90, 60))],
        view="iso",
        title="frame 3",
        spheres=[((0, 0, 0), 0.4)],
        capsules=[((-0.8, -0.5, 0.8), (0.8, -0.5, 0.8), 0.1, (90, 160, 90))],
        supersample=2,
    )
    assert img.shape == (180, 240, 3) and img.dtype == np.uint8
    assert ink(img[:20]).any()  # title
    assert ink(img).mean() > 0.2
    g = decode_gif(im.write_gif(tmp_path / "scene.gif", [img, img]).read_bytes())
    assert len(g["frames"]) == 2 and (np.abs(g["frames"][1].astype(int) - img).max(axis=(0, 1)) <= np.ceil(STEPS)).all()
    empty = im.render_scene((60, 40), [], title=None)
    assert empty.shape == (40, 60, 3)
    with pytest.raises(ValueError):
        im.render_scene((60, 40), [(pos, tris, 0)], view="fisheye")
