"""Geometry a client needs without the server package: grid rest pose and triangles, Wavefront
OBJ parsing (PROTOCOL.md section 4). drape.server.sim.fabric uses these same functions."""
from __future__ import annotations

from typing import Iterable

import numpy as np

def grid_geometry(
    cols: int,
    rows: int,
    width: float = 1.0,
    height: float = 1.0,
    orientation: str = "horizontal",
    origin: Iterable[float] = (0.0, 0.0, 0.0),
) -> tuple[np.ndarray, np.ndarray]:
    """Rest positions (rows*cols, 3) float32 and triangles (m, 3) uint32 of a grid cloth, exactly
    as the server builds them (drape.server.sim.fabric.grid_mesh).

    Vertex (r, c) = r * cols + c. x = origin.x + c * width / (cols - 1) (0 when cols == 1).
    horizontal: y = origin.y, z = origin.z + r * height / (rows - 1);
    vertical: y = origin.y - r * height / (rows - 1), z = origin.z.
    Triangles: for every cell (r, c) in row-major order, a = r*cols + c, b = a + 1, d = a + cols,
    e = d + 1: first all (a, d, b), then all (b, d, e)."""
    if cols < 1 or rows < 1:
        raise ValueError("a grid needs at least one column and one row")
    ox, oy, oz = (float(v) for v in origin)
    u = np.linspace(0.0, width, cols) if cols > 1 else np.zeros(1)
    w = np.linspace(0.0, height, rows) if rows > 1 else np.zeros(1)
    cc, rr = np.meshgrid(u, w)
    verts = np.zeros((rows * cols, 3))
    verts[:, 0] = ox + cc.ravel()
    if orientation == "horizontal":
        verts[:, 1] = oy
        verts[:, 2] = oz + rr.ravel()
    elif orientation == "vertical":
        verts[:, 1] = oy - rr.ravel()
        verts[:, 2] = oz
    else:
        raise ValueError("orientation must be 'horizontal' or 'vertical'")
    r, c = np.meshgrid(np.arange(rows - 1), np.arange(cols - 1), indexing="ij")
    a = (r * cols + c).ravel()
    b, d, e = a + 1, a + cols, a + cols + 1
    tris = np.concatenate([np.stack([a, d, b], 1), np.stack([b, d, e], 1)]).astype(np.uint32)
    return verts.astype(np.float32), tris


def parse_obj(text: str) -> tuple[np.ndarray, np.ndarray]:
    """Vertices (n, 3) float32 and triangles (m, 3) uint32 of Wavefront OBJ text: faces
    fan-triangulated, v/vt/vn and negative indices accepted, everything else ignored (the same
    rules as drape.server.sim.fabric.parse_obj)."""
    verts: list[tuple[float, float, float]] = []
    tris: list[tuple[int, int, int]] = []
    for lineno, line in enumerate(text.splitlines(), 1):
        parts = line.split("#", 1)[0].split()
        if not parts:
            continue
        if parts[0] == "v":
            if len(parts) < 4:
                raise ValueError(f"OBJ line {lineno}: vertex needs x y z")
            verts.append((float(parts[1]), float(parts[2]), float(parts[3])))
        elif parts[0] == "f":
            idx = []
            for p in parts[1:]:
                i = int(p.split("/")[0])
                idx.append(i - 1 if i > 0 else len(verts) + i)
            if len(idx) < 3:
                raise ValueError(f"OBJ line {lineno}: face needs three vertices")
            if min(idx) < 0:
                raise ValueError(f"OBJ line {lineno}: vertex index out of range")
            for k in range(1, len(idx) - 1):
                tris.append((idx[0], idx[k], idx[k + 1]))
    return np.asarray(verts, np.float32).reshape(-1, 3), np.asarray(tris, np.uint32).reshape(-1, 3)
