"""Ground truth from outside the synthetic world: a registered scan + cameras, per-vertex reflectance.

Formats: docs/artifacts.md, "External ground truth".

Two documented formats, so that users with their own scans can measure the pipeline:

* **Geometry** (``fit-geometry --from-truth MESH --rig CAMERAS.toml``): a mesh file (``.ply``, ``.obj``,
  ``.off``; read with trimesh, ``process=False`` so the vertex order is kept) whose vertices are those of the
  face model (same count and order: a scan registered to the model's topology), in mm in the frame of the rig
  table that holds the cameras (``reflectmm_cli/rig.py`` format: positions, look-at, up, focal, image size) and
  the flashes.  :func:`geometry_truth_arrays` turns them into the arrays a ``synth-truth`` artifact has for
  geometry (``vertices``, ``camera_names``, ``K``, ``R``, ``t``, ``image_size``, ``flash_*``; shape and
  expression coefficients are unknown and stored empty).
* **Reflectance** (``evaluate truth --truth REFL.npz --face-model FM``): a plain NPZ with ``albedo (V, 3)``
  linear diffuse albedo per vertex and ``spec_albedo (V,)`` the total specular albedo Σw per vertex,
  optionally ``weights (K, V)`` with ``exponents (K,)``; V = the face model's vertex count.
  :func:`vertex_reflectance_to_uv` rasterises them into the UV maps ``evaluate truth`` compares with
  (barycentric interpolation in the face model's UV layout, exactly as the fitted maps are laid out).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from reflectmm_cli.errors import ReflectmmError

__all__ = ["MESH_SUFFIXES", "read_truth_mesh", "geometry_truth_arrays", "read_vertex_reflectance",
           "vertex_reflectance_to_uv"]

MESH_SUFFIXES = (".ply", ".obj", ".off", ".stl", ".glb")


def read_truth_mesh(path: str | Path, n_vertices: int | None = None) -> np.ndarray:
    """(V, 3) float64 vertices of a mesh file (vertex order kept); ``n_vertices`` checks the count."""
    import trimesh

    p = Path(path)
    try:
        mesh = trimesh.load(p, process=False, force="mesh")
    except Exception as exc:  # trimesh raises many types for bad files
        raise ReflectmmError(f"cannot read mesh ({exc})", p) from None
    v = np.asarray(getattr(mesh, "vertices", np.zeros((0, 3))), np.float64)
    if v.ndim != 2 or v.shape[1] != 3 or not len(v):
        raise ReflectmmError("mesh has no vertices", p)
    if n_vertices is not None and len(v) != n_vertices:
        raise ReflectmmError(f"mesh has {len(v)} vertices but the face model has {n_vertices}: the scan must be "
                             "registered to the face model's topology (same vertices, same order)", p)
    if not np.all(np.isfinite(v)):
        raise ReflectmmError("mesh has non-finite vertices", p)
    return v


def geometry_truth_arrays(mesh_path: str | Path, rig, n_vertices: int | None = None) -> tuple[dict, dict]:
    """Synth-truth-like geometry arrays from a registered mesh and a :class:`reflectmm_cli.rig.Rig`.

    Returns (arrays, meta) with arrays ``vertices (V,3)``, ``shape_coeffs (0,)``, ``exp_coeffs (0,)``,
    ``camera_names (C,)``, ``K``, ``R (C,3,3)``, ``t (C,3)``, ``image_size (2,)``, ``flash_ids (F,)``,
    ``flash_pos (F,3)``, ``flash_intensity (F,)``; meta ``views``, ``flashes``.  Every camera must have the same
    image size (one capture frame).
    """
    verts = read_truth_mesh(mesh_path, n_vertices)
    sizes = {(c.width, c.height) for c in rig.cameras}
    if len(sizes) != 1:
        raise ReflectmmError(f"the cameras of the truth rig have several image sizes {sorted(sizes)}", rig.source)
    W, H = sizes.pop()
    arrays = {"vertices": verts, "shape_coeffs": np.zeros(0), "exp_coeffs": np.zeros(0),
              "camera_names": np.array(rig.camera_names, dtype=str), "K": np.stack([c.K for c in rig.cameras]),
              "R": np.stack([c.R for c in rig.cameras]), "t": np.stack([c.t for c in rig.cameras]),
              "image_size": np.array([W, H], np.int32),
              "flash_ids": np.array(rig.flash_ids, dtype=str),
              "flash_pos": np.array([f.position for f in rig.flashes], np.float64).reshape(-1, 3),
              "flash_intensity": np.array([f.intensity for f in rig.flashes], np.float64)}
    return arrays, {"views": rig.camera_names, "flashes": rig.flash_ids}


def read_vertex_reflectance(path: str | Path, n_vertices: int) -> dict[str, np.ndarray]:
    """Validate a per-vertex reflectance NPZ (see the module docstring)."""
    p = Path(path)
    try:
        with np.load(p, allow_pickle=False) as z:
            d = {k: np.asarray(z[k]) for k in z.files if k != "__meta__"}
    except (OSError, ValueError) as exc:
        raise ReflectmmError(f"cannot read per-vertex reflectance NPZ ({exc})", p) from None
    for k, shape in (("albedo", (n_vertices, 3)), ("spec_albedo", (n_vertices,))):
        if k not in d:
            raise ReflectmmError(f"per-vertex reflectance has no '{k}' array", p)
        if d[k].shape != shape:
            raise ReflectmmError(f"'{k}' has shape {d[k].shape}, expected {shape} (V = the face model's vertices)",
                                 p)
    if ("weights" in d) != ("exponents" in d):
        raise ReflectmmError("give both 'weights' (K, V) and 'exponents' (K,), or neither", p)
    if "weights" in d and d["weights"].shape != (d["exponents"].reshape(-1).size, n_vertices):
        raise ReflectmmError(f"'weights' has shape {d['weights'].shape}, expected (K, {n_vertices})", p)
    return d


def vertex_reflectance_to_uv(vertex: dict[str, np.ndarray], uv: np.ndarray, triangles: np.ndarray, size: int
                             ) -> dict[str, np.ndarray]:
    """UV maps (``albedo (3,S,S)``, ``spec_albedo (S,S)``, optional ``weights (K,S,S)``, ``exponents``,
    ``mask (S,S)``) of per-vertex values, by barycentric interpolation over the face model's UV layout."""
    from reflectmm_cli.geometry import rasterize_uv

    ras = rasterize_uv(uv, triangles, size)
    tri = np.asarray(triangles, np.int64)
    ids = tri[np.where(ras.mask, ras.tri_id, 0)]                      # (S, S, 3)
    b = np.where(ras.mask[..., None], ras.bary.astype(np.float64), 0.0)

    def interp(vals: np.ndarray) -> np.ndarray:                       # (V, ...) → (..., S, S)
        out = np.einsum("ijk,ijk...->ij...", b, np.asarray(vals, np.float64)[ids])
        return np.moveaxis(out, (0, 1), (-2, -1))

    res = {"albedo": interp(vertex["albedo"]), "spec_albedo": interp(vertex["spec_albedo"]), "mask": ras.mask}
    if "weights" in vertex:
        res["weights"] = interp(np.asarray(vertex["weights"]).T)
        res["exponents"] = np.asarray(vertex["exponents"], np.float64).reshape(-1)
    return res
