"""Host time of the scenes' step alone (SceneCollision.step, no device wait): 64 scenes of two
8 x 8 cloths, 50 steps, median and minimum. Run with the code before on PYTHONPATH to compare
(docs/results/s16/scenes-cpu/run.sh builds that tree the same way)."""

import statistics
import time

from drape.server.sim.fabric import cook_grid
from drape.server.sim.opencl import scenes
from drape.server.sim.opencl.clworld import CLWorld
from drape.server.sim.params import ClothParams, Material

fab = cook_grid(8, 8, 0.2, 0.2, pinned=[0, 7], origin=(0.0, 1.0, 0.0))
w = CLWorld("workgroup", device="cpu")
p = ClothParams(iterations=2, material=Material(thickness=0.01))
for s in range(64):
    for j in range(2):
        w.add(fab, p, positions=fab.rest_positions + [0.1 * j, 0, 10.0 * s], scene=f"s{s}")
for _ in range(3):
    w.step(1 / 60)
w.sync()
sc = w.scene_collision
ts = []
for _ in range(50):
    w.sync()
    t0 = time.perf_counter()
    sc.step(1 / 60)
    ts.append((time.perf_counter() - t0) * 1e3)
w.sync()
print(scenes.__file__, f"scene step host ms: median {statistics.median(ts):.3f}, min {min(ts):.3f}")
