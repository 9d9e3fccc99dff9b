"""Which vertices each camera sees, by ray casting (Embree, ``reflectmm_cli.geometry``) at the current estimate."""

from __future__ import annotations

import numpy as np

from reflectmm_cli.geometry import RayScene, visibility


def vertex_visibility(vertices: np.ndarray, triangles: np.ndarray, normals: np.ndarray, centers: np.ndarray,
                      sample: np.ndarray | None = None, cos_cutoff: float = 0.05) -> np.ndarray:
    """(V, M) bool: vertex ``sample[m]`` faces camera ``v`` (n·dir > cos_cutoff) and the segment from the vertex
    to the camera centre hits no triangle.

    Args:
        vertices: (N, 3) mesh vertices; triangles: (T, 3); normals: (N, 3) unit vertex normals.
        centers: (V, 3) camera centres in the mesh frame.
        sample: (M,) vertex ids to test (default all).
    """
    v = np.asarray(vertices, dtype=np.float64)
    n = np.asarray(normals, dtype=np.float64)
    idx = np.arange(len(v)) if sample is None else np.asarray(sample, dtype=np.int64)
    p, pn = v[idx], n[idx]
    scene = RayScene(v, triangles, normals=n)
    out = np.zeros((len(centers), len(idx)), dtype=bool)
    for k, c in enumerate(np.asarray(centers, dtype=np.float64)):
        d = c[None, :] - p
        d /= np.linalg.norm(d, axis=-1, keepdims=True)
        facing = (pn * d).sum(-1) > cos_cutoff
        out[k] = visibility(scene, p, pn, c) & facing
    return out
