"""Rendering between states: a renderer that draws faster than the server ticks (144 Hz against
60) shows the same state for two or three frames unless it samples the cloth at its own frame
time. :func:`sample` gives the positions at a render time from the last two states: interpolated
(the default: the render time runs ``delay`` behind the newest state, so it almost always lies
between two received states) or extrapolated (no delay added; a guess past the newest state).

The render time is on the client's clock; the states carry the server's. :class:`ServerClock`
maps one to the other by the smallest ``receive - server`` time seen lately: the clock offset plus
the network's shortest delay (what the smallest value over a window measures best).

The latency it adds: interpolation shows the cloth as it was ``delay`` before the newest state
arrived (default one tick, 16.7 ms at 60 Hz); extrapolation adds none but overshoots where the
motion turns (by up to ``velocity x max_ahead``)."""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass

import numpy as np

from .protocol import ClothState


@dataclass
class ServerClock:
    """The client's clock as the server's: ``server_ns = client_ns - offset``."""

    window: int = 120  # states whose receive - server difference are kept (2 s at 60 Hz)

    def __post_init__(self) -> None:
        self._diffs: deque[int] = deque(maxlen=self.window)
        self._min: int | None = None

    def observe(self, st: ClothState) -> None:
        if st.receive_time_ns and st.server_time_ns and not st.extrapolated:
            d = st.receive_time_ns - st.server_time_ns
            if len(self._diffs) == self._diffs.maxlen:
                gone = self._diffs.popleft()
                self._diffs.append(d)
                if gone == self._min:
                    self._min = min(self._diffs)
                    return
            else:
                self._diffs.append(d)
            self._min = d if self._min is None else min(self._min, d)

    @property
    def offset_ns(self) -> int | None:
        """client time - server time of the fastest recent state (None before any)."""
        return self._min

    def to_server(self, client_ns: int) -> int | None:
        return None if self._min is None else client_ns - self._min


def sample(
    prev: ClothState | None,
    last: ClothState | None,
    server_ns: int,
    delay_ns: int | None = None,
    extrapolate: bool = False,
    max_ahead: float = 1.0,
) -> np.ndarray | None:
    """The positions at server time ``server_ns`` (a render time already on the server's clock)
    from the last two states ``prev`` and ``last``: interpolated at ``server_ns - delay_ns``
    (``delay_ns`` None: the time between the two states, one tick) and held at the ends;
    ``extrapolate``: at ``server_ns`` itself, up to ``max_ahead`` state intervals past ``last``.
    None before any state; ``last``'s positions when there is one state only."""
    if last is None:
        return None
    if prev is None or last.server_time_ns <= prev.server_time_ns or prev.n_vertices != last.n_vertices:
        return last.positions
    span = last.server_time_ns - prev.server_time_ns
    t = server_ns if extrapolate else server_ns - (span if delay_ns is None else delay_ns)
    a = (t - prev.server_time_ns) / span
    a = min(max(a, 0.0), 1.0 + max_ahead) if extrapolate else min(max(a, 0.0), 1.0)
    out = prev.positions + np.float32(a) * (last.positions - prev.positions)
    return out.astype(np.float32, copy=False)
