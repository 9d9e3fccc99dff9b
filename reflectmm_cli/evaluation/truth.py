"""Errors of fitted reflectance maps and geometry against the synthetic world's ground truth.

Reflectance (UV space, texels of the fitted map's mask):

* regions: ``observable`` = mask ∧ ¬flagged, ``flagged`` = mask ∧ flagged (filled from mirror/neighbours), ``all``;
* diffuse albedo: RMSE over texels and the 3 linear RGB channels, and the relative error RMSE / RMS(truth);
* specular albedo: Σ_i w_i against the truth's ``spec_albedo`` (the GGX directional albedo at normal view, the
  same quantity: the shading under uniform unit radiance seen head-on), RMSE, relative error (RMSE / RMS of the
  truth) and the median of the per-texel ratio Σw / spec_albedo (robust to the few texels with least data);
* lobe weights against the truth's 3-lobe reference ``weights`` when the exponents agree (exact in ``model``
  mode, only the closest 3-lobe fit in ``ggx`` mode);
* scale ambiguity: the flash intensity and the reflectance share one global scale (docs/pipeline.md). Every
  error is reported raw and after one global least-squares scale ``s = Σ C·C* / Σ C²`` fitted on the diffuse
  albedo of the observable texels and applied to both C and W (one scale for the whole identity, as the
  ambiguity is one scale for both).

Geometry: per-vertex distance (mm) of the fitted mesh to the true mesh (same topology, model space), raw and
after the best rigid alignment (Kabsch; a global rigid motion is exchangeable with the per-view poses), camera
centre distance (mm) matched by view name, and the landmark RMSE (px) the fit stored.
"""
from __future__ import annotations

from typing import Any, Mapping

import numpy as np

from reflectmm_cli.errors import ReflectmmError
from reflectmm_cli.geometry.align import rigid_align

__all__ = ["reflectance_errors", "geometry_errors", "global_scale", "kabsch"]


def global_scale(albedo: np.ndarray, truth: np.ndarray, region: np.ndarray) -> float:
    """Least-squares s minimising Σ (s·C − C*)² over ``region`` texels and all channels."""
    c = np.asarray(albedo, np.float64)[:, region]
    t = np.asarray(truth, np.float64)[:, region]
    den = float((c * c).sum())
    return float((c * t).sum() / den) if den > 0 else 1.0


def _err(pred: np.ndarray, truth: np.ndarray) -> tuple[float, float]:
    if pred.size == 0:
        return float("nan"), float("nan")
    d = pred - truth
    rmse = float(np.sqrt(np.mean(d * d)))
    rms = float(np.sqrt(np.mean(truth * truth)))
    return rmse, (rmse / rms if rms > 0 else float("nan"))


def reflectance_errors(maps: Mapping[str, np.ndarray], truth: Mapping[str, np.ndarray]) -> dict[str, Any]:
    """Error table (nested dict of floats) of fitted maps (reflectance-maps arrays) against a truth mapping with
    ``albedo (3,S,S)``, ``spec_albedo (S,S)`` and optionally ``weights (K,S,S)`` + ``exponents (K,)``."""
    C = np.asarray(maps["albedo"], np.float64)
    W = np.asarray(maps["weights"], np.float64)
    Ct = np.asarray(truth["albedo"], np.float64)
    if C.shape != Ct.shape:
        raise ReflectmmError(f"evaluate truth: fitted albedo has shape {C.shape} but the truth has {Ct.shape} "
                             "(the UV sizes must agree)")
    S = C.shape[-1]
    mask = np.asarray(maps.get("mask", np.ones((S, S), bool)), bool)
    flagged = np.asarray(maps.get("flagged", np.zeros((S, S), bool)), bool) & mask
    regions = {"observable": mask & ~flagged, "flagged": flagged, "all": mask}
    st = np.asarray(truth["spec_albedo"], np.float64) if "spec_albedo" in truth else None
    Wt = np.asarray(truth["weights"], np.float64) if "weights" in truth else None
    same_lobes = False
    if Wt is not None and "exponents" in truth:
        et = np.asarray(truth["exponents"], np.float64).reshape(-1)
        ef = np.asarray(maps.get("exponents", []), np.float64).reshape(-1)
        same_lobes = et.shape == ef.shape and np.allclose(et, ef) and Wt.shape == W.shape
    scale = global_scale(C, Ct, regions["observable"]) if regions["observable"].any() else 1.0
    out: dict[str, Any] = {"scale": scale, "texels": {k: int(v.sum()) for k, v in regions.items()},
                           "scale_fitted_on": "diffuse albedo, observable texels", "raw": {}, "scaled": {}}
    for mode, s in (("raw", 1.0), ("scaled", scale)):
        for name, reg in regions.items():
            e: dict[str, float] = {}
            e["albedo_rmse"], e["albedo_rel"] = _err(s * C[:, reg], Ct[:, reg])
            # robust companion: the typical texel's relative colour error (RMS over channels, per texel)
            if reg.any():
                d = np.sqrt(np.mean((s * C[:, reg] - Ct[:, reg]) ** 2, axis=0))
                r = np.sqrt(np.mean(Ct[:, reg] ** 2, axis=0))
                ok = r > 0
                e["albedo_rel_median"] = float(np.median(d[ok] / r[ok])) if ok.any() else float("nan")
            else:
                e["albedo_rel_median"] = float("nan")
            if st is not None:
                e["spec_rmse"], e["spec_rel"] = _err(s * W.sum(0)[reg], st[reg])
                # robust companion of spec_rel (an RMS, dominated by the few texels with least data)
                pos = reg & (st > 0)
                e["spec_ratio_median"] = (float(np.median(s * W.sum(0)[pos] / st[pos])) if pos.any()
                                          else float("nan"))
            if same_lobes:
                e["weights_rmse"], e["weights_rel"] = _err(s * W[:, reg], Wt[:, reg])
            out[mode][name] = e
    return out


