"""Pictures without dependencies: PNG and animated GIF writers, a bitmap font, a raster canvas,
plots and an orthographic cloth renderer, in numpy and the standard library only.

Everything here works on ``uint8`` RGB arrays of shape ``(H, W, 3)``. Image coordinates put
pixel centres on integers, ``x`` to the right and ``y`` down. World coordinates (the cloth
renderer) are right-handed with ``Y`` up. Sizes are always ``(width, height)``.

- :func:`encode_png` / :func:`write_png`: 8-bit RGB or RGBA PNG (filter 0, zlib).
- :func:`encode_gif` / :func:`write_gif`: looping GIF89a animation on a fixed 6x7x6 colour cube,
  with a real variable-width LZW coder; frames after the first only carry the changed rectangle.
- :func:`draw_text`, :func:`text_size`: a 5x7 bitmap font (with descenders) for ASCII 32..126.
- :class:`Canvas`: lines, rectangles, circles, markers, polylines, triangles (batched), text.
- :func:`line_plot`, :func:`scatter_plot`, :func:`histogram`: plots with ticks, titles, legends.
- :func:`render_cloth`, :func:`render_scene`: shaded, painter-sorted triangle meshes plus
  sphere and capsule colliders and a floor grid, for stills and animation frames.
"""

from __future__ import annotations

import logging
import math
import struct
import zlib
from collections.abc import Iterator, Mapping, Sequence
from contextlib import contextmanager
from pathlib import Path
from typing import Any, Union

import numpy as np

log = logging.getLogger(__name__)

ColorLike = Union[Sequence[int], int, str, np.ndarray]

WHITE = (255, 255, 255)
BLACK = (0, 0, 0)
#: Series colours of the plots (matplotlib's "tab10").
PALETTE: tuple[tuple[int, int, int], ...] = (
    (31, 119, 180),
    (255, 127, 14),
    (44, 160, 44),
    (214, 39, 40),
    (148, 103, 189),
    (140, 86, 75),
    (227, 119, 194),
    (127, 127, 127),
    (188, 189, 34),
    (23, 190, 207),
)
#: Marker shapes cycled through by the plots.
MARKERS = ("o", "s", "^", "d", "v", "x", "+")


def _rgb(color: ColorLike) -> np.ndarray:
    """A colour as a ``uint8`` array of 3: ``(r, g, b)``, a grey level, or ``"#rrggbb"``."""
    if isinstance(color, str):
        s = color.lstrip("#")
        if len(s) != 6:
            raise ValueError(f"colour {color!r} is not #rrggbb")
        return np.array([int(s[i : i + 2], 16) for i in (0, 2, 4)], np.uint8)
    if isinstance(color, (int, np.integer)):
        return np.array([color] * 3, np.uint8)
    c = np.asarray(color)
    if c.shape != (3,):
        raise ValueError(f"colour {color!r} is not (r, g, b)")
    return np.clip(c, 0, 255).astype(np.uint8)


def _as_image(img: Any, channels: tuple[int, ...] = (3, 4)) -> np.ndarray:
    """Validate an image: a :class:`Canvas` or an integer array (H, W), (H, W, 3) or (H, W, 4)."""
    if isinstance(img, Canvas):
        img = img.array
    a = np.asarray(img)
    if a.ndim == 2:
        a = np.repeat(a[:, :, None], 3, axis=2)
    if a.ndim != 3 or a.shape[2] not in channels:
        raise ValueError(f"image must be (H, W, {'|'.join(map(str, channels))}), got {a.shape}")
    if a.shape[0] < 1 or a.shape[1] < 1:
        raise ValueError(f"image has no pixels: {a.shape}")
    if a.dtype != np.uint8:
        if a.dtype != np.bool_ and not np.issubdtype(a.dtype, np.integer):
            raise ValueError(f"image must be uint8, got {a.dtype}")
        if a.size and (a.min() < 0 or a.max() > 255):
            raise ValueError("image values must lie in 0..255")
        a = a.astype(np.uint8)
    return a


# ----------------------------------------------------------------------------------------------
# PNG


def _png_chunk(tag: bytes, data: bytes) -> bytes:
    return struct.pack(">I", len(data)) + tag + data + struct.pack(">I", zlib.crc32(tag + data) & 0xFFFFFFFF)


def encode_png(rgb: np.ndarray, compress_level: int = 6) -> bytes:
    """Encode a ``uint8`` (H, W, 3) or (H, W, 4) array (or (H, W) grey, or a Canvas) as PNG.

    Rows use filter type 0 (none); the stream is one zlib IDAT chunk.
    """
    a = _as_image(rgb)
    h, w, c = a.shape
    raw = np.zeros((h, 1 + w * c), np.uint8)  # leading 0 = filter type "none" on every row
    raw[:, 1:] = a.reshape(h, w * c)
    ihdr = struct.pack(">IIBBBBB", w, h, 8, 2 if c == 3 else 6, 0, 0, 0)
    return b"".join(
        (
            b"\x89PNG\r\n\x1a\n",
            _png_chunk(b"IHDR", ihdr),
            _png_chunk(b"IDAT", zlib.compress(raw.tobytes(), compress_level)),
            _png_chunk(b"IEND", b""),
        )
    )


def _write_bytes(path: str | Path, data: bytes) -> Path:
    p = Path(path)
    p.parent.mkdir(parents=True, exist_ok=True)
    p.write_bytes(data)
    return p


def write_png(path: str | Path, rgb: np.ndarray) -> Path:
    """Write ``rgb`` (see :func:`encode_png`) to ``path``, creating parent folders. Returns the path."""
    p = _write_bytes(path, encode_png(rgb))
    log.debug("wrote %s (%d bytes)", p, p.stat().st_size)
    return p


# ----------------------------------------------------------------------------------------------
# GIF

_CUBE = (6, 7, 6)  # levels of red, green, blue: 252 colours
TRANSPARENT_INDEX = 255  # never produced by quantisation


def _make_palette() -> np.ndarray:
    nr, ng, nb = _CUBE
    r, g, b = np.meshgrid(np.arange(nr), np.arange(ng), np.arange(nb), indexing="ij")
    cube = np.stack(
        [np.rint(r * 255 / (nr - 1)), np.rint(g * 255 / (ng - 1)), np.rint(b * 255 / (nb - 1))], axis=-1
    ).reshape(-1, 3)
    pal = np.zeros((256, 3), np.uint8)
    pal[: len(cube)] = cube
    return pal


#: The fixed GIF palette: a 6x7x6 colour cube in entries 0..251 (index = r*42 + g*6 + b).
GIF_PALETTE: np.ndarray = _make_palette()
_LUTS = tuple(
    (np.rint(np.arange(256) * (n - 1) / 255) * mult).astype(np.uint8)
    for n, mult in zip(_CUBE, (_CUBE[1] * _CUBE[2], _CUBE[2], 1))
)
_BAYER4 = (np.array([[0, 8, 2, 10], [12, 4, 14, 6], [3, 11, 1, 9], [15, 7, 13, 5]]) + 0.5) / 16 - 0.5


