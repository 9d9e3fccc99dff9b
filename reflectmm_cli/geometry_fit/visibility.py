"""Which vertices each camera sees, by ray casting (Embree, ``reflectmm_cli.geometry``) at the current estimate."""

from __future__ import annotations

import numpy as np

from reflectmm_cli.geometry import RayScene, visibility


def vertex_visibility(vertices: np.ndarray, triangles: np.ndarray, normals: np.ndarray, centers: np.ndarray,
                      sample: np.ndarray | None = None, cos_cutoff: float | np.ndarray = 0.05) -> np.ndarray:
    """(V, M) bool: vertex ``sample[m]`` faces eye ``v`` (n·dir > the eye's cos cutoff) and the segment from the
    vertex to the eye hits no triangle.

    Eyes at the same place (a camera and the flash it carries) cast their rays once: the occlusion of a segment
    does not depend on the cutoff, which is applied after.

    Args:
        vertices: (N, 3) mesh vertices; triangles: (T, 3); normals: (N, 3) unit vertex normals.
        centers: (V, 3) eye positions (camera centres, point lights) in the mesh frame.
        sample: (M,) vertex ids to test (default all).
        cos_cutoff: one cutoff, or (V,) one per eye.
    """
    v = np.asarray(vertices, dtype=np.float64)
    n = np.asarray(normals, dtype=np.float64)
    eyes = np.asarray(centers, dtype=np.float64).reshape(-1, 3)
    cut = np.broadcast_to(np.asarray(cos_cutoff, dtype=np.float64), (len(eyes),))
    idx = np.arange(len(v)) if sample is None else np.asarray(sample, dtype=np.int64)
    p, pn = v[idx], n[idx]
    scene = RayScene(v, triangles, normals=n)
    out = np.zeros((len(eyes), len(idx)), dtype=bool)
    seen: dict[bytes, np.ndarray] = {}
    for k, c in enumerate(eyes):
        d = c[None, :] - p
        d /= np.linalg.norm(d, axis=-1, keepdims=True)
        facing = (pn * d).sum(-1) > cut[k]
        key = c.tobytes()
        if key not in seen:
            seen[key] = visibility(scene, p, pn, c)
        out[k] = seen[key] & facing
    return out
