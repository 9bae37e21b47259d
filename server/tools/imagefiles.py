"""The drawing's files (server/tools/render.py): frames written as PNG and as an animated GIF
with one palette for all frames. Pillow is imported inside the functions (the ``tools``
extra)."""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import numpy as np


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
    delay = 10 * max(2, round(100 / fps))  # GIF delays are whole centiseconds (67 ms would be stored as 60)
    pal[0].save(p, save_all=True, append_images=pal[1:], duration=delay, loop=0, optimize=False, disposal=1)
    return p
