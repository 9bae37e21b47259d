"""Companion of decode_bench.rs: time the Python SDK's decoders on the same payload files.

    python decode_bench.py DIR      (DIR: target/bench-payloads written by decode_bench.rs)

Prints, per payload, the median ns per call of drape.client.protocol.decode_state (states) or
parse_bundle + state(i) for every entry (bundles), and the same followed by copying positions
(and normals) into preallocated arrays, as the Rust side does. Needs numpy and drape.client.
"""
import statistics
import sys
import time
from pathlib import Path

import numpy as np

from drape.client import protocol as P


def median_ns(fn, iters: int, rounds: int = 31) -> float:
    out = []
    for _ in range(rounds):
        t0 = time.perf_counter_ns()
        for _ in range(iters):
            fn()
        out.append((time.perf_counter_ns() - t0) / iters)
    return statistics.median(out)


def main() -> None:
    pos = np.zeros((4096, 3), np.float32)
    nrm = np.zeros((4096, 3), np.float32)
    # the folder also holds predictive_bench's stream (not one state): only decode_bench's payloads
    paths = [p for p in sorted(Path(sys.argv[1]).glob("*.bin")) if p.name.startswith(("state_", "bundle_"))]
    for path in paths:
        data = path.read_bytes()
        if path.name.startswith("bundle"):
            def dec():
                b = P.parse_bundle(data)
                return [b.state(i) for i in range(len(b.entries))]

            def dec_copy():
                for st in dec():
                    np.copyto(pos[:len(st.positions)], st.positions)

            verts = 16 * 1024
        else:
            def dec():
                return P.decode_state(data)

            def dec_copy():
                st = P.decode_state(data)
                np.copyto(pos[:len(st.positions)], st.positions)
                if st.normals is not None:
                    np.copyto(nrm[:len(st.normals)], st.normals)

            verts = 4096
        iters = max(10, 400_000 // verts)
        print(path.stem, f"{median_ns(dec, iters):.0f}", f"{median_ns(dec_copy, iters):.0f}")


if __name__ == "__main__":
    main()
