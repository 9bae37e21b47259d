"""Buffers kept across frame plans: how large a buffer made for a plan is, and when one is kept.

A plan change (a cloth comes or goes) must not allocate the whole frame again (about 400 MB of
device buffers and pinned host frames at 8192 predictive cloths). A buffer is kept while it
holds the new plan's bytes and is not far too large (:func:`fits`); otherwise it is made anew at
:func:`capacity`: grown geometrically (x :data:`GROW`), or, when a load shrank below
1 / :data:`SHRINK` of it, made smaller so that the memory goes back. :class:`ReusedBuffer` is
one device buffer under that rule, counting the buffers it made (the tests count them).
"""

from __future__ import annotations

import pyopencl as cl

GROW = 1.5  # a buffer that must grow is made this much larger than the last one (or than needed)
SHRINK = 4  # a buffer more than this many times larger than needed is made smaller
SMALL = 1 << 20  # bytes: a buffer this small is never made smaller


def fits(have: int, need: int) -> bool:
    """Whether a buffer of ``have`` bytes is kept for ``need`` bytes."""
    return need <= have and (have <= SHRINK * need or have <= SMALL)


def capacity(have: int, need: int) -> int:
    """The bytes of a new buffer for ``need`` bytes replacing one of ``have`` that does not fit
    (8-byte aligned): x GROW the old one when growing, x GROW what is needed when shrinking."""
    cap = max(need, int(GROW * have)) if need > have else int(GROW * need)
    return max(8, -(-cap // 8) * 8)


class ReusedBuffer:
    """A device buffer of ``flags`` kept from plan to plan while it :func:`fits`."""

    def __init__(self, ctx: cl.Context, flags: int) -> None:
        self.ctx, self.flags = ctx, flags
        self.buf: cl.Buffer | None = None
        self.made = 0  # buffers made so far

    def get(self, need: int) -> cl.Buffer:
        """A buffer of at least ``need`` bytes: the same one as last time when it fits."""
        have = self.buf.size if self.buf is not None else 0
        if self.buf is None or not fits(have, need):
            self.buf = cl.Buffer(self.ctx, self.flags, capacity(have, need))
            self.made += 1
        return self.buf
