"""The admission scenarios of ``drape chaos`` (issue 26; see :mod:`drape.server.tools.chaos`): one
client's work must not take the other clients' ticks. Each judged by the good client (its state
rate, missed ticks, states lost; :func:`~.chaos_faults.judge`) and by what the heavy request got:

- ``heavy-control``: an admitted 64x64 cloth raised by a control to 100 iterations x 100
  substeps (admission used to check submissions by vertices only): refused ``overloaded``, or
  served without touching the good client;
- ``big-beside-small``: one plain 256x256 cloth beside the good client's small steady load
  (a rule that trusted one load once let it in, 3 runs of 5);
- ``share``: one client submits heavy cloths until it is refused, then a newcomer's small cloth
  must be admitted (a client's share must not lock others out).

``big-submit`` (:mod:`.chaos_faults`) is the heavy submission. Bounded in messages and seconds;
talks only to 127.0.0.1.
"""

from __future__ import annotations

import time
from collections import Counter
from typing import Any

from drape.client import protocol as P

from .chaos_faults import RETRY_LATER, Context, Stage, _one_heavy, grid_request, judge
from .chaos_window import Window

SHARE_CLOTHS = 60  # share: the filler's submits at most (under the default max_cloths_per_client of 64)
SHARE_REFUSALS = 3  # share: the filler stops after this many refusals in a row (1 s apart: ticks get measured)


def _served_or_refused(m: dict[str, Any], outcome: str) -> list[str]:
    """The heavy request refused ('overloaded') or served without touching others (judge)."""
    fails = judge(m)
    if outcome not in ("ok", "overloaded"):
        fails.append(f"the heavy request got {outcome}")
    return fails


def heavy_control(ctx: Context) -> dict[str, Any]:
    """An admitted 64x64 cloth raised by a control to 100 iterations x 100 substeps."""
    with Stage(ctx, "heavy-control") as st:
        st.declare_alive("heavy")  # a game's client: its cloth is not reclaimed while it waits
        base = st.baseline()
        for _ in range(10):  # a plain cloth: 'overloaded' only while the host's noise fills the ticks
            submitted, reply = st.submit(grid_request("heavy", 64))
            if submitted not in RETRY_LATER:
                break
            time.sleep(1.0)
        time.sleep(1.0)  # the plain cloth's own arrival (a new group's buffers) is not the control's
        w = Window.open(st.server)
        ctl = P.ControlRequest(reply.get("cloth", ""), reply.get("token", ""), iterations=100, substeps=100)
        outcome, _ = st.request("control", P.encode_control(ctl), client="heavy")
        time.sleep(ctx.seconds)
        m = w.close([st.good] if st.good else [])
        st.remove(reply)
    m.update(baseline=base, submit_outcome=submitted, control_outcome=outcome)
    fails = _served_or_refused(m, outcome)
    if submitted != "ok":
        fails.append(f"the plain 64x64 cloth was not admitted ({submitted})")
    return {**m, "fails": fails}


def big_beside_small(ctx: Context) -> dict[str, Any]:
    """One plain 256x256 cloth beside the good client's small steady load."""
    out = _one_heavy(ctx, "big-beside-small", grid_request("big", 256), max(ctx.seconds, 10.0))
    if out.get("submit_outcome") not in ("ok", "overloaded"):
        out["fails"].append(f"the big cloth's submit got {out.get('submit_outcome')}")
    return out


def share(ctx: Context) -> dict[str, Any]:
    """A client submits heavy cloths until refused; then a newcomer's small cloth must get in."""
    with Stage(ctx, "share") as st:
        for client in ("filler", "newcomer"):  # game clients: the filler's cloths stay while it fills
            st.declare_alive(client)
        base = st.baseline()
        w = Window.open(st.server)
        outcomes: Counter[str] = Counter()
        replies = []
        refused_in_a_row = 0
        for _ in range(SHARE_CLOTHS):
            o, r = st.submit(grid_request("filler", 32, quality="accurate"))
            outcomes[o] += 1
            if o == "ok":
                replies.append(r)
                refused_in_a_row = 0
                continue
            refused_in_a_row += 1
            if o not in RETRY_LATER or refused_in_a_row >= SHARE_REFUSALS:
                break
            time.sleep(1.0)
        newcomer, nreply = st.submit(grid_request("newcomer", 16))
        time.sleep(ctx.seconds)
        m = w.close([st.good] if st.good else [])
        for r in [*replies, nreply]:
            st.remove(r)
    m.update(baseline=base, filler_admitted=len(replies), filler_outcomes=dict(outcomes), newcomer_submit=newcomer)
    fails = judge(m, rss=False)  # its RSS "after" is read with the filler's cloths still held
    if newcomer != "ok":
        fails.append(f"a newcomer's small cloth got {newcomer} while the filler held its share")
    return {**m, "fails": fails}
