"""A sampling profiler of the server's own threads (``DRAPE_PROFILE``): where the tick and publish
threads spend their time under a real load, without a profiler installed on the host.

Every ``1 / hz`` seconds the sampler reads the Python stacks of the threads whose names start
with one of ``prefixes`` (``sys._current_frames``) and counts each distinct stack. A stack costs
a walk of its frames under the GIL (about 10-30 us): at the default 200 Hz the sampled process
loses well under 1 % of a core. At the end :meth:`ThreadSampler.write` leaves two files:

- ``PATH.folded``: one line per distinct stack, ``thread;outer;...;inner count`` (the folded
  format flame-graph tools read), and
- ``PATH.txt``: per thread, the functions with the largest share of samples, inclusive (on the
  stack) and self (innermost), as percentages of that thread's samples.

A thread waiting (on the device's event, a queue, the tick's deadline) shows the waiting call as
its innermost frame: the report says where the wall time goes, not only the CPU time.
"""

from __future__ import annotations

import logging
import sys
import threading
from collections import Counter
from pathlib import Path
from types import FrameType

log = logging.getLogger(__name__)

DEFAULT_PREFIXES = ("drape-tick", "drape-publish", "drape-cook", "drape-requests")


def _frame_name(f: FrameType) -> str:
    code = f.f_code
    return f"{Path(code.co_filename).stem}.{code.co_qualname}"


def _stack(f: FrameType | None, limit: int) -> tuple[str, ...]:
    names: list[str] = []
    while f is not None and len(names) < limit:
        names.append(_frame_name(f))
        f = f.f_back
    names.reverse()  # outermost first
    return tuple(names)


class ThreadSampler:
    """Counts the stacks of the named threads at ``hz`` until :meth:`stop`."""

    def __init__(self, prefixes: tuple[str, ...] = DEFAULT_PREFIXES, hz: float = 200.0, depth: int = 48) -> None:
        if hz <= 0:
            raise ValueError(f"sampling rate must be > 0, not {hz}")
        self.prefixes, self.period, self.depth = prefixes, 1.0 / hz, depth
        self.stacks: Counter[tuple[str, tuple[str, ...]]] = Counter()  # (thread kind, stack) -> samples
        self.samples: Counter[str] = Counter()  # thread kind -> samples
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="drape-sampler", daemon=True)

    def start(self) -> ThreadSampler:
        self._thread.start()
        return self

    def stop(self) -> None:
        self._stop.set()
        if self._thread.is_alive() and self._thread is not threading.current_thread():
            self._thread.join(2.0)

    def _kind(self, name: str) -> str | None:
        for p in self.prefixes:
            if name.startswith(p):
                return p
        return None

    def sample(self) -> None:
        """Take one sample of every matching thread (public for tests: deterministic, no timer)."""
        frames = sys._current_frames()
        for t in threading.enumerate():
            kind = self._kind(t.name)
            if kind is None or t.ident not in frames:
                continue
            self.stacks[(kind, _stack(frames[t.ident], self.depth))] += 1
            self.samples[kind] += 1

    def _run(self) -> None:
        while not self._stop.wait(self.period):
            self.sample()

    def summary(self, top: int = 30) -> str:
        """Per thread kind: the functions with the most samples, inclusive and self, in %."""
        out: list[str] = []
        for kind, total in sorted(self.samples.items()):
            incl: Counter[str] = Counter()
            self_: Counter[str] = Counter()
            for (k, stack), n in self.stacks.items():
                if k != kind or not stack:
                    continue
                for name in set(stack):
                    incl[name] += n
                self_[stack[-1]] += n
            out.append(f"== {kind}: {total} samples")
            out.append(f"{'inclusive %':>12} {'self %':>8}  function")
            for name, n in incl.most_common(top):
                out.append(f"{100.0 * n / total:12.1f} {100.0 * self_[name] / total:8.1f}  {name}")
            out.append("-- self only")
            for name, n in self_.most_common(top // 2):
                out.append(f"{'':12} {100.0 * n / total:8.1f}  {name}")
            out.append("")
        return "\n".join(out)

    def folded(self) -> str:
        return "".join(f"{';'.join((kind, *stack))} {n}\n" for (kind, stack), n in sorted(self.stacks.items()))

    def write(self, path: str | Path) -> tuple[Path, Path]:
        """Write ``PATH.folded`` and ``PATH.txt``; return their paths."""
        base = Path(path)
        base.parent.mkdir(parents=True, exist_ok=True)
        folded, text = base.with_name(base.name + ".folded"), base.with_name(base.name + ".txt")
        folded.write_text(self.folded())
        text.write_text(self.summary())
        log.info("profile of %s written to %s and %s", ", ".join(sorted(self.samples)) or "no thread", folded, text)
        return folded, text