def kabsch(a: np.ndarray, b: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Rotation R and translation t minimising Σ ‖R a_i + t − b_i‖² (proper rotation;
    :func:`reflectmm_cli.geometry.align.rigid_align` without scale)."""
    R, t, _ = rigid_align(a, b)
    return R, t


def geometry_errors(geometry: Mapping[str, np.ndarray], truth: Mapping[str, np.ndarray]) -> dict[str, Any]:
    """Vertex (mm, raw and rigidly aligned), camera centre (mm) and landmark (px) errors of a geometry artifact."""
    out: dict[str, Any] = {}
    if "vertices" in geometry and "vertices" in truth:
        v = np.asarray(geometry["vertices"], np.float64)
        vt = np.asarray(truth["vertices"], np.float64)
        if v.shape != vt.shape:
            raise ReflectmmError(f"evaluate truth: fitted mesh has {v.shape} vertices, truth {vt.shape} "
                                 "(same topology needed)")
        d = np.linalg.norm(v - vt, axis=1)
        R, t = kabsch(v, vt)
        da = np.linalg.norm(v @ R.T + t - vt, axis=1)
        out.update(vertex_mean_mm=float(d.mean()), vertex_rms_mm=float(np.sqrt((d ** 2).mean())),
                   vertex_max_mm=float(d.max()), vertex_aligned_mean_mm=float(da.mean()),
                   vertex_aligned_rms_mm=float(np.sqrt((da ** 2).mean())))
    ds = list(camera_errors_by_view(geometry, truth).values())
    if ds:
        out.update(camera_mean_mm=float(np.mean(ds)), camera_max_mm=float(np.max(ds)), cameras_matched=len(ds))
    if "vertex_mean_mm" not in out and "err_vertex_rmse_mm" in geometry:
        # no truth given: the errors fit-geometry stored when it was run with --truth
        out["vertex_rms_mm"] = float(np.asarray(geometry["err_vertex_rmse_mm"]).reshape(-1)[0])
        out["source"] = "geometry artifact (err_* arrays)"
    if "camera_mean_mm" not in out and "err_cam_center_mm" in geometry:
        c = np.asarray(geometry["err_cam_center_mm"], np.float64).reshape(-1)
        out.update(camera_mean_mm=float(c.mean()), camera_max_mm=float(c.max()), cameras_matched=int(c.size))
        out["source"] = "geometry artifact (err_* arrays)"
    if "landmark_rmse_px" in geometry:
        lm = np.asarray(geometry["landmark_rmse_px"], np.float64)
        lm = lm[np.isfinite(lm)]  # NaN: a view without landmarks
        if lm.size:
            out.update(landmark_rmse_px=float(np.sqrt(np.mean(lm ** 2))), landmark_max_px=float(lm.max()))
    return out


def camera_errors_by_view(geometry: Mapping[str, np.ndarray], truth: Mapping[str, np.ndarray]) -> dict[str, float]:
    """Camera centre error (mm) of each view of a geometry artifact that the truth has, by view name."""
    cams_t = _truth_cameras(truth)
    if cams_t is None or "cam_centers" not in geometry:
        return {}
    names = [str(x) for x in np.asarray(geometry.get("view_names", []))]
    cc = np.asarray(geometry["cam_centers"], np.float64)
    return {n: float(np.linalg.norm(cc[i] - cams_t[n])) for i, n in enumerate(names) if n in cams_t}


def _truth_cameras(truth: Mapping[str, np.ndarray]) -> dict[str, np.ndarray] | None:
    """name → camera centre from a truth mapping (``view_names``/``camera_names`` + ``cam_centers``, or R, t)."""
    names = None
    for k in ("view_names", "camera_names", "cameras"):
        if k in truth and np.asarray(truth[k]).dtype.kind in "US":
            names = [str(x) for x in np.asarray(truth[k]).reshape(-1)]
            break
    if names is None:
        return None
    if "cam_centers" in truth:
        c = np.asarray(truth["cam_centers"], np.float64)
    elif "R" in truth and "t" in truth:
        R, t = np.asarray(truth["R"], np.float64), np.asarray(truth["t"], np.float64)
        c = -np.einsum("vji,vj->vi", R, t)
    else:
        return None
    if c.shape != (len(names), 3):
        return None
    return dict(zip(names, c))
