"""Expressive power of a reflectance model, measured against ground truth (synthetic world): how well the true
per-vertex reflectance of identities the model has never seen lies in the model's span, and the same measure for an
*oracle* model of the same size built from the training identities' own truth.

Shapes: N identities, V vertices, C channels (3 for the diffuse albedo, K for the lobe weights), M components.

Projection of one identity's truth ``t`` (V, C) onto a model part (mean μ (V, C), bases b_k (V, C), σ_k), with one
free scale s (an identity's overall brightness is not the model's business: the light absorbs it) and the model's
prior on β (β in units of σ):

    (s, c) = argmin  ‖s μ + Σ_k c_k σ_k b_k − t‖²_R / ‖t‖²_R  +  λ ‖c‖²,        c = s β

over the vertices R of the region. It is linear in (s, c): one dense (M+1)×(M+1) solve per identity. The relative
residual ``‖s μ + Σ c_k σ_k b_k − t‖_R / ‖t‖_R`` is reported.
"""
from __future__ import annotations

from typing import Sequence

import numpy as np

from reflectmm_cli.errors import ReflectmmError

__all__ = ["projection_residuals", "projection_coefficients", "oracle_model", "oracle_reflectance_model", "gap_closed",
           "PRIOR_WEIGHT"]

#: λ of the projection (relative data term): a coefficient of 3σ costs 0.009, as much as a relative residual of 0.095.
PRIOR_WEIGHT = 1e-3


def projection_residuals(mean, basis, sigma, truth, region=None, *, prior: float = PRIOR_WEIGHT) -> np.ndarray:
    """Relative residual of each identity's truth after projection onto a model part (module docstring).

    Args:
        mean: (V, C) the part's mean; basis: (M, V, C) its bases; sigma: (M,) their standard deviations.
        truth: (N, V, C) true per-vertex values of N identities.
        region: (V,) or (N, V) bool vertices that count (default all).
        prior: λ ≥ 0.
    Returns:
        (N,) float64 relative residuals (0 = the truth is in the span).
    """
    return _project(mean, basis, sigma, truth, region, prior)[1]


def projection_coefficients(mean, basis, sigma, truth, region=None, *, prior: float = PRIOR_WEIGHT) -> np.ndarray:
    """The minimisers (s, c) of the projection (module docstring) of each identity's truth, arguments as
    :func:`projection_residuals`: (N, M+1) float64, column 0 the scale s, then c = s β (so β = c / s)."""
    return _project(mean, basis, sigma, truth, region, prior)[0]


def _project(mean, basis, sigma, truth, region, prior: float) -> tuple[np.ndarray, np.ndarray]:
    """((N, M+1) minimisers (s, c), (N,) relative residuals) of the projection, inputs checked."""
    mu = np.asarray(mean, np.float64)
    B = np.asarray(basis, np.float64)
    sg = np.asarray(sigma, np.float64).reshape(-1)
    T = np.asarray(truth, np.float64)
    if mu.ndim != 2 or B.shape[1:] != mu.shape or B.shape[0] != sg.shape[0]:
        raise ReflectmmError(f"expressive power: the model part has mean {mu.shape}, bases {B.shape}, sigma "
                             f"{sg.shape}; expected (V,C), (M,V,C), (M,)")
    if T.ndim != 3 or T.shape[1:] != mu.shape:
        raise ReflectmmError(f"expressive power: truth must be (N,{mu.shape[0]},{mu.shape[1]}), got {T.shape}")
    if not (np.isfinite(mu).all() and np.isfinite(B).all() and np.isfinite(T).all()):
        raise ReflectmmError("expressive power: NaN or inf in the model or the truth")
    if not (prior >= 0 and np.isfinite(prior)):
        raise ReflectmmError(f"expressive power: prior must be finite and ≥ 0, got {prior}")
    N, V = T.shape[:2]
    R = np.ones((N, V), bool) if region is None else np.broadcast_to(np.asarray(region, bool), (N, V))
    M = B.shape[0]
    X = np.empty((N, M + 1))
    out = np.empty(N)
    for i in range(N):
        r = R[i]
        t = T[i][r].reshape(-1)
        tt = float(t @ t)
        if tt <= 0:
            raise ReflectmmError(f"expressive power: identity {i} has zero truth over its region")
        A = np.concatenate([mu[r].reshape(-1, 1), (B[:, r] * sg[:, None, None]).reshape(M, -1).T], 1)
        H = A.T @ A / tt
        H[1:, 1:] += prior * np.eye(M)
        x = np.linalg.solve(H + 1e-12 * np.eye(M + 1) * max(np.trace(H), 1e-300), A.T @ t / tt)
        res = A @ x - t
        X[i] = x
        out[i] = float(np.sqrt(res @ res / tt))
    return X, out


