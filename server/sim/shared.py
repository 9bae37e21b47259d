"""Constants and geometry helpers every back end shares (the reference solver, the OpenCL
world and the service), so that no back end imports another: the Jacobi over-relaxation factor
the kernels are built with, the epsilons of the link equation and area-weighted vertex normals.
"""

from __future__ import annotations

import numpy as np

from .fabric import Fabric

JACOBI_OMEGA = 1.5  # over-relaxation of the Jacobi vertex solver (kernels: -DJACOBI_OMEGA)
EPS_LEN2 = 1e-20  # below this squared length a direction is undefined: no correction
EPS_DENOM = 1e-30


def vertex_normals(x: np.ndarray, fabric: Fabric) -> tuple[np.ndarray, np.ndarray]:
    """Unit vertex normals (area-weighted face normals; (0, 0, 0) where there are none) and
    per-vertex areas (a third of each incident triangle)."""
    t = fabric.triangles
    normals = np.zeros_like(x)
    area = np.zeros(len(x), x.dtype)
    if len(t):
        fn = np.cross(x[t[:, 1]] - x[t[:, 0]], x[t[:, 2]] - x[t[:, 0]])
        fa = 0.5 * np.linalg.norm(fn, axis=1)
        for k in range(3):
            np.add.at(normals, t[:, k], fn)
            np.add.at(area, t[:, k], fa / 3.0)
    ln = np.linalg.norm(normals, axis=1)
    ok = ln > 1e-30
    normals[ok] /= ln[ok, None]
    normals[~ok] = 0.0
    return normals, area
