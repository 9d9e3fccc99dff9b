"""Build the reflectance model from fitted maps files (library entry of ``build-pca``)."""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np

from reflectmm_cli.artifacts import read_artifact
from reflectmm_cli.errors import ReflectmmError
from reflectmm_cli.progress import progress
from reflectmm_cli.workspace import check_given_once

from .pca import add_vertex_model, fit_reflectance_pca

log = logging.getLogger("reflectmm")

__all__ = ["load_maps", "build_reflectance_model"]


def load_maps(paths: list[Path]):
    """Read reflectance-maps artifacts; all must share exponents and UV size.

    Returns (ids, albedos, weights, masks, flagged, exponents): lists of (3,S,S), (K,S,S), (S,S), (S,S) arrays and
    the shared (K,) exponents."""
    ids, albedos, weights, masks, flagged = [], [], [], [], []
    exps = None
    check_given_once(paths, "each identity's maps count once in the model")
    for p in progress(paths, desc="maps", unit="map"):
        art = read_artifact(p, "reflectance-maps")
        e = np.asarray(art["exponents"], np.float64).reshape(-1)
        if exps is None:
            exps, first = e, p
        elif e.shape != exps.shape or not np.allclose(e, exps):
            if e.shape == exps.shape and np.allclose(np.sort(e), np.sort(exps)):
                raise ReflectmmError(f"lobe exponents {e.tolist()} are those of {first} in another order "
                                     f"({exps.tolist()}); fit every identity with one order (--exponents)", p)
            raise ReflectmmError(f"lobe exponents {e.tolist()} differ from {exps.tolist()} of {first}; a model "
                                 "needs one set of exponents", p)
        ids.append(str(art.meta.get("identity") or art.meta.get("params", {}).get("id") or Path(p).stem))
        albedos.append(art["albedo"])
        weights.append(art["weights"])
        masks.append(art["mask"] if "mask" in art.arrays else np.ones(art["albedo"].shape[1:], bool))
        flagged.append(art["flagged"] if "flagged" in art.arrays else np.zeros(art["albedo"].shape[1:], bool))
        _check_fit(p, albedos[-1], weights[-1], masks[-1], flagged[-1])
    return ids, albedos, weights, masks, flagged, exps


#: Albedo or lobe weights below −this in a map's face mask are refused (fit-reflectance's solvers keep them ≥ 0).
NEGATIVE_MAP_TOL = 1e-3


def _check_fit(path, albedo, weights, mask, flagged) -> None:
    """Refuse maps that are not a fit: every texel of the face mask flagged (nothing was fitted, the values are
    fill), or albedo / lobe weights below zero (another convention, or a damaged file)."""
    m = np.asarray(mask, bool)
    if m.any() and np.asarray(flagged, bool)[m].all():
        raise ReflectmmError(f"every one of its {int(m.sum())} face texels is flagged: nothing was fitted (check "
                             "fit-reflectance's log); leave these maps out", path)
    for what, a in (("albedo", albedo), ("lobe weights", weights)):
        v = np.asarray(a)[:, m]
        with np.errstate(invalid="ignore"):
            neg = int((v < -NEGATIVE_MAP_TOL).sum())
        if neg:
            raise ReflectmmError(f"{what} below 0 at {neg} value(s) of the face mask (min {float(np.nanmin(v)):.3g}): "
                                 "reflectance maps are ≥ 0", path)


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
