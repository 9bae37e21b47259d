"""Rates per subscriber on the Python SDK's side (protocol 1.8, 1.9's lower rates; PROTOCOL.md
9.3): which key a subscription takes (every k-th state: :func:`drape.client.protocol.every_key`),
which rates a server serves (:func:`drape.client.protocol.served_rates`: 2 and 3 since 1.8, 6 and
12 since 1.9) and, with ``rate="auto"``, :class:`RateGovernor`, which steps a subscription down
the ladder of the rates its server serves (60 -> 30 -> 20 -> 10 -> 5 Hz at the default tick on a
1.9 server, stopping at 20 Hz on a 1.8 one) when its states arrive late or too few, and back up
after a quiet period.

"Late" is measured without a shared clock: a state's lateness is its ``receive - server`` time
minus the smallest such difference seen lately (the clock offset plus the link's shortest delay,
as smoothing.ServerClock takes it), so only the queueing on the way counts. Over each window
(``window_s`` of receive time) the governor looks at the 90th percentile of that lateness and at
the share of the window's states (at the current rate) that never came; either over its bound
steps down, one rate at a time, or straight to the lowest when the lateness is far over
(``jump_s``: a link far too slow, where each step would cost another window of backlog). A
step up waits ``quiet_s`` of good windows, doubled (up to ``max_quiet_s``) each time a step up
is followed by a step down in the first window judged after it, so a link that cannot carry the
higher rate is not probed every few seconds. The first window after a change is not judged
(what was queued before it drains). Every input is an argument (the receive time included), so
tests drive it with injected times.
"""

from __future__ import annotations

import logging
from collections import deque
from dataclasses import dataclass, field

import numpy as np

from . import protocol as P

log = logging.getLogger(__name__)

AUTO = "auto"


def fit_rate(rate: int, served: tuple[int, ...]) -> int:
    """The rate a subscription asking for every ``rate``-th state takes from a server serving
    ``served`` (protocol.served_rates): ``rate`` itself, or the served rate nearest below it (a
    1.8 server asked for 6 or 12 gives every 3rd state)."""
    return max(k for k in served if k <= rate)


def rate_option(rate: int | str) -> tuple[int, bool]:
    """(the rate to start at, whether it is governed) of a client's ``rate`` option: one of
    ``protocol.RATES`` or ``"auto"`` (start at full rate)."""
    if rate == AUTO:
        return 1, True
    if rate not in P.RATES:
        raise ValueError(f"rate={rate!r}: one of {P.RATES} or {AUTO!r}")
    return int(rate), False


@dataclass
class RateGovernor:
    """Steps one subscription's rate down when its states arrive late, up after a quiet period."""

    window_s: float = 1.0
    late_s: float = 0.05  # lateness (90th percentile over a window) past which it steps down
    jump_s: float = 0.2  # lateness past which it steps straight to the lowest rate (a link far too slow)
    lost_share: float = 0.25  # share of a window's states that never came past which it steps down
    quiet_s: float = 5.0  # good windows' length before a step up
    max_quiet_s: float = 60.0
    rates: tuple[int, ...] = P.RATES
    rate: int = 1
    step_downs: int = 0
    step_ups: int = 0
    _base_window: int = 30  # windows the lateness baseline (the smallest difference) is kept over
    _start: int | None = None  # receive time (ns) of the window's first state
    _first_tick: int = 0
    _last_tick: int = 0
    _diffs: list[int] = field(default_factory=list)
    _mins: deque[int] = field(default_factory=deque)
    _settle_until: int = 0
    _good_since: int | None = None
    _up_at: int | None = None
    _quiet: float = 0.0

    def __post_init__(self) -> None:
        self._quiet = self.quiet_s
        self._mins = deque(maxlen=self._base_window)

    def limit(self, rates: tuple[int, ...]) -> int:
        """The ladder of the rates the subscription's server serves (protocol.served_rates: a
        subscription placed, or failed over, on a 1.8 server stops at 3); the rate it is at now
        (fit_rate: the current one, or the served one below it)."""
        self.rates = rates
        self.rate = fit_rate(self.rate, rates)
        return self.rate

    def observe(self, tick: int, server_ns: int, receive_ns: int) -> int | None:
        """A state (or bundle) of ``tick`` stamped ``server_ns`` by the server arrived at
        ``receive_ns``; the new rate when this changes it, else None."""
        if not server_ns or not receive_ns:
            return None
        if self._start is None:
            self._start, self._first_tick, self._diffs = receive_ns, tick, []
        self._diffs.append(receive_ns - server_ns)
        self._last_tick = max(self._last_tick, tick)
        if receive_ns - self._start < self.window_s * 1e9:
            return None
        return self._judge(receive_ns)

    def _judge(self, now: int) -> int | None:
        diffs = np.array(self._diffs, np.int64)
        self._mins.append(int(diffs.min()))
        expected = (self._last_tick - self._first_tick) // self.rate + 1
        lost = 1.0 - min(len(diffs), expected) / max(expected, 1)
        late = float(np.percentile(diffs - min(self._mins), 90)) / 1e9
        self._start = None
        self._last_tick = 0
        log.debug(
            "every %d: %d states, late %.1f ms (p90), %.0f %% lost", self.rate, len(diffs), late * 1e3, 100 * lost
        )
        if now < self._settle_until:
            return None
        i = self.rates.index(self.rate)
        if late > self.late_s or lost > self.lost_share:
            self._good_since = None
            if i + 1 >= len(self.rates):
                return None
            if self._up_at is not None and now - self._up_at <= 3 * self.window_s * 1e9:
                self._quiet = min(2 * self._quiet, self.max_quiet_s)  # the step up did not hold
            self._up_at = None
            self.step_downs += 1
            return self._change(self.rates[-1] if late > self.jump_s else self.rates[i + 1], now)
        if self._good_since is None:
            self._good_since = now
        if i > 0 and now - self._good_since >= self._quiet * 1e9:
            self.step_ups += 1
            self._up_at = now
            self._good_since = None
            return self._change(self.rates[i - 1], now)
        return None

    def _change(self, rate: int, now: int) -> int:
        self.rate = rate
        self._settle_until = now + int(1.5 * self.window_s * 1e9)  # the next window is not judged
        return rate


__all__ = ["AUTO", "RateGovernor", "fit_rate", "rate_option"]