def _oracle_pca(albedos, weights, exponents, components: int, ids: Sequence[str] | None):
    """build-pca's PCA and transfer of N identities' per-vertex truth: (the model on a square grid of the V
    vertices, the map ``back`` from its (..., C, S, S) arrays to (..., V, C))."""
    from reflectmm_cli.model.pca import fit_reflectance_pca

    a = np.asarray(albedos, np.float32)
    w = np.asarray(weights, np.float32)
    if a.ndim != 3 or a.shape[2] != 3 or w.ndim != 3 or w.shape[:2] != a.shape[:2]:
        raise ReflectmmError(f"oracle model: albedos (N,V,3) and weights (N,V,K) expected, got {a.shape} and "
                             f"{w.shape}")
    N, V, K = w.shape
    # the PCA works on square (C, S, S) maps: lay the V vertices out on an S×S grid, padded texels masked out
    S = int(np.ceil(np.sqrt(V)))
    mask = np.zeros(S * S, bool)
    mask[:V] = True
    mask = mask.reshape(S, S)

    def grid(x):  # (V, C) → (C, S, S)
        g = np.zeros((S * S, x.shape[1]), np.float32)
        g[:V] = x
        return g.T.reshape(x.shape[1], S, S)

    model = fit_reflectance_pca([grid(x) for x in a], [grid(x) for x in w], exponents, masks=[mask] * N,
                                components=components, ids=ids)

    def back(m):  # (..., C, S, S) → (..., V, C)
        flat = m.reshape(m.shape[:-2] + (S * S,))[..., :V]
        return np.moveaxis(flat, -1, -2).astype(np.float32)

    return model, back


def oracle_model(albedos, weights, exponents, components: int, ids: Sequence[str] | None = None) -> dict:
    """A per-vertex model of ``components`` components built from N identities' *true* per-vertex reflectance by
    the very PCA and lobe-weight transfer of ``build-pca`` (:func:`reflectmm_cli.model.pca.fit_reflectance_pca`):
    the best a model of that size can do with that population — the oracle of finetuning.

    Args:
        albedos: (N, V, 3); weights: (N, V, K); exponents: (K,); components: M (capped at N − 1 as in build-pca).
    Returns:
        ``{"vertex_albedo_mean" (V,3), "vertex_albedo_basis" (M,V,3), "vertex_weights_mean" (V,K),
        "vertex_weights_basis" (M,V,K), "sigma" (M,), "exponents" (K,)}`` float32.
    """
    model, back = _oracle_pca(albedos, weights, exponents, components, ids)
    return {"vertex_albedo_mean": back(model.albedo_mean), "vertex_albedo_basis": back(model.albedo_basis),
            "vertex_weights_mean": back(model.weights_mean), "vertex_weights_basis": back(model.weights_basis),
            "sigma": np.asarray(model.sigma, np.float32), "exponents": np.asarray(exponents, np.float32)}


def oracle_reflectance_model(albedos, weights, exponents, components: int, uv, triangles, size: int,
                             ids: Sequence[str] | None = None):
    """The oracle of :func:`oracle_model` as a whole :class:`~reflectmm_cli.model.pca.ReflectanceModel`, so that
    ``finetune``, ``reconstruct``, ``evaluate`` and ``view`` read it like ``build-pca``'s model: its per-vertex part
    is exactly :func:`oracle_model`'s (the same PCA of the same truth), its UV maps that part interpolated over the
    face model's UV layout (barycentric, carried to the nearest covered texel outside it; the model's domain is
    the layout's coverage), σ, the explained variance and the training coefficients those of the PCA.

    Args:
        albedos: (N, V, 3); weights: (N, V, K); exponents: (K,); components: M (capped at N − 1);
        uv: (V, 2) the face model's vertex UVs; triangles: (T, 3); size: S of the S×S UV maps.
    """
    from scipy.ndimage import distance_transform_edt

    from reflectmm_cli.geometry.uv import rasterize_uv, vertex_to_uv_map
    from reflectmm_cli.model.pca import ReflectanceModel

    model, back = _oracle_pca(albedos, weights, exponents, components, ids)
    uv = np.asarray(uv, np.float64)
    V = int(np.shape(albedos)[1])
    if uv.ndim != 2 or uv.shape != (V, 2):
        raise ReflectmmError(f"oracle model: the face model has {uv.shape[0]} vertex UVs, the truth {V} vertices")
    r = rasterize_uv(uv, triangles, int(size))
    vam, vab = back(model.albedo_mean), back(model.albedo_basis)
    vwm, vwb = back(model.weights_mean), back(model.weights_basis)
    # texels outside the layout take their nearest covered texel's value, so that a bilinear lookup at a vertex
    # on the layout's border does not blend in zeros
    near = distance_transform_edt(~np.asarray(r.mask, bool), return_distances=False, return_indices=True)

    def to_map(x):  # (V, C) → (C, S, S)
        m = vertex_to_uv_map(x, r)
        return m[:, near[0], near[1]].astype(np.float32)

    return ReflectanceModel(
        albedo_mean=to_map(vam), albedo_basis=np.stack([to_map(b) for b in vab]),
        weights_mean=to_map(vwm), weights_basis=np.stack([to_map(b) for b in vwb]),
        sigma=np.asarray(model.sigma, np.float32), explained_variance=np.asarray(model.explained_variance, np.float32),
        explained_variance_ratio=np.asarray(model.explained_variance_ratio, np.float32),
        exponents=np.asarray(exponents, np.float32), mask=np.asarray(r.mask, bool),
        train_coeffs=np.asarray(model.train_coeffs, np.float32), ids=list(model.ids),
        vertex_albedo_mean=vam, vertex_albedo_basis=vab, vertex_weights_mean=vwm, vertex_weights_basis=vwb,
        stats={"baseline": "oracle", "n_vertices": V, "uv_maps": "the per-vertex model interpolated over the UV "
               "layout"})


def gap_closed(initial: float, finetuned: float, oracle: float) -> float:
    """``(initial − finetuned) / (initial − oracle)`` for an error measure (lower is better): 1 = finetuning reached
    the oracle, 0 = no change, < 0 = it moved away; NaN when the oracle is no better than the initial model."""
    den = initial - oracle
    return float((initial - finetuned) / den) if den > 0 else float("nan")
