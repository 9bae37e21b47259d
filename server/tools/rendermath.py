"""The drawing's colour and vector arithmetic (server/tools/render.py and its parts): sRGB
0-255 colours to linear light and back (highlights rolled off, not clipped), unit vectors."""

from __future__ import annotations

from collections.abc import Sequence
from functools import lru_cache
from typing import Any

import numpy as np

Colour = tuple[int, int, int]


def unit(v: np.ndarray) -> np.ndarray:
    n = np.linalg.norm(v, axis=-1, keepdims=True)
    return v / np.where(n > 0, n, 1.0)


def linear(c: Any) -> np.ndarray:
    """sRGB 0-255 colours (..., 3) to linear 0-1."""
    return (np.asarray(c, np.float64)[..., :3] / 255.0) ** 2.2


@lru_cache(maxsize=1)
def srgb_table() -> np.ndarray:
    """Linear 0..2 in 4096 steps to sRGB uint8, highlights above 0.8 rolled off, not clipped."""
    x = np.linspace(0.0, 2.0, 4096)
    x = np.where(x > 0.8, 0.8 + 0.2 * np.tanh((x - 0.8) / 0.2), x)
    return np.clip(255.0 * x ** (1 / 2.2) + 0.5, 0, 255).astype(np.uint8)


def srgb(x: np.ndarray) -> np.ndarray:
    """Linear colours to sRGB 0-255 uint8 (by table)."""
    i = np.clip(x * (4095 / 2.0), 0, 4095).astype(np.int32)
    return srgb_table()[i]


def rgb(c: Sequence[int]) -> Colour:
    return int(c[0]), int(c[1]), int(c[2])
