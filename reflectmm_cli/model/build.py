"""Build the reflectance model from fitted maps files (library entry of ``build-pca``)."""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np

from reflectmm_cli.artifacts import read_artifact
from reflectmm_cli.errors import ReflectmmError
from reflectmm_cli.progress import progress

from .pca import add_vertex_model, fit_reflectance_pca

log = logging.getLogger("reflectmm")

__all__ = ["load_maps", "build_reflectance_model"]


def load_maps(paths: list[Path]):
    """Read reflectance-maps artifacts; all must share exponents and UV size.

    Returns (ids, albedos, weights, masks, flagged, exponents): lists of (3,S,S), (K,S,S), (S,S), (S,S) arrays and
    the shared (K,) exponents."""
    ids, albedos, weights, masks, flagged = [], [], [], [], []
    exps = None
    for p in progress(paths, desc="maps", unit="map"):
        art = read_artifact(p, "reflectance-maps")
        e = np.asarray(art["exponents"], np.float64).reshape(-1)
        if exps is None:
            exps, first = e, p
        elif e.shape != exps.shape or not np.allclose(e, exps):
            raise ReflectmmError(f"lobe exponents {e.tolist()} differ from {exps.tolist()} of {first}; a model "
                                 "needs one set of exponents", p)
        ids.append(str(art.meta.get("identity") or art.meta.get("params", {}).get("id") or Path(p).stem))
        albedos.append(art["albedo"])
        weights.append(art["weights"])
        masks.append(art["mask"] if "mask" in art.arrays else np.ones(art["albedo"].shape[1:], bool))
        flagged.append(art["flagged"] if "flagged" in art.arrays else np.zeros(art["albedo"].shape[1:], bool))
    return ids, albedos, weights, masks, flagged, exps


def build_reflectance_model(map_paths: list[Path], components: int = 80, face_model: Path | None = None):
    """(ReflectanceModel, FaceModel or None) from reflectance-maps files; with a face model the per-vertex model
    is added (:func:`~reflectmm_cli.model.pca.add_vertex_model`)."""
    ids, A, W, M, F, exps = load_maps(map_paths)
    if len(set(ids)) != len(ids):
        ids = [Path(p).stem for p in map_paths]
    reflectance_model = fit_reflectance_pca(A, W, exps, masks=M, flagged=F, components=components, ids=ids,
                                            log=log.warning)
    fm = None
    if face_model is not None:
        from reflectmm_cli.geometry.face_model import load_face_model

        fm = load_face_model(face_model)
        add_vertex_model(reflectance_model, fm.uv)
    return reflectance_model, fm
