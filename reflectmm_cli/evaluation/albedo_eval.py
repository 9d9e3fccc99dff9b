"""Table 3 on the synthetic world: how well each reflectance model represents held-out identities' albedo.

**What is fitted to what.** For a held-out identity, each model's coefficients β (units of σ) are fitted to the
identity's ``uv-observations`` (unwrap-uv: per texel and (view, flash) pair, the OLAT radiance, with the texel's
position and normal from the identity's geometry). For fixed lobe exponents the shading is linear in the
reflectance and the model is linear in β, so every observed (pair, texel, channel) value is

    I = E·[ (μ_C + Σ_k β_k σ_k b_k)_ch · g_d + Σ_i (μ_W + Σ_k β_k σ_k s_k)_i · g_i ]

with ``g_d = max(n·l,0)/π`` and ``g_i = f_i max(n·h,0)^p_i`` (exactly what ``shade_directional`` computes for
unit albedo / unit lobe weight; the normal equations are built from it, no second BRDF). β minimises the
regularised linear least squares

    (1/N) Σ_rows (I_model − I_obs)²  +  λ · ȳ² · Σ_k β_k²        (ȳ² = mean squared observed radiance)

— the data term of every observed row (``observed`` mask of the pairs used) and the Gaussian prior Σ(β/σ)² in the
model's σ units, ``λ = prior`` scale-free. Solved in closed form (normal equations, M×M). Optionally an
**oracle** β: the orthogonal projection of the TRUE diffuse albedo on the model's bases (the best the model can do
for the diffuse part; the specular part then follows from the same β).

**Reported** (:func:`albedo_errors`) on the region = model domain ∧ the truth's mask ∧ texels observed in at least
one used pair: diffuse albedo PSNR (linear, peak 1, MSE over texels and RGB), specular albedo PSNR (Σ_i w_i against
the truth's ``spec_albedo`` — the paper's Table 3 uses Σw as the specular albedo), and relative RMS errors
(RMSE / RMS(truth)); each raw and after ONE global least-squares scale fitted on the diffuse albedo and applied to
both (the flash-intensity / reflectance scale ambiguity of real captures; exactly 1 in synthetic data with the
true irradiance, so "scaled" ≥ "raw" measures the overall brightness error).
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, Mapping, Sequence

import numpy as np

from reflectmm_cli.errors import ReflectmmError

from .truth import global_scale

__all__ = ["resample_truth", "NormalEquations", "observation_normal_equations", "fit_coefficients",
           "oracle_coefficients", "albedo_errors", "AlbedoResult", "evaluate_albedo", "albedo_table_rows",
           "DEFAULT_PRIOR"]

#: default λ of the coefficient prior (relative to the mean squared radiance).
DEFAULT_PRIOR = 1e-4


def resample_truth(truth: Mapping[str, np.ndarray], size: int) -> dict[str, np.ndarray]:
    """The truth's ``albedo`` (3,S,S), ``spec_albedo`` (S,S) and ``uv_mask`` at UV size ``size``: box average of
    f×f texel blocks when S = f·size (a texel's mask = all of its block), else bilinear at the new texel centres
    (docs/pipeline.md texel convention; mask = nearest). Same size: returned as is."""
    from reflectmm_cli.model.pca import sample_uv_bilinear

    a = np.asarray(truth["albedo"], np.float64)
    S = a.shape[-1]
    sp = np.asarray(truth["spec_albedo"], np.float64)
    m = np.asarray(truth.get("uv_mask", np.ones((S, S), bool)), bool)
    if S == size:
        return {"albedo": a, "spec_albedo": sp, "uv_mask": m}
    if S % size == 0:
        f = S // size
        box = lambda x: x.reshape(x.shape[:-2] + (size, f, size, f)).mean((-3, -1))  # noqa: E731
        return {"albedo": box(a), "spec_albedo": box(sp), "uv_mask": box(m.astype(np.float64)) == 1.0}
    c = (np.arange(size) + 0.5) / size
    u, v = np.meshgrid(c, c)
    uv = np.stack([u.ravel(), v.ravel()], 1)
    stack = np.concatenate([a, sp[None], m[None].astype(np.float64)])
    r = sample_uv_bilinear(stack, uv).T.reshape(5, size, size)
    iy = np.minimum((c * S).astype(int), S - 1)
    return {"albedo": r[:3], "spec_albedo": r[3], "uv_mask": m[np.ix_(iy, iy)]}


def _get(model, k):
    return getattr(model, k) if hasattr(model, k) and not isinstance(model, Mapping) else model[k]


@dataclass
class NormalEquations:
    """``AᵀA`` (M,M), ``Aᵀy`` (M,), ``yᵀy``, row count ``n`` and ``sum_y2`` of the linear model I = A β + y0
    (y = I_obs − y0), plus ``observed`` (S,S) bool: texels observed in at least one used pair."""

    AtA: np.ndarray
    Aty: np.ndarray
    yty: float
    n: int
    sum_y2: float
    observed: np.ndarray


def observation_normal_equations(model, obs: Mapping[str, np.ndarray], pairs: Sequence[int] | None = None,
                                 n_components: int | None = None) -> NormalEquations:
    """Accumulate the normal equations of the observed radiance of ``pairs`` (default all) in β.

    ``model``: :class:`reflectmm_cli.model.ReflectanceModel` or artifact arrays (UV part: ``albedo_mean``
    (3,S,S), ``albedo_basis`` (M,3,S,S), ``weights_mean`` (K,S,S), ``weights_basis`` (M,K,S,S), ``sigma``,
    ``exponents``, ``mask``); ``obs``: uv-observations arrays of the SAME UV size.
    """
    from reflectmm_cli.shading import shade_directional

    from .representation import pair_geometry

    am = np.asarray(_get(model, "albedo_mean"), np.float64)
    S = am.shape[-1]
    if np.asarray(obs["mask"]).shape != (S, S):
        raise ReflectmmError(f"albedo eval: model UV size {S} but observations are {np.asarray(obs['mask']).shape}")
    sigma = np.asarray(_get(model, "sigma"), np.float64)
    M = sigma.shape[0] if n_components is None else min(int(n_components), sigma.shape[0])
    exps = np.asarray(_get(model, "exponents"), np.float64).reshape(-1)
    K = exps.shape[0]
    flat = lambda x: x.reshape(x.shape[:-2] + (S * S,))  # noqa: E731 - texels on one axis
    dom = flat(np.asarray(_get(model, "mask"), bool) & np.asarray(obs["mask"], bool))
    J = np.asarray(obs["pair_flash"]).shape[0]
    pairs = list(range(J)) if pairs is None else [int(j) for j in pairs]
    am = flat(am)  # (3,S²)
    ab = flat(np.asarray(_get(model, "albedo_basis"), np.float64)[:M])  # (M,3,S²)
    wb = flat(np.asarray(_get(model, "weights_basis"), np.float64)[:M])  # (M,K,S²)
    wm = flat(np.asarray(_get(model, "weights_mean"), np.float64))
    nrm = np.asarray(obs["normal"], np.float64).reshape(S * S, 3)
    observed = np.asarray(obs["observed"], bool)
    radiance = np.asarray(obs["radiance"])
    # one shading call per pair gives the diffuse transport (slot 0: white albedo, no lobe) and each lobe's
    # (slot 1 + i: lobe i of weight 1), broadcast over a (texels, 1 + K) leading shape
    unit_c = np.zeros((1, K + 1, 3))
    unit_c[0, 0] = 1.0
    unit_w = np.zeros((1, K + 1, K))
    unit_w[0, 1:] = np.eye(K)
    AtA = np.zeros((M, M))
    Aty = np.zeros(M)
    yty = sum_y2 = 0.0
    n = 0
    seen = np.zeros(S * S, bool)
    for j in pairs:
        idx = np.flatnonzero(observed[j].reshape(-1) & dom)
        if idx.size == 0:
            continue
        seen[idx] = True
        l_, v_, E = pair_geometry(obs, j, idx)
        Et = np.repeat(E[:, None], 3, 1)
        g = shade_directional(unit_c, unit_w, exps, nrm[idx][:, None], l_[:, None], v_[:, None], Et[:, None])
        gd, gl = g[:, 0, 0], g[:, 1:, 0]  # (T,), (T,K)
        spec_mean = (wm[:, idx].T * gl).sum(1)  # (T,)
        spec_basis = np.einsum("mkt,tk->tm", wb[:, :, idx], gl) * sigma[:M]  # (T,M)
        rad = np.asarray(radiance[j].reshape(S * S, 3)[idx], np.float64)  # (T,3)
        for ch in range(3):
            A = ab[:, ch, idx].T * sigma[:M] * gd[:, None] + spec_basis  # (T,M)
            y = rad[:, ch] - (am[ch, idx] * gd + spec_mean)
            AtA += A.T @ A
            Aty += A.T @ y
            yty += float(y @ y)
            sum_y2 += float(rad[:, ch] @ rad[:, ch])
            n += idx.size
    seen = seen.reshape(S, S)
    if n == 0:
        raise ReflectmmError("albedo eval: no observed texel inside the model domain in the pairs used")
    return NormalEquations(AtA, Aty, yty, n, sum_y2, seen)


def fit_coefficients(model, obs: Mapping[str, np.ndarray], *, prior: float = DEFAULT_PRIOR,
                     pairs: Sequence[int] | None = None, n_components: int | None = None,
                     equations: NormalEquations | None = None) -> tuple[np.ndarray, dict[str, float]]:
    """β (M,) minimising ``(1/N)‖Aβ − y‖² + prior · ȳ² · ‖β‖²`` (module docstring) and fit statistics
    ``{"rms_residual", "rms_radiance", "rows"}``."""
    if prior < 0 or not np.isfinite(prior):
        raise ReflectmmError(f"albedo eval: prior must be a finite number ≥ 0, got {prior}")
    ne = equations or observation_normal_equations(model, obs, pairs, n_components)
    ybar2 = ne.sum_y2 / ne.n
    H = ne.AtA / ne.n + prior * ybar2 * np.eye(ne.AtA.shape[0])
    beta = np.linalg.lstsq(H, ne.Aty / ne.n, rcond=None)[0]
    res = (beta @ ne.AtA @ beta - 2 * beta @ ne.Aty + ne.yty) / ne.n
    return beta, {"rms_residual": float(np.sqrt(max(res, 0.0))), "rms_radiance": float(np.sqrt(ybar2)),
                  "rows": int(ne.n)}


def oracle_coefficients(model, truth_albedo: np.ndarray, n_components: int | None = None) -> np.ndarray:
    """β of the orthogonal projection of the true diffuse albedo (3,S,S) on the model's diffuse bases (domain)."""
    d = np.asarray(_get(model, "mask"), bool)
    sigma = np.asarray(_get(model, "sigma"), np.float64)
    m = sigma.shape[0] if n_components is None else min(int(n_components), sigma.shape[0])
    x = (np.asarray(truth_albedo, np.float64) - np.asarray(_get(model, "albedo_mean"), np.float64))[:, d].reshape(-1)
    B = np.asarray(_get(model, "albedo_basis"), np.float64)[:m][:, :, d].reshape(m, -1)
    return np.linalg.lstsq(B.T, x, rcond=None)[0] / sigma[:m]


def _psnr(pred, truth, peak=1.0):
    mse = float(np.mean((pred - truth) ** 2))
    return float("inf") if mse == 0 else float(10 * np.log10(peak * peak / mse))


def _relative_rmse(pred, truth):
    """RMSE of ``pred`` / RMS of ``truth`` (NaN when the truth is zero)."""
    rms = float(np.sqrt(np.mean(truth ** 2)))
    return float(np.sqrt(np.mean((pred - truth) ** 2)) / rms) if rms > 0 else float("nan")


def albedo_errors(albedo: np.ndarray, spec_albedo: np.ndarray, truth_albedo: np.ndarray,
                  truth_spec: np.ndarray, region: np.ndarray, peak: float = 1.0) -> dict[str, Any]:
    """Diffuse (3,S,S) and specular (S,S) albedo against the truth over ``region`` (S,S) bool, raw and after one
    global scale (fitted on the diffuse albedo, applied to both): ``{"scale", "texels", "raw": {...},
    "scaled": {...}}`` with ``diffuse_psnr``, ``specular_psnr`` (dB, linear, ``peak``), ``diffuse_rel``,
    ``specular_rel`` (RMSE / RMS truth)."""
    C, Ct = np.asarray(albedo, np.float64), np.asarray(truth_albedo, np.float64)
    s_, st = np.asarray(spec_albedo, np.float64), np.asarray(truth_spec, np.float64)
    reg = np.asarray(region, bool)
    if C.shape != Ct.shape or s_.shape != st.shape or reg.shape != st.shape:
        raise ReflectmmError(f"albedo eval: shapes differ: albedo {C.shape} vs {Ct.shape}, specular {s_.shape} vs "
                             f"{st.shape}, region {reg.shape}")
    if not reg.any():
        raise ReflectmmError("albedo eval: the evaluation region is empty")
    scale = global_scale(C, Ct, reg)
    out: dict[str, Any] = {"scale": scale, "texels": int(reg.sum()), "raw": {}, "scaled": {}}
    for mode, k in (("raw", 1.0), ("scaled", scale)):
        out[mode] = {"diffuse_psnr": _psnr(k * C[:, reg], Ct[:, reg], peak),
                     "specular_psnr": _psnr(k * s_[reg], st[reg], peak),
                     "diffuse_rel": _relative_rmse(k * C[:, reg], Ct[:, reg]),
                     "specular_rel": _relative_rmse(k * s_[reg], st[reg])}
    return out


@dataclass
class AlbedoResult:
    """Per model: per identity error dicts (``per_identity[model][id]``), fitted β and fit statistics."""

    per_identity: dict[str, dict[str, dict[str, Any]]] = field(default_factory=dict)
    betas: dict[str, dict[str, np.ndarray]] = field(default_factory=dict)
    fits: dict[str, dict[str, dict[str, float]]] = field(default_factory=dict)


def evaluate_albedo(models: Mapping[str, Any], identities: Mapping[str, tuple[Mapping[str, np.ndarray],
                                                                              Mapping[str, np.ndarray]]],
                    *, prior: float = DEFAULT_PRIOR, pairs: Sequence[int] | None = None, oracle: bool = False,
                    progress_fn=None) -> AlbedoResult:
    """Table 3: every model × every held-out identity.

    Args:
        models: name → reflectance model (object or artifact arrays), all of the observations' UV size.
        identities: id → (uv-observations arrays, truth arrays with ``albedo`` (3,S,S), ``spec_albedo`` (S,S) and
            optionally ``uv_mask``; a truth of another UV size is resampled with :func:`resample_truth`).
        prior: λ of :func:`fit_coefficients`; pairs: pair indices used for the fit (default all).
        oracle: also evaluate the projection of the true diffuse albedo (model name suffixed " (oracle)").
    """
    from reflectmm_cli.model.pca import sample_model

    res = AlbedoResult()
    items = [(m, i) for m in models for i in identities]
    it = progress_fn(items) if progress_fn is not None else items
    for mname, iid in it:
        model = models[mname]
        obs, truth = identities[iid]
        truth = resample_truth(truth, int(np.asarray(obs["mask"]).shape[-1]))
        ne = observation_normal_equations(model, obs, pairs)
        beta, stats = fit_coefficients(model, obs, prior=prior, equations=ne)
        tmask = np.asarray(truth.get("uv_mask", np.ones(ne.observed.shape, bool)), bool)
        region = ne.observed & tmask
        variants = [(mname, beta)]
        if oracle:
            variants.append((f"{mname} (oracle)", oracle_coefficients(model, truth["albedo"])))
        for name, b in variants:
            C, W = sample_model(model, b, "uv")
            err = albedo_errors(C, W.sum(0), truth["albedo"], truth["spec_albedo"], region)
            res.per_identity.setdefault(name, {})[iid] = err
            res.betas.setdefault(name, {})[iid] = np.asarray(b, np.float64)
            res.fits.setdefault(name, {})[iid] = stats if name == mname else {}
    return res


def albedo_table_rows(result: AlbedoResult, level: float = 0.95) -> list[dict[str, Any]]:
    """One row per model: mean (and CI over identities) of each error, raw and scaled."""
    from .face_metrics import mean_ci

    rows = []
    for name, per in result.per_identity.items():
        row: dict[str, Any] = {"model": name, "identities": len(per)}
        for mode in ("raw", "scaled"):
            for k in ("diffuse_psnr", "specular_psnr", "diffuse_rel", "specular_rel"):
                vals = [min(e[mode][k], 100.0) for e in per.values()]
                row[f"{mode}.{k}"] = mean_ci(vals, level=level)
        rows.append(row)
    return rows