def quantize(rgb: np.ndarray, dither: bool = False) -> np.ndarray:
    """Map an RGB image to indices into :data:`GIF_PALETTE` (nearest level per channel).

    With ``dither`` a 4x4 ordered (Bayer) dither trades banding in smooth shading for a fine
    pattern. Returns a ``uint8`` (H, W) array.
    """
    a = _as_image(rgb)[:, :, :3]
    if not dither:
        return _LUTS[0][a[:, :, 0]] + _LUTS[1][a[:, :, 1]] + _LUTS[2][a[:, :, 2]]
    h, w = a.shape[:2]
    t = np.tile(_BAYER4, (h // 4 + 1, w // 4 + 1))[:h, :w]
    idx = np.zeros((h, w), np.int32)
    mult = 1
    for ch in (2, 1, 0):
        n = _CUBE[ch]
        step = 255.0 / (n - 1)
        lev = np.clip(np.rint(a[:, :, ch] / step + t), 0, n - 1).astype(np.int32)
        idx += lev * mult
        mult *= n
    return idx.astype(np.uint8)


def _lzw_encode(data: bytes, min_code_size: int = 8) -> bytes:
    """GIF flavoured LZW: LSB-first codes of 9..12 bits, a clear code first and whenever the
    4096-entry table is full, an end code last."""
    clear = 1 << min_code_size
    eoi = clear + 1
    first = clear + 2
    codes: list[int] = [clear]
    emit = codes.append
    table: dict[int, int] = {}
    get = table.get
    nxt = first
    it = iter(data)
    try:
        prefix = next(it)
    except StopIteration:
        prefix = None
    if prefix is not None:
        for c in it:
            key = (prefix << 8) | c
            code = get(key)
            if code is not None:
                prefix = code
                continue
            emit(prefix)
            if nxt < 4096:
                table[key] = nxt
                nxt += 1
            else:  # table full: start over
                emit(clear)
                table.clear()
                nxt = first
            prefix = c
        emit(prefix)
    emit(eoi)
    # Code widths follow from the sequence alone: the j-th code after a clear is written with
    # the width of (first - 1 + j), capped at 12 bits (the decoder's table lags by one entry,
    # which is exactly what this accounts for, the end code and mid-stream clears included).
    arr = np.asarray(codes, np.int64)
    n = len(arr)
    marks = np.zeros(n, np.int64)
    if n > 1:
        after_clear = np.flatnonzero(arr[:-1] == clear) + 1
        marks[after_clear] = after_clear
    j = np.arange(n) - np.maximum.accumulate(marks)
    widths = np.minimum(np.frexp((first - 1 + j).astype(np.float64))[1], 12)
    widths = np.maximum(widths, min_code_size + 1)
    bits = (arr[:, None] >> np.arange(12)) & 1
    keep = np.arange(12)[None, :] < widths[:, None]
    return np.packbits(bits[keep].astype(np.uint8), bitorder="little").tobytes()


def _sub_blocks(data: bytes) -> bytes:
    out = bytearray()
    for i in range(0, len(data), 255):
        chunk = data[i : i + 255]
        out.append(len(chunk))
        out += chunk
    out.append(0)
    return bytes(out)


def encode_gif(frames: Sequence[np.ndarray], fps: float = 20, loop: bool = True, dither: bool = True) -> bytes:
    """Encode equally sized RGB frames as an animated GIF89a.

    Colours are quantised to :data:`GIF_PALETTE` (see :func:`quantize`), by default with an
    ordered dither, which keeps shading smooth and, being fixed in place, costs nothing where
    frames do not change; pass ``dither=False`` for nearest colours only. The first frame is
    stored whole; each later one only as the rectangle that changed, with unchanged pixels in it
    transparent (disposal "do not dispose"), so static backgrounds cost next to nothing. Delays
    are in hundredths of a second, spread so the average rate matches ``fps`` (at least 2 cs,
    since browsers slow down anything faster). ``loop`` adds the NETSCAPE2.0 repeat-forever block.
    """
    if len(frames) == 0:
        raise ValueError("no frames")
    if not (fps > 0 and math.isfinite(fps)):
        raise ValueError(f"fps must be positive, got {fps}")
    first = _as_image(frames[0])
    h, w = first.shape[:2]
    if w > 0xFFFF or h > 0xFFFF:
        raise ValueError(f"GIF frames are at most 65535 pixels a side, got {w}x{h}")
    out = bytearray(b"GIF89a")
    out += struct.pack("<HHBBB", w, h, 0xF7, 0, 0)  # global table of 2**(7+1) colours
    out += GIF_PALETTE.tobytes()
    if loop:
        out += b"\x21\xff\x0bNETSCAPE2.0\x03\x01" + struct.pack("<H", 0) + b"\x00"
    prev: np.ndarray | None = None
    for i, frame in enumerate(frames):
        a = _as_image(frame)
        if a.shape[:2] != (h, w):
            raise ValueError(f"frame {i} is {a.shape[1]}x{a.shape[0]}, frame 0 is {w}x{h}")
        q = quantize(a, dither)
        transparent = prev is not None
        if prev is None:
            x0, y0, sub = 0, 0, q
        else:
            changed = q != prev
            rows = np.flatnonzero(changed.any(axis=1))
            if len(rows) == 0:
                x0, y0, sub = 0, 0, np.full((1, 1), TRANSPARENT_INDEX, np.uint8)
            else:
                cols = np.flatnonzero(changed.any(axis=0))
                y0, y1, x0, x1 = rows[0], rows[-1] + 1, cols[0], cols[-1] + 1
                sub = q[y0:y1, x0:x1].copy()
                sub[~changed[y0:y1, x0:x1]] = TRANSPARENT_INDEX
        prev = q
        delay = max(2, round(100 * (i + 1) / fps) - round(100 * i / fps))
        out += b"\x21\xf9\x04" + struct.pack("<BHBB", (1 << 2) | int(transparent), delay, TRANSPARENT_INDEX, 0)
        sh, sw = sub.shape
        out += b"\x2c" + struct.pack("<HHHHB", int(x0), int(y0), sw, sh, 0)
        out += b"\x08" + _sub_blocks(_lzw_encode(np.ascontiguousarray(sub).tobytes(), 8))
    out += b"\x3b"
    return bytes(out)


def write_gif(
    path: str | Path, frames: Sequence[np.ndarray], fps: float = 20, loop: bool = True, dither: bool = True
) -> Path:
    """Write an animated GIF (see :func:`encode_gif`) to ``path``. Returns the path."""
    data = encode_gif(frames, fps=fps, loop=loop, dither=dither)
    p = _write_bytes(path, data)
    log.debug("wrote %s (%d frames, %d bytes)", p, len(frames), len(data))
    return p


# ----------------------------------------------------------------------------------------------
# Font: 5 columns, 7 rows above the baseline, 2 more for descenders ("|" separates rows).

_GLYPH_ROWS = {
    " ": ".....|.....|.....|.....|.....|.....|.....",
    "!": "..#..|..#..|..#..|..#..|..#..|.....|..#..",
    '"': ".#.#.|.#.#.|.#.#.|.....|.....|.....|.....",
    "#": ".#.#.|.#.#.|#####|.#.#.|#####|.#.#.|.#.#.",
    "$": "..#..|.####|#.#..|.###.|..#.#|####.|..#..",
    "%": "##...|##..#|...#.|..#..|.#...|#..##|...##",
    "&": ".##..|#..#.|#.#..|.#...|#.#.#|#..#.|.##.#",
    "'": "..#..|..#..|.#...|.....|.....|.....|.....",
    "(": "...#.|..#..|.#...|.#...|.#...|..#..|...#.",
    ")": ".#...|..#..|...#.|...#.|...#.|..#..|.#...",
    "*": ".....|..#..|#.#.#|.###.|#.#.#|..#..|.....",
    "+": ".....|..#..|..#..|#####|..#..|..#..|.....",
    ",": ".....|.....|.....|.....|.....|.##..|.##..|..#..|.#...",
    "-": ".....|.....|.....|#####|.....|.....|.....",
    ".": ".....|.....|.....|.....|.....|.##..|.##..",
    "/": ".....|....#|...#.|..#..|.#...|#....|.....",
    "0": ".###.|#...#|#..##|#.#.#|##..#|#...#|.###.",
    "1": "..#..|.##..|..#..|..#..|..#..|..#..|.###.",
    "2": ".###.|#...#|....#|...#.|..#..|.#...|#####",
    "3": "#####|...#.|..#..|...#.|....#|#...#|.###.",
    "4": "...#.|..##.|.#.#.|#..#.|#####|...#.|...#.",
    "5": "#####|#....|####.|....#|....#|#...#|.###.",
    "6": "..##.|.#...|#....|####.|#...#|#...#|.###.",
    "7": "#####|....#|...#.|..#..|.#...|.#...|.#...",
    "8": ".###.|#...#|#...#|.###.|#...#|#...#|.###.",
    "9": ".###.|#...#|#...#|.####|....#|...#.|.##..",
    ":": ".....|.##..|.##..|.....|.##..|.##..|.....",
    ";": ".....|.##..|.##..|.....|.##..|.##..|..#..|.#...",
    "<": "...#.|..#..|.#...|#....|.#...|..#..|...#.",
    "=": ".....|.....|#####|.....|#####|.....|.....",
    ">": ".#...|..#..|...#.|....#|...#.|..#..|.#...",
    "?": ".###.|#...#|....#|...#.|..#..|.....|..#..",
    "@": ".###.|#...#|....#|.##.#|#.#.#|#.#.#|.###.",
    "A": ".###.|#...#|#...#|#####|#...#|#...#|#...#",
    "B": "####.|#...#|#...#|####.|#...#|#...#|####.",
    "C": ".###.|#...#|#....|#....|#....|#...#|.###.",
    "D": "###..|#..#.|#...#|#...#|#...#|#..#.|###..",
    "E": "#####|#....|#....|####.|#....|#....|#####",
    "F": "#####|#....|#....|####.|#....|#....|#....",
    "G": ".###.|#...#|#....|#.###|#...#|#...#|.####",
    "H": "#...#|#...#|#...#|#####|#...#|#...#|#...#",
    "I": ".###.|..#..|..#..|..#..|..#..|..#..|.###.",
    "J": "..###|...#.|...#.|...#.|...#.|#..#.|.##..",
    "K": "#...#|#..#.|#.#..|##...|#.#..|#..#.|#...#",
    "L": "#....|#....|#....|#....|#....|#....|#####",
    "M": "#...#|##.##|#.#.#|#.#.#|#...#|#...#|#...#",
    "N": "#...#|#...#|##..#|#.#.#|#..##|#...#|#...#",
    "O": ".###.|#...#|#...#|#...#|#...#|#...#|.###.",
    "P": "####.|#...#|#...#|####.|#....|#....|#....",
    "Q": ".###.|#...#|#...#|#...#|#.#.#|#..#.|.##.#",
    "R": "####.|#...#|#...#|####.|#.#..|#..#.|#...#",
    "S": ".####|#....|#....|.###.|....#|....#|####.",
    "T": "#####|..#..|..#..|..#..|..#..|..#..|..#..",
    "U": "#...#|#...#|#...#|#...#|#...#|#...#|.###.",
    "V": "#...#|#...#|#...#|#...#|#...#|.#.#.|..#..",
    "W": "#...#|#...#|#...#|#.#.#|#.#.#|#.#.#|.#.#.",
    "X": "#...#|#...#|.#.#.|..#..|.#.#.|#...#|#...#",
    "Y": "#...#|#...#|.#.#.|..#..|..#..|..#..|..#..",
    "Z": "#####|....#|...#.|..#..|.#...|#....|#####",
    "[": ".###.|.#...|.#...|.#...|.#...|.#...|.###.",
    "\\": ".....|#....|.#...|..#..|...#.|....#|.....",
    "]": ".###.|...#.|...#.|...#.|...#.|...#.|.###.",
    "^": "..#..|.#.#.|#...#|.....|.....|.....|.....",
    "_": ".....|.....|.....|.....|.....|.....|.....|#####",
    "`": ".#...|..#..|...#.|.....|.....|.....|.....",
    "a": ".....|.....|.###.|....#|.####|#...#|.####",
    "b": "#....|#....|#.##.|##..#|#...#|#...#|####.",
    "c": ".....|.....|.###.|#....|#....|#...#|.###.",
    "d": "....#|....#|.##.#|#..##|#...#|#...#|.####",
    "e": ".....|.....|.###.|#...#|#####|#....|.###.",
    "f": "..##.|.#..#|.#...|###..|.#...|.#...|.#...",
    "g": ".....|.....|.####|#...#|#...#|#...#|.####|....#|.###.",
    "h": "#....|#....|#.##.|##..#|#...#|#...#|#...#",
    "i": "..#..|.....|.##..|..#..|..#..|..#..|.###.",
    "j": "...#.|.....|..##.|...#.|...#.|...#.|...#.|#..#.|.##..",
    "k": "#....|#....|#..#.|#.#..|##...|#.#..|#..#.",
    "l": ".##..|..#..|..#..|..#..|..#..|..#..|.###.",
    "m": ".....|.....|##.#.|#.#.#|#.#.#|#.#.#|#.#.#",
    "n": ".....|.....|#.##.|##..#|#...#|#...#|#...#",
    "o": ".....|.....|.###.|#...#|#...#|#...#|.###.",
    "p": ".....|.....|####.|#...#|#...#|#...#|####.|#....|#....",
    "q": ".....|.....|.####|#...#|#...#|#...#|.####|....#|....#",
    "r": ".....|.....|#.##.|##..#|#....|#....|#....",
    "s": ".....|.....|.####|#....|.###.|....#|####.",
    "t": ".#...|.#...|###..|.#...|.#...|.#..#|..##.",
    "u": ".....|.....|#...#|#...#|#...#|#..##|.##.#",
    "v": ".....|.....|#...#|#...#|#...#|.#.#.|..#..",
    "w": ".....|.....|#...#|#...#|#.#.#|#.#.#|.#.#.",
    "x": ".....|.....|#...#|.#.#.|..#..|.#.#.|#...#",
    "y": ".....|.....|#...#|#...#|#...#|#...#|.####|....#|.###.",
    "z": ".....|.....|#####|...#.|..#..|.#...|#####",
    "{": "...##|..#..|..#..|.#...|..#..|..#..|...##",
    "|": "..#..|..#..|..#..|..#..|..#..|..#..|..#..",
    "}": "##...|..#..|..#..|...#.|..#..|..#..|##...",
    "~": ".....|.....|.#...|#.#.#|...#.|.....|.....",
}
GLYPH_WIDTH = 5
GLYPH_HEIGHT = 9  # 7 above the baseline, 2 below
CAP_HEIGHT = 7
ADVANCE = 6  # glyph plus one column of spacing
LINE_HEIGHT = 11


def _build_font() -> dict[str, np.ndarray]:
    font = {}
    for ch, spec in _GLYPH_ROWS.items():
        g = np.zeros((GLYPH_HEIGHT, GLYPH_WIDTH), bool)
        for r, row in enumerate(spec.split("|")):
            g[r] = [c == "#" for c in row]
        font[ch] = g
    return font


#: Glyph masks, (GLYPH_HEIGHT, GLYPH_WIDTH) bool arrays for every printable ASCII character.
FONT: dict[str, np.ndarray] = _build_font()


def text_size(text: str, scale: int = 1) -> tuple[int, int]:
    """(width, height) in pixels of :func:`text_mask` for ``text``; the height counts the
    descender rows of the last line."""
    lines = text.split("\n")
    cols = max(len(line) for line in lines)
    w = max(0, cols * ADVANCE - 1) * scale
    h = ((len(lines) - 1) * LINE_HEIGHT + GLYPH_HEIGHT) * scale
    return w, h


def text_mask(text: str, scale: int = 1) -> np.ndarray:
    """A bool (height, width) mask of ``text`` (newlines start new lines, characters outside
    ASCII 32..126 draw as ``?``), each font pixel a ``scale`` x ``scale`` block."""
    scale = max(1, int(scale))
    lines = text.replace("\t", "    ").split("\n")
    w, h = text_size("\n".join(lines), 1)
    m = np.zeros((h, max(w, 0) + 1), bool)
    for li, line in enumerate(lines):
        y = li * LINE_HEIGHT
        for ci, ch in enumerate(line):
            g = FONT.get(ch, FONT["?"])
            m[y : y + GLYPH_HEIGHT, ci * ADVANCE : ci * ADVANCE + GLYPH_WIDTH] |= g
    m = m[:, : max(w, 0)]
    if scale > 1:
        m = np.repeat(np.repeat(m, scale, axis=0), scale, axis=1)
    return m


def draw_text(
    canvas: Canvas | np.ndarray,
    x: float,
    y: float,
    text: str,
    color: ColorLike = BLACK,
    scale: int = 1,
    anchor: str = "tl",
    angle: int = 0,
) -> tuple[int, int, int, int]:
    """Draw ``text`` on a :class:`Canvas` or an (H, W, 3) array (modified in place).

    ``anchor`` is two letters, vertical then horizontal: ``t``/``m``/``b`` (top of the capitals,
    their middle, the baseline of the last line) and ``l``/``c``/``r``; e.g. ``"tl"``, ``"mc"``.
    ``angle`` is 0 or 90 (reading bottom to top; the anchor then applies to the rotated box).
    Returns the drawn box ``(x0, y0, x1, y1)``, exclusive of ``x1``/``y1``.
    """
    c = canvas if isinstance(canvas, Canvas) else Canvas.wrap(canvas)
    return c.text(x, y, text, color, scale=scale, anchor=anchor, angle=angle)


# ----------------------------------------------------------------------------------------------
# Canvas


def _clip_segments(
    x0: np.ndarray, y0: np.ndarray, x1: np.ndarray, y1: np.ndarray, box: tuple[float, float, float, float]
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Liang-Barsky clipping of segments to ``box = (xmin, ymin, xmax, ymax)``; returns the
    clipped end points and a mask of the segments that survive."""
    xmin, ymin, xmax, ymax = box
    dx = x1 - x0
    dy = y1 - y0
    t0 = np.zeros_like(x0)
    t1 = np.ones_like(x0)
    ok = np.isfinite(x0) & np.isfinite(y0) & np.isfinite(x1) & np.isfinite(y1)
    with np.errstate(divide="ignore", invalid="ignore"):
        for p, q in ((-dx, x0 - xmin), (dx, xmax - x0), (-dy, y0 - ymin), (dy, ymax - y0)):
            ok &= ~((p == 0) & (q < 0))
            r = q / p
            t0 = np.where(p < 0, np.maximum(t0, r), t0)
            t1 = np.where(p > 0, np.minimum(t1, r), t1)
    ok &= t0 <= t1
    return x0 + t0 * dx, y0 + t0 * dy, x0 + t1 * dx, y0 + t1 * dy, ok


def _brush(width: float) -> tuple[np.ndarray, np.ndarray]:
    """Pixel offsets of a round pen ``width`` pixels across."""
    w = max(1, int(round(width)))
    if w == 1:
        return np.zeros(1, np.int64), np.zeros(1, np.int64)
    lo, hi = -((w - 1) // 2), w // 2
    oy, ox = np.mgrid[lo : hi + 1, lo : hi + 1]
    cx = (lo + hi) / 2
    keep = (ox - cx) ** 2 + (oy - cx) ** 2 <= (w / 2) ** 2 + 0.25
    return ox[keep].astype(np.int64), oy[keep].astype(np.int64)


def _marker_offsets(kind: str, size: int) -> tuple[np.ndarray, np.ndarray]:
    """Pixel offsets of a marker of radius ``size``: o s ^ v d x + (filled where it makes sense)."""
    r = max(1, int(size))
    oy, ox = np.mgrid[-r : r + 1, -r : r + 1]
    if kind == "o":
        m = ox**2 + oy**2 <= (r + 0.35) ** 2
    elif kind == "s":
        m = np.ones_like(ox, bool)
    elif kind == "d":
        m = np.abs(ox) + np.abs(oy) <= r
    elif kind == "^":
        m = np.abs(ox) * 2 <= (oy + r) + 0.5
    elif kind == "v":
        m = np.abs(ox) * 2 <= (r - oy) + 0.5
    elif kind == "x":
        m = np.abs(np.abs(ox) - np.abs(oy)) <= (0 if r < 3 else 1)
    elif kind == "+":
        th = 0 if r < 3 else 1
        m = (np.abs(ox) <= th) | (np.abs(oy) <= th)
    else:
        raise ValueError(f"unknown marker {kind!r}; one of {MARKERS}")
    return ox[m].astype(np.int64), oy[m].astype(np.int64)


class Canvas:
    """An RGB raster (numpy ``uint8`` (H, W, 3), white unless told otherwise) to draw on.

    Coordinates may be floats; pixel centres are at integers. Everything is clipped to the
    canvas, or to a smaller rectangle inside :meth:`clip`. :attr:`array` is the live buffer.
    """

    def __init__(self, width: int, height: int, background: ColorLike = WHITE) -> None:
        if width < 1 or height < 1:
            raise ValueError(f"canvas must be at least 1x1, got {width}x{height}")
        self._a = np.empty((int(height), int(width), 3), np.uint8)
        self._a[:] = _rgb(background)
        self.background = tuple(int(v) for v in _rgb(background))
        self._clip = (0, 0, self.width - 1, self.height - 1)

    @classmethod
    def wrap(cls, array: np.ndarray) -> Canvas:
        """A canvas drawing straight into an existing ``uint8`` (H, W, 3) array (no copy)."""
        if not (isinstance(array, np.ndarray) and array.dtype == np.uint8 and array.ndim == 3 and array.shape[2] == 3):
            raise ValueError("Canvas.wrap needs a uint8 (H, W, 3) numpy array")
        c = cls.__new__(cls)
        c._a = array
        c.background = WHITE
        c._clip = (0, 0, array.shape[1] - 1, array.shape[0] - 1)
        return c

    @property
    def array(self) -> np.ndarray:
        """The pixels, ``uint8`` (H, W, 3); not a copy."""
        return self._a

    @property
    def width(self) -> int:
        return self._a.shape[1]

    @property
    def height(self) -> int:
        return self._a.shape[0]

    @property
    def size(self) -> tuple[int, int]:
        return self.width, self.height

    def copy(self) -> Canvas:
        c = Canvas.wrap(self._a.copy())
        c.background = self.background
        return c

    def clear(self, color: ColorLike | None = None) -> None:
        self._a[:] = _rgb(self.background if color is None else color)

    @contextmanager
    def clip(self, x0: int, y0: int, x1: int, y1: int) -> Iterator[Canvas]:
        """Restrict drawing to the inclusive rectangle (x0, y0)..(x1, y1) inside the block."""
        old = self._clip
        self._clip = (
            max(int(x0), old[0]),
            max(int(y0), old[1]),
            min(int(x1), old[2]),
            min(int(y1), old[3]),
        )
        try:
            yield self
        finally:
            self._clip = old

    def to_png(self, path: str | Path) -> Path:
        """Write the canvas as a PNG file."""
        return write_png(path, self._a)

    # -- low level ------------------------------------------------------------------------

    def _put(self, xs: np.ndarray, ys: np.ndarray, color: ColorLike | np.ndarray) -> None:
        """Set pixels (integer arrays) to one colour or per-pixel colours (n, 3), clipped."""
        cx0, cy0, cx1, cy1 = self._clip
        keep = (xs >= cx0) & (xs <= cx1) & (ys >= cy0) & (ys <= cy1)
        col = np.asarray(color)
        if col.ndim == 2:
            self._a[ys[keep], xs[keep]] = col[keep]
        else:
            self._a[ys[keep], xs[keep]] = _rgb(color)

    def _stamp(self, xs: np.ndarray, ys: np.ndarray, ox: np.ndarray, oy: np.ndarray, color: ColorLike) -> None:
        if len(xs) == 0:
            return
        self._put((xs[:, None] + ox[None, :]).ravel(), (ys[:, None] + oy[None, :]).ravel(), color)

    def _blit(self, x: int, y: int, mask: np.ndarray, color: ColorLike) -> None:
        h, w = mask.shape
        cx0, cy0, cx1, cy1 = self._clip
        x0, y0 = max(x, cx0), max(y, cy0)
        x1, y1 = min(x + w - 1, cx1), min(y + h - 1, cy1)
        if x1 < x0 or y1 < y0:
            return
        sub = mask[y0 - y : y1 - y + 1, x0 - x : x1 - x + 1]
        self._a[y0 : y1 + 1, x0 : x1 + 1][sub] = _rgb(color)

    def _segment_pixels(
        self, x0: np.ndarray, y0: np.ndarray, x1: np.ndarray, y1: np.ndarray, pad: int, dash: tuple[int, int] | None
    ) -> tuple[np.ndarray, np.ndarray]:
        """DDA pixels of many segments at once (clipped first, so far-off points cost nothing)."""
        cx0, cy0, cx1, cy1 = self._clip
        box = (cx0 - pad - 1.0, cy0 - pad - 1.0, cx1 + pad + 1.0, cy1 + pad + 1.0)
        f = lambda v: np.atleast_1d(np.asarray(v, np.float64))  # noqa: E731
        a0, b0, a1, b1, ok = _clip_segments(f(x0), f(y0), f(x1), f(y1), box)
        if dash is not None:
            # keep the dash phase of the unclipped start, so clipping does not shift the pattern
            sx, sy = f(x0)[ok], f(y0)[ok]
        a0, b0, a1, b1 = (np.rint(v[ok]).astype(np.int64) for v in (a0, b0, a1, b1))
        if len(a0) == 0:
            return np.zeros(0, np.int64), np.zeros(0, np.int64)
        n = np.maximum(np.abs(a1 - a0), np.abs(b1 - b0)) + 1
        seg = np.repeat(np.arange(len(n)), n)
        starts = np.cumsum(n) - n
        k = np.arange(int(n.sum())) - starts[seg]
        t = np.where(n[seg] > 1, k / np.maximum(n[seg] - 1, 1), 0.0)
        xs = np.rint(a0[seg] + t * (a1 - a0)[seg]).astype(np.int64)
        ys = np.rint(b0[seg] + t * (b1 - b0)[seg]).astype(np.int64)
        if dash is not None:
            on, off = max(1, int(dash[0])), max(0, int(dash[1]))
            phase = np.maximum(np.abs(a0 - sx), np.abs(b0 - sy)).astype(np.int64)
            keep = ((k + phase[seg]) % (on + off)) < on
            xs, ys = xs[keep], ys[keep]
        return xs, ys

    # -- primitives -----------------------------------------------------------------------

    def pixel(self, x: float, y: float, color: ColorLike) -> None:
        self._put(np.array([int(round(x))]), np.array([int(round(y))]), color)

    def line(
        self,
        x0: float,
        y0: float,
        x1: float,
        y1: float,
        color: ColorLike,
        width: float = 1,
        dash: tuple[int, int] | None = None,
    ) -> None:
        """A straight line (DDA, equivalent to Bresenham), clipped; ``width`` in pixels with a
        round pen; ``dash=(on, off)`` for a dashed line."""
        self.lines(np.array([[x0, y0, x1, y1]], np.float64), color, width, dash)

    def lines(
        self, segments: np.ndarray, color: ColorLike, width: float = 1, dash: tuple[int, int] | None = None
    ) -> None:
        """Many segments, (k, 4) rows of ``x0, y0, x1, y1``, in one vectorised pass."""
        s = np.asarray(segments, np.float64).reshape(-1, 4)
        ox, oy = _brush(width)
        pad = int(np.abs(ox).max(initial=0)) + 1
        xs, ys = self._segment_pixels(s[:, 0], s[:, 1], s[:, 2], s[:, 3], pad, dash)
        self._stamp(xs, ys, ox, oy, color)

    def polyline(
        self,
        points: Sequence[Sequence[float]] | np.ndarray,
        color: ColorLike,
        width: float = 1,
        closed: bool = False,
        dash: tuple[int, int] | None = None,
    ) -> None:
        """Connected segments through ``points`` ((n, 2)); non-finite points break the line."""
        p = np.asarray(points, np.float64).reshape(-1, 2)
        if closed and len(p) > 2:
            p = np.vstack([p, p[:1]])
        if len(p) < 2:
            if len(p) == 1 and np.isfinite(p).all():
                ox, oy = _brush(width)
                self._stamp(np.rint(p[:, 0]).astype(np.int64), np.rint(p[:, 1]).astype(np.int64), ox, oy, color)
            return
        seg = np.hstack([p[:-1], p[1:]])
        self.lines(seg[np.isfinite(seg).all(axis=1)], color, width, dash)

    def rect(self, x0: float, y0: float, x1: float, y1: float, color: ColorLike, width: float = 1) -> None:
        """Outline of the rectangle with corners (x0, y0) and (x1, y1), inclusive."""
        xa, xb = sorted((x0, x1))
        ya, yb = sorted((y0, y1))
        w = max(1, int(round(width)))
        for i in range(w):
            self.lines(
                np.array(
                    [
                        [xa + i, ya + i, xb - i, ya + i],
                        [xa + i, yb - i, xb - i, yb - i],
                        [xa + i, ya + i, xa + i, yb - i],
                        [xb - i, ya + i, xb - i, yb - i],
                    ]
                ),
                color,
            )

    def fill_rect(self, x0: float, y0: float, x1: float, y1: float, color: ColorLike) -> None:
        """Fill the rectangle with corners (x0, y0) and (x1, y1), inclusive."""
        xa, xb = sorted((int(round(x0)), int(round(x1))))
        ya, yb = sorted((int(round(y0)), int(round(y1))))
        cx0, cy0, cx1, cy1 = self._clip
        xa, ya, xb, yb = max(xa, cx0), max(ya, cy0), min(xb, cx1), min(yb, cy1)
        if xb >= xa and yb >= ya:
            self._a[ya : yb + 1, xa : xb + 1] = _rgb(color)

    def _disc_box(self, x: float, y: float, r: float) -> tuple[np.ndarray, np.ndarray] | None:
        cx0, cy0, cx1, cy1 = self._clip
        xa, xb = max(int(math.floor(x - r - 1)), cx0), min(int(math.ceil(x + r + 1)), cx1)
        ya, yb = max(int(math.floor(y - r - 1)), cy0), min(int(math.ceil(y + r + 1)), cy1)
        if xb < xa or yb < ya:
            return None
        yy, xx = np.mgrid[ya : yb + 1, xa : xb + 1]
        return xx, yy

    def circle(self, x: float, y: float, r: float, color: ColorLike, width: float = 1, fill: bool = False) -> None:
        """Circle of radius ``r`` around (x, y): an outline ``width`` thick, or filled."""
        if fill:
            self.dot(x, y, r, color)
            return
        box = self._disc_box(x, y, r + width)
        if box is None:
            return
        xx, yy = box
        d = np.hypot(xx - x, yy - y)
        m = np.abs(d - r) <= max(width, 1) / 2 + 0.2
        self._a[yy[m], xx[m]] = _rgb(color)

    def dot(self, x: float, y: float, r: float, color: ColorLike) -> None:
        """Filled disc of radius ``r`` around (x, y)."""
        box = self._disc_box(x, y, r)
        if box is None:
            return
        xx, yy = box
        m = (xx - x) ** 2 + (yy - y) ** 2 <= (r + 0.35) ** 2
        self._a[yy[m], xx[m]] = _rgb(color)

    def markers(self, xs: np.ndarray, ys: np.ndarray, color: ColorLike, kind: str = "o", size: int = 3) -> None:
        """Markers (``o s ^ v d x +``) of radius ``size`` at each finite (x, y)."""
        x = np.asarray(xs, np.float64).ravel()
        y = np.asarray(ys, np.float64).ravel()
        ok = np.isfinite(x) & np.isfinite(y)
        ox, oy = _marker_offsets(kind, size)
        self._stamp(np.rint(x[ok]).astype(np.int64), np.rint(y[ok]).astype(np.int64), ox, oy, color)

    def triangle_fill(self, p0: Sequence[float], p1: Sequence[float], p2: Sequence[float], color: ColorLike) -> None:
        """Fill one triangle (pixel centres inside or on an edge), clipped."""
        self.triangles_fill(np.array([[p0, p1, p2]], np.float64), _rgb(color)[None, :])

    def triangles_fill(self, tris: np.ndarray, colors: np.ndarray | ColorLike, max_candidates: int = 1 << 21) -> None:
        """Fill many triangles, (m, 3, 2) screen points, in order: where they overlap the later
        one wins (painter's algorithm). ``colors`` is one colour or (m, 3). Vectorised over
        triangles: candidate pixels of each bounding box are tested with edge functions."""
        t = np.asarray(tris, np.float64).reshape(-1, 3, 2)
        m = len(t)
        if m == 0:
            return
        if isinstance(colors, np.ndarray) and colors.ndim == 2:
            if len(colors) != m:
                raise ValueError(f"{len(colors)} colours for {m} triangles")
            cols = np.clip(colors, 0, 255).astype(np.uint8)
        else:
            cols = np.broadcast_to(_rgb(colors), (m, 3))
        cx0, cy0, cx1, cy1 = self._clip
        xs, ys = t[:, :, 0], t[:, :, 1]
        ok = np.isfinite(t).all(axis=(1, 2))
        area = (xs[:, 1] - xs[:, 0]) * (ys[:, 2] - ys[:, 0]) - (xs[:, 2] - xs[:, 0]) * (ys[:, 1] - ys[:, 0])
        ok &= area != 0
        with np.errstate(invalid="ignore"):
            bx0 = np.maximum(np.ceil(np.where(ok, xs.min(axis=1), 0) - 1e-9), cx0)
            bx1 = np.minimum(np.floor(np.where(ok, xs.max(axis=1), -1) + 1e-9), cx1)
            by0 = np.maximum(np.ceil(np.where(ok, ys.min(axis=1), 0) - 1e-9), cy0)
            by1 = np.minimum(np.floor(np.where(ok, ys.max(axis=1), -1) + 1e-9), cy1)
        ok &= (bx1 >= bx0) & (by1 >= by0)
        idx = np.flatnonzero(ok)
        if len(idx) == 0:
            return
        bw = (bx1[idx] - bx0[idx] + 1).astype(np.int64)
        bh = (by1[idx] - by0[idx] + 1).astype(np.int64)
        cnt = bw * bh
        flat = self._a.reshape(-1, 3)
        W = self.width
        # chunks of consecutive triangles keep memory bounded; chunks are drawn in order
        csum = np.cumsum(cnt)
        start = 0
        while start < len(idx):
            base = csum[start - 1] if start else 0
            stop = int(np.searchsorted(csum, base + max_candidates, side="right"))
            stop = max(stop, start + 1)
            sel = slice(start, stop)
            ti = idx[sel]
            c = cnt[sel]
            owner = np.repeat(np.arange(len(ti)), c)
            local = np.arange(int(c.sum())) - np.repeat(np.cumsum(c) - c, c)
            bwo = bw[sel][owner]
            px = bx0[ti][owner] + local % bwo
            py = by0[ti][owner] + local // bwo
            tx, ty = xs[ti][owner], ys[ti][owner]
            sgn = np.sign(area[ti])[owner]
            eps = -1e-7 * np.abs(area[ti])[owner]
            inside = np.ones(len(px), bool)
            for a, b in ((0, 1), (1, 2), (2, 0)):
                e = (tx[:, b] - tx[:, a]) * (py - ty[:, a]) - (ty[:, b] - ty[:, a]) * (px - tx[:, a])
                inside &= e * sgn >= eps
            pix = (py[inside] * W + px[inside]).astype(np.int64)
            tri_of = ti[owner[inside]]
            # last writer wins: first occurrence in the reversed order
            rev = pix[::-1]
            uniq, first = np.unique(rev, return_index=True)
            flat[uniq] = cols[tri_of[::-1][first]]
            start = stop

    def text(
        self,
        x: float,
        y: float,
        text: str,
        color: ColorLike = BLACK,
        scale: int = 1,
        anchor: str = "tl",
        angle: int = 0,
    ) -> tuple[int, int, int, int]:
        """Draw ``text`` with the bitmap font; see :func:`draw_text` for ``anchor`` and ``angle``."""
        if len(anchor) != 2 or anchor[0] not in "tmb" or anchor[1] not in "lcr":
            raise ValueError(f"anchor must be [tmb][lcr], got {anchor!r}")
        scale = max(1, int(scale))
        mask = text_mask(text, scale)
        h, w = mask.shape
        n_lines = text.count("\n") + 1
        caps = ((n_lines - 1) * LINE_HEIGHT + CAP_HEIGHT) * scale  # top of caps to last baseline
        if angle % 360 == 90:
            mask = np.rot90(mask)  # reads bottom to top
            h, w = mask.shape
            along, across = h, caps
            # rotated: "vertical" anchor letter is across the text (x), "horizontal" along it (y)
            ox = {"t": 0, "m": -across / 2, "b": -across}[anchor[0]]
            oy = {"l": -along, "c": -along / 2, "r": 0}[anchor[1]]
        elif angle % 360 == 0:
            ox = {"l": 0, "c": -w / 2, "r": -w}[anchor[1]]
            oy = {"t": 0, "m": -caps / 2, "b": -caps}[anchor[0]]
        else:
            raise ValueError("angle must be 0 or 90")
        x0, y0 = int(round(x + ox)), int(round(y + oy))
        self._blit(x0, y0, mask, color)
        return x0, y0, x0 + w, y0 + h


# ----------------------------------------------------------------------------------------------
# Plots


def nice_ticks(lo: float, hi: float, target: int = 6) -> tuple[np.ndarray, float]:
    """Round tick values (steps of 1, 2, 2.5 or 5 times a power of ten) inside [lo, hi];
    returns the ticks and the step."""
    span = hi - lo
    if not (math.isfinite(lo) and math.isfinite(hi)) or span <= 0:
        return np.array([lo]), 1.0
    raw = span / max(1, target)
    mag = 10.0 ** math.floor(math.log10(raw))
    step = next(m * mag for m in (1, 2, 2.5, 5, 10) if m * mag >= raw * (1 - 1e-9))
    first = math.ceil(lo / step - 1e-9)
    last = math.floor(hi / step + 1e-9)
    ticks = np.arange(first, last + 1) * step
    ticks[np.abs(ticks) < step * 1e-9] = 0.0
    return ticks, step


def _fmt_tick(v: float, step: float) -> str:
    """A tick label with just enough digits for the step."""
    if v == 0:
        return "0"
    av = abs(v)
    if av >= 1e6 or av < 1e-4:
        digits = max(0, min(6, math.floor(math.log10(av)) - math.floor(math.log10(step) + 1e-9)))
        s = f"{v:.{digits}e}"
        mant, exp = s.split("e")
        if "." in mant:
            mant = mant.rstrip("0").rstrip(".")
        return f"{mant}e{int(exp)}"
    decimals = max(0, -math.floor(math.log10(step) + 1e-9))
    if abs(step / 10 ** math.floor(math.log10(step) + 1e-9) - 2.5) < 1e-6:
        decimals += 1
    return f"{v:.{decimals}f}"


def _fmt_log_tick(v: float) -> str:
    k = math.log10(v)
    if abs(k - round(k)) < 1e-9:
        k = int(round(k))
        if -3 <= k <= 4:
            return f"{10.0**k:.{max(0, -k)}f}"
        return f"1e{k}"
    return _fmt_num(v, 3)


def _fmt_num(v: float, sig: int = 4) -> str:
    """A compact number for legends: 4 significant digits, short exponent."""
    if not math.isfinite(v):
        return str(v)
    s = f"{v:.{sig}g}"
    if "e" in s:
        mant, exp = s.split("e")
        return f"{mant}e{int(exp)}"
    return s


class _Axis:
    """One axis: data range (in log10 when ``log``), ticks and the mapping to pixels."""

    def __init__(self, lo: float, hi: float, log: bool, pad: float = 0.04, pad_lo: bool = True) -> None:
        self.log = log
        if log:
            lo, hi = math.log10(lo), math.log10(hi)
        if hi <= lo:
            d = abs(lo) * 0.1 if lo != 0 else 1.0
            if log:
                d = 0.5
            lo, hi = lo - d, hi + d
        span = hi - lo
        self.lo = lo - (span * pad if pad_lo else 0.0)
        self.hi = hi + span * pad
        self.p0 = 0.0
        self.p1 = 1.0

    def set_pixels(self, p0: float, p1: float) -> None:
        self.p0, self.p1 = p0, p1

    def to_px(self, v: np.ndarray) -> np.ndarray:
        v = np.asarray(v, np.float64)
        if self.log:
            with np.errstate(divide="ignore", invalid="ignore"):
                v = np.where(v > 0, np.log10(np.where(v > 0, v, 1.0)), np.nan)
        return self.p0 + (v - self.lo) / (self.hi - self.lo) * (self.p1 - self.p0)

    def ticks(self, target: int) -> tuple[list[tuple[float, str]], list[float]]:
        """(value, label) major ticks and unlabelled minor tick values."""
        if not self.log:
            t, step = nice_ticks(self.lo, self.hi, target)
            return [(float(v), _fmt_tick(float(v), step)) for v in t], []
        k0, k1 = math.ceil(self.lo - 1e-9), math.floor(self.hi + 1e-9)
        n_dec = k1 - k0 + 1
        if self.hi - self.lo >= 2.5 and n_dec >= 2:
            every = max(1, math.ceil(n_dec / target))
            ks = [k for k in range(k0, k1 + 1) if k % every == 0]
            major = [(10.0**k, _fmt_log_tick(10.0**k)) for k in ks]
            minor: list[float] = []
            if every == 1 and self.hi - self.lo <= 8:
                for k in range(k0 - 1, k1 + 1):
                    minor += [m * 10.0**k for m in range(2, 10) if self.lo <= k + math.log10(m) <= self.hi]
            elif every > 1:
                minor = [10.0**k for k in range(k0, k1 + 1) if k % every]
            return major, minor
        # a few decades at most: label 1-2-5 steps, mark the rest; else plain round numbers
        inside = lambda v: self.lo - 1e-9 <= math.log10(v) <= self.hi + 1e-9  # noqa: E731
        vals = [m * 10.0**k for k in range(k0 - 1, k1 + 2) for m in (1, 2, 5) if inside(m * 10.0**k)]
        if len(vals) < 3:
            t, step = nice_ticks(10**self.lo, 10**self.hi, max(3, target // 2))
            return [(float(v), _fmt_tick(float(v), step)) for v in t if v > 0], []
        minor = [m * 10.0**k for k in range(k0 - 1, k1 + 2) for m in (3, 4, 6, 7, 8, 9) if inside(m * 10.0**k)]
        return [(v, _fmt_log_tick(v)) for v in vals], minor


def _clean_xy(xs: Any, ys: Any, logx: bool, logy: bool) -> tuple[np.ndarray, np.ndarray]:
    """Float arrays of equal length; points that cannot be shown become NaN (breaking lines)."""
    y = np.asarray(ys, np.float64).ravel()
    x = np.arange(len(y), dtype=np.float64) if xs is None else np.asarray(xs, np.float64).ravel()
    n = min(len(x), len(y))
    if len(x) != len(y):
        log.warning("plot series with %d x and %d y values; using the first %d", len(x), len(y), n)
    x, y = x[:n].copy(), y[:n].copy()
    bad = ~(np.isfinite(x) & np.isfinite(y))
    if logx:
        bad |= ~(x > 0)
    if logy:
        bad |= ~(y > 0)
    x[bad] = np.nan
    y[bad] = np.nan
    return x, y


def _series_items(series: Mapping[str, Any]) -> list[tuple[str, Any, Any]]:
    out = []
    for name, s in series.items():
        if isinstance(s, tuple) and len(s) == 2:
            out.append((str(name), s[0], s[1]))
        else:  # just y values
            out.append((str(name), None, s))
    return out


class _Figure:
    """Shared plot layout: title, axis titles, ticks, grid, frame, legend and "no data"."""

    def __init__(
        self,
        size: tuple[int, int],
        title: str,
        xlabel: str,
        ylabel: str,
        xr: tuple[float, float] | None,
        yr: tuple[float, float] | None,
        logx: bool,
        logy: bool,
        ypad_lo: bool = True,
        xpad: float = 0.04,
    ) -> None:
        w, h = int(size[0]), int(size[1])
        self.canvas = Canvas(w, h)
        self.s = max(1, round(min(w, h) / 450))
        self.empty = xr is None or yr is None
        self.x = _Axis(*(xr or (0.0, 1.0)), log=logx and not self.empty, pad=xpad)
        self.y = _Axis(*(yr or (0.0, 1.0)), log=logy and not self.empty, pad_lo=ypad_lo)
        s = self.s
        c = self.canvas
        xt, xminor = self.x.ticks(max(3, w // (90 * s)))
        yt, yminor = self.y.ticks(max(3, h // (60 * s)))
        ylab_w = max(text_size(lbl, s)[0] for _, lbl in yt) if yt else 0
        top = 12 * s + (text_size(title, 2 * s)[1] + 10 * s if title else 0)
        left = 10 * s + (CAP_HEIGHT * s + 8 * s if ylabel else 0) + ylab_w + 8 * s
        bottom = 8 * s + GLYPH_HEIGHT * s + 6 * s + (CAP_HEIGHT * s + 10 * s if xlabel else 0)
        right = 16 * s + max(0, text_size(xt[-1][1], s)[0] // 2 if xt else 0)
        self.box = (left, top, w - 1 - right, h - 1 - bottom)
        if self.box[2] - self.box[0] < 10 or self.box[3] - self.box[1] < 10:
            self.box = (0, 0, w - 1, h - 1)
        bx0, by0, bx1, by1 = self.box
        self.x.set_pixels(bx0, bx1)
        self.y.set_pixels(by1, by0)
        grid, tickc, frame = (232, 232, 232), (90, 90, 90), (60, 60, 60)
        if title:
            c.text((bx0 + bx1) / 2, 10 * s, title, BLACK, scale=2 * s, anchor="tc")
        if xlabel:
            c.text((bx0 + bx1) / 2, h - 8 * s - 2 * s, xlabel, BLACK, scale=s, anchor="bc")
        if ylabel:
            c.text(8 * s, (by0 + by1) / 2, ylabel, BLACK, scale=s, anchor="tc", angle=90)
        if not self.empty:
            for v in xminor:
                px = float(self.x.to_px(v))
                c.line(px, by0, px, by1, (244, 244, 244))
                c.line(px, by1, px, by1 + 2 * s, tickc)
            for v in yminor:
                py = float(self.y.to_px(v))
                c.line(bx0, py, bx1, py, (244, 244, 244))
                c.line(bx0 - 2 * s, py, bx0, py, tickc)
            for v, lbl in xt:
                px = float(self.x.to_px(v))
                if bx0 - 0.5 <= px <= bx1 + 0.5:
                    c.line(px, by0, px, by1, grid)
                    c.line(px, by1, px, by1 + 4 * s, tickc, width=s)
                    c.text(px, by1 + 7 * s, lbl, (40, 40, 40), scale=s, anchor="tc")
            for v, lbl in yt:
                py = float(self.y.to_px(v))
                if by0 - 0.5 <= py <= by1 + 0.5:
                    c.line(bx0, py, bx1, py, grid)
                    c.line(bx0 - 4 * s, py, bx0, py, tickc, width=s)
                    c.text(bx0 - 7 * s, py, lbl, (40, 40, 40), scale=s, anchor="mr")
        self.frame_color = frame
        self.legend: list[tuple[str, tuple[int, int, int], str, str | None]] = []
        self.occupied: list[np.ndarray] = []  # (n, 2) pixel points, for legend placement

    def px(self, x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        return self.x.to_px(x), self.y.to_px(y)

    @contextmanager
    def inside(self) -> Iterator[Canvas]:
        bx0, by0, bx1, by1 = self.box
        with self.canvas.clip(bx0 + 1, by0 + 1, bx1 - 1, by1 - 1) as c:
            yield c

    def add_legend(
        self, label: str, color: tuple[int, int, int], style: str = "line", marker: str | None = None
    ) -> None:
        """``style``: "line" (with optional marker), "marker", "box" or "dash"."""
        self.legend.append((label, color, style, marker))

    def finish(self, path: str | Path | None) -> np.ndarray:
        c, s = self.canvas, self.s
        bx0, by0, bx1, by1 = self.box
        if self.empty:
            c.text((bx0 + bx1) / 2, (by0 + by1) / 2, "no data", (150, 150, 150), scale=3 * s, anchor="mc")
        c.rect(bx0, by0, bx1, by1, self.frame_color)
        if self.legend and not self.empty:
            self._draw_legend()
        if path is not None:
            c.to_png(path)
        return c.array

    def _draw_legend(self) -> None:
        c, s = self.canvas, self.s
        bx0, by0, bx1, by1 = self.box
        sw = 22 * s  # swatch width
        row_h = LINE_HEIGHT * s + 4 * s
        tw = max(text_size(lbl, s)[0] for lbl, *_ in self.legend)
        lw = 8 * s + sw + 6 * s + tw + 8 * s
        lh = 6 * s + row_h * len(self.legend) + 2 * s
        inset = 8 * s
        if lw > bx1 - bx0 - 2 * inset or lh > by1 - by0 - 2 * inset:
            inset = 1  # crowded plot: tuck it into a corner anyway
        corners = [
            (bx1 - inset - lw, by0 + inset),  # top right
            (bx0 + inset, by0 + inset),  # top left
            (bx1 - inset - lw, by1 - inset - lh),  # bottom right
            (bx0 + inset, by1 - inset - lh),  # bottom left
        ]
        pts = np.vstack(self.occupied) if self.occupied else np.zeros((0, 2))
        pts = pts[np.isfinite(pts).all(axis=1)]

        def crowd(corner: tuple[float, float]) -> int:
            x0, y0 = corner
            return int(
                np.count_nonzero(
                    (pts[:, 0] >= x0) & (pts[:, 0] <= x0 + lw) & (pts[:, 1] >= y0) & (pts[:, 1] <= y0 + lh)
                )
            )

        lx, ly = min(corners, key=crowd)  # min keeps the first (top right) on ties
        lx, ly = int(round(lx)), int(round(ly))
        c.fill_rect(lx, ly, lx + lw, ly + lh, WHITE)
        c.rect(lx, ly, lx + lw, ly + lh, (170, 170, 170))
        for i, (label, color, style, marker) in enumerate(self.legend):
            cy = ly + 6 * s + i * row_h + (CAP_HEIGHT * s) // 2
            x0, x1 = lx + 8 * s, lx + 8 * s + sw
            if style == "box":
                c.fill_rect(x0, cy - 4 * s, x1, cy + 4 * s, color)
            elif style == "dash":
                c.line(x0, cy, x1, cy, color, width=2 * s, dash=(4 * s, 3 * s))
            elif style == "line":
                c.line(x0, cy, x1, cy, color, width=2 * s)
            if marker:
                c.markers(np.array([(x0 + x1) / 2]), np.array([cy]), color, marker, 3 * s)
            c.text(x1 + 6 * s, cy, label, (20, 20, 20), scale=s, anchor="ml")


def _range(arrays: Sequence[np.ndarray]) -> tuple[float, float] | None:
    vals = [a[np.isfinite(a)] for a in arrays]
    vals = [v for v in vals if len(v)]
    if not vals:
        return None
    return float(min(v.min() for v in vals)), float(max(v.max() for v in vals))


def line_plot(
    path: str | Path | None,
    series: Mapping[str, tuple[Any, Any] | Any],
    title: str = "",
    xlabel: str = "",
    ylabel: str = "",
    logx: bool = False,
    logy: bool = False,
    size: tuple[int, int] = (800, 500),
    markers: bool | None = None,
) -> np.ndarray:
    """Lines with markers, one colour and marker shape per series; ``series`` maps a name to
    ``(xs, ys)`` (or to ys alone, plotted against their index). Non-finite points (and
    non-positive ones on log axes) are skipped and break the line. ``markers=None`` draws them
    when a series has at most 60 points. Writes a PNG to ``path`` (unless None) and returns the
    image."""
    items = [(n, *_clean_xy(x, y, logx, logy)) for n, x, y in _series_items(series)]
    fig = _Figure(
        size, title, xlabel, ylabel, _range([x for _, x, _ in items]), _range([y for _, _, y in items]), logx, logy
    )
    s = fig.s
    for i, (name, x, y) in enumerate(items):
        color = PALETTE[i % len(PALETTE)]
        mk = MARKERS[i % len(MARKERS)]
        n_ok = int(np.count_nonzero(np.isfinite(x)))
        show_mk = (n_ok <= 60) if markers is None else markers
        if n_ok and not fig.empty:
            px, py = fig.px(x, y)
            with fig.inside() as c:
                c.polyline(np.column_stack([px, py]), color, width=2 * s)
                if show_mk:
                    c.markers(px, py, color, mk, 3 * s)
            fig.occupied.append(np.column_stack([px, py]))
        fig.add_legend(name if n_ok else f"{name} (no data)", color, "line", mk if show_mk else None)
    return fig.finish(path)


def scatter_plot(
    path: str | Path | None,
    points: Mapping[str, tuple[Any, Any]],
    title: str = "",
    xlabel: str = "",
    ylabel: str = "",
    logx: bool = False,
    logy: bool = False,
    highlight: tuple[Any, Any] | None = None,
    highlight_label: str = "Pareto front",
    size: tuple[int, int] = (800, 500),
) -> np.ndarray:
    """Scatter of named point sets, one colour and marker each. ``highlight`` points (e.g. the
    Pareto front) are joined by a line, in x order, drawn on top. Non-finite points (and
    non-positive ones on log axes) are skipped. Writes a PNG to ``path`` (unless None) and
    returns the image."""
    items = [(n, *_clean_xy(x, y, logx, logy)) for n, x, y in _series_items(points)]
    hx = hy = None
    if highlight is not None:
        hx, hy = _clean_xy(highlight[0], highlight[1], logx, logy)
        ok = np.isfinite(hx)
        order = np.argsort(hx[ok], kind="stable")
        hx, hy = hx[ok][order], hy[ok][order]
    xs = [x for _, x, _ in items] + ([hx] if hx is not None else [])
    ys = [y for _, _, y in items] + ([hy] if hy is not None else [])
    fig = _Figure(size, title, xlabel, ylabel, _range(xs), _range(ys), logx, logy)
    s = fig.s
    total = sum(int(np.count_nonzero(np.isfinite(x))) for _, x, _ in items)
    msize = (3 if total <= 2000 else 2 if total <= 50_000 else 1) * s
    for i, (name, x, y) in enumerate(items):
        color = PALETTE[i % len(PALETTE)]
        mk = MARKERS[i % len(MARKERS)]
        n_ok = int(np.count_nonzero(np.isfinite(x)))
        if n_ok and not fig.empty:
            px, py = fig.px(x, y)
            with fig.inside() as c:
                c.markers(px, py, color, mk, msize)
            fig.occupied.append(np.column_stack([px, py]))
        fig.add_legend(name if n_ok else f"{name} (no data)", color, "marker", mk)
    if hx is not None:
        hcolor = (20, 20, 20)
        if len(hx) and not fig.empty:
            px, py = fig.px(hx, hy)
            with fig.inside() as c:
                c.polyline(np.column_stack([px, py]), hcolor, width=2 * s)
                c.markers(px, py, (255, 255, 255), "o", 4 * s)
                c.markers(px, py, hcolor, "o", 3 * s)
            fig.occupied.append(np.column_stack([px, py]))
        fig.add_legend(highlight_label, hcolor, "line", "o")
    return fig.finish(path)


_MARKER_COLORS = (PALETTE[3], PALETTE[1], PALETTE[2], PALETTE[4], PALETTE[6], PALETTE[5], PALETTE[9])


def histogram(
    path: str | Path | None,
    values: Any,
    bins: int = 50,
    title: str = "",
    xlabel: str = "",
    ylabel: str = "count",
    size: tuple[int, int] = (800, 500),
    markers: Mapping[str, float] | None = None,
    label: str | None = None,
) -> np.ndarray:
    """Histogram of the finite ``values`` in ``bins`` equal bins, with optional labelled vertical
    dashed lines (``markers={"p50": 1.2, "p99": 3.4}``). The legend shows the sample count (or
    ``label``) and each marker's value. Writes a PNG to ``path`` (unless None) and returns the
    image."""
    v = np.asarray(values, np.float64).ravel()
    n_bad = int(np.count_nonzero(~np.isfinite(v)))
    v = v[np.isfinite(v)]
    mk = {str(k): float(x) for k, x in (markers or {}).items() if x is not None and math.isfinite(float(x))}
    if len(v):
        counts, edges = np.histogram(v, bins=max(1, int(bins)))
        lo, hi = float(edges[0]), float(edges[-1])
        if mk:
            lo, hi = min(lo, *mk.values()), max(hi, *mk.values())
        xr: tuple[float, float] | None = (lo, hi)
        yr: tuple[float, float] | None = (0.0, float(counts.max()))
    else:
        counts, edges, xr, yr = np.zeros(0), np.zeros(1), None, None
    fig = _Figure(size, title, xlabel, ylabel, xr, yr, False, False, ypad_lo=False, xpad=0.02)
    s = fig.s
    bar = (31, 119, 180)
    edge = (20, 80, 130)
    if len(v):
        px = fig.x.to_px(edges)
        py = fig.y.to_px(counts)
        base = fig.y.to_px(0.0)
        with fig.inside() as c:
            for i, n in enumerate(counts):
                if n <= 0:
                    continue
                x0, x1 = px[i], px[i + 1]
                c.fill_rect(math.ceil(x0), py[i], math.floor(x1), base, bar)
                if x1 - x0 >= 4:
                    c.rect(math.ceil(x0), py[i], math.floor(x1), base, edge)
        fig.occupied.append(np.column_stack([(px[:-1] + px[1:]) / 2, py]))
        extra = f", {n_bad} non-finite skipped" if n_bad else ""
        fig.add_legend(label or f"n = {len(v)}{extra}", bar, "box")
        bx0, by0, bx1, by1 = fig.box
        with fig.inside() as c:
            for i, (name, x) in enumerate(sorted(mk.items(), key=lambda kv: kv[1])):
                color = _MARKER_COLORS[i % len(_MARKER_COLORS)]
                xp = float(fig.x.to_px(x))
                c.line(xp, by0, xp, by1, color, width=2 * s, dash=(6 * s, 4 * s))
                ty = by0 + 6 * s + i * (LINE_HEIGHT * s + 2 * s)
                right = xp + 5 * s + text_size(name, s)[0] < bx1 - 2
                c.text(xp + 5 * s if right else xp - 5 * s, ty, name, color, scale=s, anchor="tl" if right else "tr")
                fig.add_legend(f"{name} = {_fmt_num(x)}", color, "dash")
                fig.occupied.append(np.column_stack([np.full(24, xp), np.linspace(by0, by1, 24)]))
    return fig.finish(path)


# ----------------------------------------------------------------------------------------------
# Cloth rendering


def _rot_x(a: float) -> np.ndarray:
    c, s = math.cos(a), math.sin(a)
    return np.array([[1, 0, 0], [0, c, -s], [0, s, c]])


def _rot_y(a: float) -> np.ndarray:
    c, s = math.cos(a), math.sin(a)
    return np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]])


#: World to view rotations; rows are the screen's right, up and toward-the-viewer axes.
VIEWS: dict[str, np.ndarray] = {
    "front": np.eye(3),  # looking down -Z
    "side": np.array([[0.0, 0, -1], [0, 1, 0], [1, 0, 0]]),  # from +X, looking down -X
    "top": np.array([[1.0, 0, 0], [0, 0, -1], [0, 1, 0]]),  # from above, +Z toward the bottom
    "iso": _rot_x(math.radians(25)) @ _rot_y(math.radians(-35)),  # yaw 35 deg, pitch 25 deg down
}
_LIGHT = np.array([-0.35, 0.55, 0.76]) / np.linalg.norm([-0.35, 0.55, 0.76])  # in view space
AMBIENT = 0.3


class _Camera:
    """Orthographic projection fitting world ``bounds`` into a pixel rectangle."""

    def __init__(self, view: str, bounds: np.ndarray, rect: tuple[float, float, float, float]) -> None:
        if view not in VIEWS:
            raise ValueError(f"view must be one of {sorted(VIEWS)}, got {view!r}")
        self.R = VIEWS[view]
        lo, hi = bounds
        corners = np.array([[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1]) for z in (lo[2], hi[2])])
        v = corners @ self.R.T
        umin, vmin = v[:, 0].min(), v[:, 1].min()
        umax, vmax = v[:, 0].max(), v[:, 1].max()
        x0, y0, x1, y1 = rect
        du, dv = umax - umin, vmax - vmin
        scale_u = (x1 - x0) / du if du > 1e-12 else math.inf
        scale_v = (y1 - y0) / dv if dv > 1e-12 else math.inf
        self.scale = min(scale_u, scale_v)
        if not math.isfinite(self.scale):
            self.scale = 1.0
        self.uc, self.vc = (umin + umax) / 2, (vmin + vmax) / 2
        self.cx, self.cy = (x0 + x1) / 2, (y0 + y1) / 2

    def view(self, p: np.ndarray) -> np.ndarray:
        return np.asarray(p, np.float64) @ self.R.T

    def screen(self, v: np.ndarray) -> np.ndarray:
        """View coordinates (..., 3) to screen (..., 2)."""
        return np.stack(
            [self.cx + (v[..., 0] - self.uc) * self.scale, self.cy - (v[..., 1] - self.vc) * self.scale], axis=-1
        )


def _fit_bounds(
    cloths: Sequence[tuple[np.ndarray, np.ndarray, Any]],
    spheres: Sequence[Sequence[Any]],
    capsules: Sequence[Sequence[Any]],
    margin: float = 0.05,
) -> np.ndarray:
    pts = []
    for pos, _, _ in cloths:
        p = np.asarray(pos, np.float64).reshape(-1, 3)
        pts.append(p[np.isfinite(p).all(axis=1)])
    for sph in spheres:
        c, r = np.asarray(sph[0], np.float64), float(sph[1])
        pts.append(np.array([c - r, c + r]))
    for cap in capsules:
        a, b, r = np.asarray(cap[0], np.float64), np.asarray(cap[1], np.float64), float(cap[2])
        pts.append(np.array([a - r, a + r, b - r, b + r]))
    allp = np.vstack(pts) if pts else np.zeros((0, 3))
    if len(allp) == 0:
        return np.array([[-1.0, -1.0, -1.0], [1.0, 1.0, 1.0]])
    lo, hi = allp.min(axis=0), allp.max(axis=0)
    ext = max(float((hi - lo).max()), 1e-6)
    return np.array([lo - margin * ext, hi + margin * ext])


def _shade(base: np.ndarray, intensity: np.ndarray) -> np.ndarray:
    return np.clip(base[None, :].astype(np.float64) * intensity[:, None], 0, 255).astype(np.uint8)


def _draw_ball(canvas: Canvas, x: float, y: float, r: float, color: np.ndarray) -> None:
    """A lit sphere of screen radius ``r`` (per-pixel lambert, one-sided, with ambient)."""
    box = canvas._disc_box(x, y, r)
    if box is None or r <= 0:
        return
    xx, yy = box
    nx = (xx - x) / max(r, 1e-9)
    ny = -(yy - y) / max(r, 1e-9)
    d2 = nx**2 + ny**2
    m = d2 <= 1.0 + 0.35 / max(r, 1)
    nz = np.sqrt(np.clip(1 - d2[m], 0, 1))
    lam = np.clip(nx[m] * _LIGHT[0] + ny[m] * _LIGHT[1] + nz * _LIGHT[2], 0, 1)
    inten = AMBIENT + (1 - AMBIENT) * lam
    canvas._a[yy[m], xx[m]] = _shade(color, inten)


def _draw_floor(canvas: Canvas, cam: _Camera, bounds: np.ndarray, y: float) -> None:
    lo, hi = bounds
    corners = np.array([[lo[0], y, lo[2]], [hi[0], y, lo[2]], [hi[0], y, hi[2]], [lo[0], y, hi[2]]])
    sc = cam.screen(cam.view(corners))
    canvas.triangles_fill(np.array([sc[[0, 1, 2]], sc[[0, 2, 3]]]), np.array([[238, 238, 234]] * 2))
    ext = float(max(hi[0] - lo[0], hi[2] - lo[2]))
    _, step = nice_ticks(0, ext, 8)
    segs = []
    for x in np.arange(math.ceil(lo[0] / step) * step, hi[0] + 1e-9, step):
        segs.append([[x, y, lo[2]], [x, y, hi[2]]])
    for z in np.arange(math.ceil(lo[2] / step) * step, hi[2] + 1e-9, step):
        segs.append([[lo[0], y, z], [hi[0], y, z]])
    if segs:
        s2 = cam.screen(cam.view(np.array(segs)))
        canvas.lines(s2.reshape(-1, 4), (205, 205, 200))
    canvas.polyline(sc, (150, 150, 145), closed=True)


def _as_positions(p: Any) -> np.ndarray:
    a = np.asarray(p, np.float64)
    if a.ndim != 2 or a.shape[1] != 3:
        a = a.reshape(-1, 3)
    return a


def _draw_scene(
    canvas: Canvas,
    cloths: Sequence[tuple[Any, Any, Any]],
    view: str,
    bounds: Any,
    spheres: Sequence[Sequence[Any]] = (),
    capsules: Sequence[Sequence[Any]] = (),
    floor: bool = False,
    floor_y: float | None = None,
    rect: tuple[float, float, float, float] | None = None,
    margin: float = 0.05,
) -> _Camera:
    cl = [(_as_positions(p), np.asarray(t, np.int64).reshape(-1, 3), c) for p, t, c in cloths]
    b = _fit_bounds(cl, spheres, capsules, margin) if bounds is None else np.asarray(bounds, np.float64).reshape(2, 3)
    if rect is None:
        pad = 4
        rect = (pad, pad, canvas.width - 1 - pad, canvas.height - 1 - pad)
    cam = _Camera(view, b, rect)
    if floor:
        _draw_floor(canvas, cam, b, float(b[0][1] if floor_y is None else floor_y))
    # every primitive gets a depth (larger = nearer); draw far to near
    tri_screen, tri_color, tri_depth = [], [], []
    for pos, tris, color in cl:
        if len(tris) == 0:
            continue
        if tris.min() < 0 or tris.max() >= len(pos):
            raise ValueError(f"triangle indices out of range for {len(pos)} positions")
        v = cam.view(pos)[tris]  # (m, 3, 3)
        ok = np.isfinite(v).all(axis=(1, 2))
        v = v[ok]
        nrm = np.cross(v[:, 1] - v[:, 0], v[:, 2] - v[:, 0])
        ln = np.linalg.norm(nrm, axis=1)
        lam = np.abs(nrm @ _LIGHT) / np.where(ln > 0, ln, 1)
        inten = AMBIENT + (1 - AMBIENT) * lam
        tri_screen.append(cam.screen(v))
        tri_color.append(_shade(_rgb(color), inten))
        tri_depth.append(v[:, :, 2].mean(axis=1))
    balls: list[tuple[np.ndarray, float, np.ndarray]] = []  # view centre, world radius, colour
    for sph in spheres:
        col = _rgb(sph[2]) if len(sph) > 2 else np.array([165, 160, 150], np.uint8)
        balls.append((cam.view(np.asarray(sph[0], np.float64)), float(sph[1]), col))
    for cap in capsules:
        a, bb, r = cam.view(np.asarray(cap[0], np.float64)), cam.view(np.asarray(cap[1], np.float64)), float(cap[2])
        col = _rgb(cap[3]) if len(cap) > 3 else np.array([165, 160, 150], np.uint8)
        length_px = float(np.linalg.norm((bb - a)[:2])) * cam.scale
        r_px = max(r * cam.scale, 0.5)
        n = int(min(400, max(2, math.ceil(length_px / max(r_px * 0.15, 0.5)) + 1)))
        for t in np.linspace(0, 1, n):
            balls.append((a + t * (bb - a), r, col))
    ts = np.concatenate(tri_screen) if tri_screen else np.zeros((0, 3, 2))
    tc = np.concatenate(tri_color) if tri_color else np.zeros((0, 3), np.uint8)
    td = np.concatenate(tri_depth) if tri_depth else np.zeros(0)
    bd = np.array([bl[0][2] for bl in balls]) if balls else np.zeros(0)
    depth = np.concatenate([td, bd])
    kind = np.concatenate([np.zeros(len(td), np.int64), np.ones(len(bd), np.int64)])
    ref = np.concatenate([np.arange(len(td)), np.arange(len(bd))])
    order = np.argsort(depth, kind="stable")
    kind, ref = kind[order], ref[order]
    i = 0
    while i < len(order):
        if kind[i] == 1:
            c, r, col = balls[ref[i]]
            sx, sy = cam.screen(c)
            _draw_ball(canvas, float(sx), float(sy), r * cam.scale, col)
            i += 1
            continue
        j = i
        while j < len(order) and kind[j] == 0:
            j += 1
        sel = ref[i:j]
        canvas.triangles_fill(ts[sel], tc[sel])
        i = j
    return cam


def render_cloth(
    canvas_or_size: Canvas | tuple[int, int],
    positions: np.ndarray,
    triangles: np.ndarray,
    view: str = "iso",
    bounds: Any = None,
    color: ColorLike = (70, 110, 200),
) -> np.ndarray:
    """Draw one triangle mesh: orthographic ``view`` ("front", "side", "top" or "iso": yaw 35 deg,
    pitch 25 deg), triangles sorted back to front and shaded by |normal . light| with ambient.

    ``canvas_or_size`` is a :class:`Canvas` to draw on or a ``(width, height)`` for a new white
    one. ``bounds = ((xmin, ymin, zmin), (xmax, ymax, zmax))`` fixes the camera (for animation
    frames); None fits the mesh with a margin. Triangles with non-finite corners are skipped.
    Returns the image array (the canvas's own buffer when one was given).
    """
    canvas = canvas_or_size if isinstance(canvas_or_size, Canvas) else Canvas(*canvas_or_size)
    _draw_scene(canvas, [(positions, triangles, color)], view, bounds)
    return canvas.array


def render_scene(
    size: tuple[int, int],
    cloths: Sequence[tuple[Any, Any, ColorLike]],
    view: str = "iso",
    bounds: Any = None,
    title: str | None = None,
    spheres: Sequence[Sequence[Any]] = (),
    capsules: Sequence[Sequence[Any]] = (),
    floor: bool = True,
    floor_y: float | None = None,
    supersample: int = 1,
) -> np.ndarray:
    """Render several cloths ``(positions, triangles, color)`` with colliders on a new canvas.

    ``spheres`` are ``(center, radius[, color])``, ``capsules`` ``(p0, p1, radius[, color])``;
    they are shaded balls (a capsule is drawn as the union of balls along its axis) sorted
    together with the cloth triangles by depth. ``floor`` draws a grid on the plane
    ``y = floor_y`` (default: the bottom of the bounds), seen edge-on as a ground line from the
    front and side. ``bounds`` as in :func:`render_cloth`; fixed bounds keep animation frames
    steady. ``supersample`` > 1 renders larger and averages down (smoother edges). ``title`` is
    written across the top. Returns a ``uint8`` (height, width, 3) array.
    """
    w, h = int(size[0]), int(size[1])
    k = max(1, int(supersample))
    s = max(1, round(min(w, h) / 450))
    top = (CAP_HEIGHT * 2 * s + 12 * s) if title else 0
    canvas = Canvas(w * k, h * k)
    pad = 6 * k
    _draw_scene(
        canvas,
        cloths,
        view,
        bounds,
        spheres,
        capsules,
        floor,
        floor_y,
        rect=(pad, top * k + pad, w * k - 1 - pad, h * k - 1 - pad),
    )
    img = canvas.array
    if k > 1:
        img = img.reshape(h, k, w, k, 3).mean(axis=(1, 3)).round().astype(np.uint8)
    if title:
        out = Canvas.wrap(np.ascontiguousarray(img))
        out.text(w / 2, 6 * s, title, (20, 20, 20), scale=2 * s, anchor="tc")
        img = out.array
    return img


__all__ = [
    "ADVANCE",
    "CAP_HEIGHT",
    "Canvas",
    "FONT",
    "GIF_PALETTE",
    "GLYPH_HEIGHT",
    "GLYPH_WIDTH",
    "LINE_HEIGHT",
    "MARKERS",
    "PALETTE",
    "TRANSPARENT_INDEX",
    "VIEWS",
    "draw_text",
    "encode_gif",
    "encode_png",
    "histogram",
    "line_plot",
    "nice_ticks",
    "quantize",
    "render_cloth",
    "render_scene",
    "scatter_plot",
    "text_mask",
    "text_size",
    "write_gif",
    "write_png",
]
