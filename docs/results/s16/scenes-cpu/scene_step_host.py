import time, numpy as np, statistics
from drape.server.sim.fabric import cook_grid
from drape.server.sim.params import ClothParams, Material
from drape.server.sim.opencl.clworld import CLWorld
fab = cook_grid(8, 8, 0.2, 0.2, pinned=[0, 7], origin=(0.0, 1.0, 0.0))
w = CLWorld("workgroup", device="cpu")
p = ClothParams(iterations=2, material=Material(thickness=0.01))
for s in range(64):
    for j in range(2):
        w.add(fab, p, positions=fab.rest_positions + [0.1*j, 0, 10.0*s], scene=f"s{s}")
for _ in range(3): w.step(1/60)
w.sync()
sc = w.scene_collision
ts=[]
for _ in range(50):
    w.sync()
    t0=time.perf_counter(); sc.step(1/60); ts.append((time.perf_counter()-t0)*1e3)
w.sync()
print(__import__("drape.server.sim.opencl.scenes", fromlist=["x"]).__file__.split("/")[2], "scene step host ms median", round(statistics.median(ts),3), "min", round(min(ts),3))
