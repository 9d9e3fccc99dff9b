"""The initial reflectance model: PCA of diffuse albedo with AlbedoMM-style specular transfer (docs/design.md §1 step 5).

Data. Each identity j contributes a diffuse albedo map ``C_j (3,S,S)`` and a lobe-weight map ``W_j (K,S,S)``
(``reflectance-maps`` artifacts). The model lives on the *model domain* ``D`` = union of the maps' masks; texels
outside ``D`` are 0 in the mean and every basis. Inside ``D`` a map's value is used as stored, including flagged
(ill-conditioned) texels, which the fitter has already filled from the mirror texel / neighbourhood ("the map's
own value"). A texel of ``D`` outside one map's own mask (only possible when masks differ) takes the mean of the
maps that do cover it, so it adds no variance. The counts are reported (:attr:`ReflectanceModel.stats`).

Method. ``x_j`` = flattened diffuse albedo over ``D`` (3·|D| values), ``y_j`` = flattened weights (K·|D|).
With ``X̃ = X − μ`` (N × D) and its thin SVD ``X̃ = U Σ Vᵀ`` (computed through the N×N Gram matrix
``X̃ X̃ᵀ = U Σ² Uᵀ`` plus one symmetric re-orthonormalisation step, see the code):

* diffuse basis ``b_k = V[:, k]`` — orthonormal, and ``b_k = Σ_j a_kj x̃_j`` with ``a_kj = U_jk / Σ_k``;
* specular basis ``s_k = Σ_j a_kj ỹ_j = Ỹᵀ U[:, k] / Σ_k`` — the *same* linear combination of the training
  samples (AlbedoMM), so one coefficient vector drives both and the diffuse bases stay orthonormal;
* ``σ_k = Σ_k / √(N − 1)`` — the sample standard deviation (ddof = 1) of the training projections
  ``x̃_j · b_k``; ``explained_variance = σ²``.

A sample with coefficients β (in units of σ) is ``C = μ_C + Σ_k β_k σ_k b_k`` and ``W = μ_W + Σ_k β_k σ_k s_k``.
With all N − 1 components every training pair (C_j, W_j) is reproduced exactly (β_jk = U_jk √(N−1)).
Components are capped by N − 1 (and by the numerical rank) with a message.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, Callable, Mapping, Sequence

import numpy as np

from reflectmm_cli.errors import ReflectmmError

__all__ = [
    "MODEL_KIND",
    "ReflectanceModel",
    "fit_reflectance_pca",
    "model_arrays",
    "model_from_arrays",
    "sample_model",
    "project_maps",
    "model_to_torch",
    "sample_uv_bilinear",
    "add_vertex_model",
]

MODEL_KIND = "reflectance-model"

#: singular values below this fraction of the largest are treated as zero (rank deficiency; the Gram route
#: resolves singular values down to ~1e-8 of the largest).
RANK_TOL = 1e-6


@dataclass
class ReflectanceModel:
    """PCA reflectance model (UV space, optionally per vertex). M components, K lobes, S×S UV maps.

    Attributes:
        albedo_mean: (3,S,S) linear diffuse albedo mean.
        albedo_basis: (M,3,S,S) orthonormal diffuse bases (as flattened vectors over all texels).
        weights_mean: (K,S,S) lobe-weight mean.
        weights_basis: (M,K,S,S) specular bases (same combination of training samples; not orthonormal).
        sigma: (M,) standard deviation of the training data along each diffuse basis (ddof = 1).
        explained_variance: (M,) sigma².
        explained_variance_ratio: (M,) fraction of the total diffuse variance.
        exponents: (K,) lobe exponents.
        mask: (S,S) bool model domain (union of the training masks).
        train_coeffs: (N,M) β of each training identity (units of σ).
        ids: training identity names.
        vertex_*: per-vertex model (UV maps sampled at the face model's vertex UVs), or None.
    """

    albedo_mean: np.ndarray
    albedo_basis: np.ndarray
    weights_mean: np.ndarray
    weights_basis: np.ndarray
    sigma: np.ndarray
    explained_variance: np.ndarray
    explained_variance_ratio: np.ndarray
    exponents: np.ndarray
    mask: np.ndarray
    train_coeffs: np.ndarray
    ids: list[str] = field(default_factory=list)
    vertex_albedo_mean: np.ndarray | None = None
    vertex_albedo_basis: np.ndarray | None = None
    vertex_weights_mean: np.ndarray | None = None
    vertex_weights_basis: np.ndarray | None = None
    stats: dict[str, Any] = field(default_factory=dict)

    @property
    def n_components(self) -> int:
        return int(self.sigma.shape[0])

    @property
    def size(self) -> int:
        return int(self.albedo_mean.shape[-1])

    @property
    def n_lobes(self) -> int:
        return int(self.weights_mean.shape[0])

    @property
    def has_vertex_model(self) -> bool:
        return self.vertex_albedo_mean is not None


def _check_maps(albedos: Sequence[np.ndarray], weights: Sequence[np.ndarray], masks, names) -> None:
    if len(albedos) != len(weights):
        raise ReflectmmError(f"build-pca: {len(albedos)} albedo maps but {len(weights)} weight maps")
    if len(albedos) < 2:
        raise ReflectmmError(f"build-pca: a PCA needs at least 2 identities, got {len(albedos)}")
    a0, w0 = np.shape(albedos[0]), np.shape(weights[0])
    if len(a0) != 3 or a0[0] != 3 or a0[1] != a0[2]:
        raise ReflectmmError(f"build-pca: {names[0]}: albedo must have shape (3,S,S), got {a0}")
    if len(w0) != 3 or w0[1:] != a0[1:]:
        raise ReflectmmError(f"build-pca: {names[0]}: weights must have shape (K,{a0[1]},{a0[2]}), got {w0}")
    for i in range(len(albedos)):
        if np.shape(albedos[i]) != a0:
            raise ReflectmmError(f"build-pca: {names[i]}: albedo has shape {np.shape(albedos[i])}, expected {a0} "
                                 f"(as {names[0]})")
        if np.shape(weights[i]) != w0:
            raise ReflectmmError(f"build-pca: {names[i]}: weights have shape {np.shape(weights[i])}, expected {w0} "
                                 f"(as {names[0]}; all maps must share the lobe exponents and UV size)")
        if masks is not None and np.shape(masks[i]) != a0[1:]:
            raise ReflectmmError(f"build-pca: {names[i]}: mask has shape {np.shape(masks[i])}, expected {a0[1:]}")
        for what, arr in (("albedo", albedos[i]), ("weights", weights[i])):
            if not np.all(np.isfinite(arr)):
                raise ReflectmmError(f"build-pca: {names[i]}: {what} contains NaN or inf")


def fit_reflectance_pca(albedos: Sequence[np.ndarray], weights: Sequence[np.ndarray], exponents,
                        masks: Sequence[np.ndarray] | None = None, flagged: Sequence[np.ndarray] | None = None,
                        components: int = 80, ids: Sequence[str] | None = None,
                        log: Callable[[str], Any] | None = None) -> ReflectanceModel:
    """PCA of N identities' diffuse albedo; specular bases by the same combination of training samples.

    Args:
        albedos: N arrays (3,S,S) linear diffuse albedo.
        weights: N arrays (K,S,S) lobe weights (same K and exponents for all).
        exponents: (K,) lobe exponents (stored in the model).
        masks: N bool (S,S) face masks (default: all texels).
        flagged: N bool (S,S) flagged texels (only counted; their stored, filled values are used).
        components: requested number of components; capped by N − 1 and the numerical rank (message via ``log``).
        ids: names of the identities (for messages and the model).
        log: callable receiving human-readable messages (e.g. ``logging.warning``).
    Returns:
        :class:`ReflectanceModel` (UV space only; add the vertex model with :func:`add_vertex_model`).
    """
    n = len(albedos)
    names = list(ids) if ids is not None else [f"#{i}" for i in range(n)]
    _check_maps(albedos, weights, masks, names)
    if components < 1:
        raise ReflectmmError(f"build-pca: --components must be ≥ 1, got {components}")
    K, S = int(np.shape(weights[0])[0]), int(np.shape(albedos[0])[-1])
    exps = np.asarray(exponents, np.float64).reshape(-1)
    if exps.shape[0] != K:
        raise ReflectmmError(f"build-pca: {K} lobe-weight channels but {exps.shape[0]} exponents")
    from reflectmm_cli.shading.brdf import check_distinct_exponents

    check_distinct_exponents(exps, "build-pca: the maps' lobe exponents")
    M_ = np.ones((n, S, S), bool) if masks is None else np.stack([np.asarray(m, bool) for m in masks])
    domain = M_.any(0)
    if not domain.any():
        raise ReflectmmError("build-pca: the union of the maps' masks is empty")
    cover = M_[:, domain]  # (N, D)
    # gather the domain texels only (N × 3D and N × KD float64 — never the full float64 map stacks)
    a_dom = np.stack([np.asarray(a)[:, domain] for a in albedos]).astype(np.float64)  # (N,3,D)
    w_dom = np.stack([np.asarray(w)[:, domain] for w in weights]).astype(np.float64)  # (N,K,D)
    if not cover.all():
        # fill texels of the domain that a map does not cover with the mean of the maps that cover them
        cnt = cover.sum(0)
        a_fill = (a_dom * cover[:, None]).sum(0) / cnt
        w_fill = (w_dom * cover[:, None]).sum(0) / cnt
        a_dom = np.where(cover[:, None], a_dom, a_fill[None])
        w_dom = np.where(cover[:, None], w_dom, w_fill[None])
    X = a_dom.reshape(n, -1)
    Y = w_dom.reshape(n, -1)
    del a_dom, w_dom
    mu_x, mu_y = X.mean(0), Y.mean(0)
    X -= mu_x
    Y -= mu_y
    Xc, Yc = X, Y
    # PCA through the N×N Gram matrix (one GEMM; ~50× faster than a thin SVD of N×D at D = 3·256², N ≪ D),
    # then one step of symmetric (Löwdin) re-orthonormalisation of the bases, which restores orthonormality to
    # machine precision (the Gram route alone loses accuracy for small singular values).
    G = Xc @ Xc.T
    lam, U = np.linalg.eigh(G)
    lam, U = lam[::-1], U[:, ::-1]
    s = np.sqrt(np.clip(lam, 0.0, None))
    cap = n - 1
    rank = int((s > RANK_TOL * max(s[0], 1e-300)).sum()) if s.size else 0
    m = min(components, cap, rank)
    if m < 1:
        raise ReflectmmError("build-pca: the diffuse albedo maps are all identical (zero variance); no components")
    if components > cap:
        _say(log, f"build-pca: {components} components requested but {n} identities give at most N - 1 = {cap}; "
                  f"using {m}")
    elif components > rank:
        _say(log, f"build-pca: {components} components requested but the data have rank {rank}; using {m}")
    # combination matrix: b_k = Σ_j a_jk x̃_j; the specular bases use the very same a (AlbedoMM transfer)
    Acomb = U[:, :m] / s[:m]  # (N, m)
    B = Xc.T @ Acomb  # (Dx, m)
    C = B.T @ B
    ev, Q = np.linalg.eigh(C)
    Rl = (Q / np.sqrt(ev)) @ Q.T  # C^(-1/2): B ← B C^(-1/2) stays a combination of the samples
    Acomb = Acomb @ Rl
    B = B @ Rl
    Sb = Yc.T @ Acomb  # (Dy, m)
    proj = G @ Acomb  # (N, m) training projections X̃ B = X̃ X̃ᵀ A
    sigma = proj.std(0, ddof=1)
    total_var = float((Xc ** 2).sum() / (n - 1))
    beta = proj / sigma  # (N, m) training coefficients in units of σ

    D = int(domain.sum())

    def unflat(vec, C):
        out = np.zeros(vec.shape[:-1] + (C, S, S), np.float32)
        out[..., domain] = vec.reshape(vec.shape[:-1] + (C, D))
        return out

    flagged_count = 0
    if flagged is not None:
        flagged_count = int(sum(int((np.asarray(f, bool) & domain).sum()) for f in flagged))
    stats = {"n_identities": n, "n_components": m, "requested_components": int(components),
             "domain_texels": D, "texels_valid_in_all": int(cover.all(0).sum()),
             "flagged_texels_total": flagged_count, "total_variance": total_var,
             "rank": rank}
    return ReflectanceModel(
        albedo_mean=unflat(mu_x, 3),
        albedo_basis=unflat(B.T, 3),
        weights_mean=unflat(mu_y, K),
        weights_basis=unflat(Sb.T, K),
        sigma=sigma.astype(np.float32),
        explained_variance=(sigma ** 2).astype(np.float32),
        explained_variance_ratio=((sigma ** 2) / total_var if total_var > 0 else sigma * 0).astype(np.float32),
        exponents=exps.astype(np.float32),
        mask=domain,
        train_coeffs=beta.astype(np.float32),
        ids=names,
        stats=stats,
    )


def _say(log, msg):
    if log is not None:
        log(msg)


# --------------------------------------------------------------------------- sampling

def _model_get(model, name):
    if isinstance(model, ReflectanceModel):
        return getattr(model, name)
    return model[name]


def sample_model(model, beta, space: str = "uv"):
    """Albedo and lobe weights of the model for coefficients β (in units of σ).

    Args:
        model: :class:`ReflectanceModel` or a mapping with the artifact's arrays.
        beta: (M',) or (B, M') coefficients, M' ≤ M (missing trailing coefficients are 0). numpy → numpy;
            a torch tensor → torch (differentiable w.r.t. β, on β's device and dtype).
        space: ``"uv"`` → albedo (…,3,S,S), weights (…,K,S,S); ``"vertex"`` → albedo (…,Nv,3), weights (…,Nv,K).
    Returns:
        ``(albedo, weights)`` = ``(μ_C + Σ β_k σ_k b_k, μ_W + Σ β_k σ_k s_k)``.
    """
    if space == "uv":
        names = ("albedo_mean", "albedo_basis", "weights_mean", "weights_basis")
    elif space == "vertex":
        names = ("vertex_albedo_mean", "vertex_albedo_basis", "vertex_weights_mean", "vertex_weights_basis")
    else:
        raise ReflectmmError(f"sample_model: space must be 'uv' or 'vertex', got {space!r}")
    am, ab, wm, wb = (_model_get(model, k) for k in names)
    if am is None:
        raise ReflectmmError("sample_model: this model has no per-vertex part (built without a face model)")
    sigma = _model_get(model, "sigma")
    M = int(np.shape(sigma)[0])
    try:
        import torch
        is_torch = isinstance(beta, torch.Tensor)
    except ImportError:  # pragma: no cover
        is_torch = False
    bshape = tuple(beta.shape) if is_torch else np.shape(beta)
    if len(bshape) not in (1, 2) or bshape[-1] > M:
        raise ReflectmmError(f"sample_model: beta must have shape (M',) or (B, M') with M' ≤ {M}, got {bshape}")
    m = bshape[-1]
    if is_torch:
        import torch

        dev, dt = beta.device, beta.dtype if beta.is_floating_point() else torch.float32

        def t(a):  # model tensors (e.g. trainable, from model_to_torch) are used as they are: gradients flow
            if isinstance(a, torch.Tensor):
                return a if (a.device == dev and a.dtype == dt) else a.to(dev, dt)
            return torch.as_tensor(np.asarray(a), device=dev, dtype=dt)
        coef = beta.to(dt) * t(sigma)[:m]
        alb = t(am) + torch.tensordot(coef, t(ab)[:m], dims=([-1], [0]))
        wts = t(wm) + torch.tensordot(coef, t(wb)[:m], dims=([-1], [0]))
        return alb, wts
    b = np.asarray(beta, np.float64)
    coef = b * np.asarray(sigma, np.float64)[:m]
    alb = np.asarray(am, np.float64) + np.tensordot(coef, np.asarray(ab, np.float64)[:m], axes=([-1], [0]))
    wts = np.asarray(wm, np.float64) + np.tensordot(coef, np.asarray(wb, np.float64)[:m], axes=([-1], [0]))
    return alb, wts


def model_to_torch(model, device="cpu", dtype=None, requires_grad: bool = False) -> dict:
    """The model's arrays as torch tensors (a dict usable by :func:`sample_model`), converted once.

    ``requires_grad=True`` makes the means and bases trainable leaves (finetuning updates the model jointly with
    the encoder, docs/design.md §1 step 7); ``sigma`` and ``exponents`` stay constants.
    """
    import torch

    dtype = dtype or torch.float32
    out = {}
    for k, v in model_arrays(model).items() if isinstance(model, ReflectanceModel) else dict(model).items():
        a = np.asarray(v)
        if a.dtype.kind in "fiu":  # numbers → tensors; mask (bool) and ids (str) stay numpy
            t = torch.as_tensor(a, dtype=dtype, device=device).clone()
            if requires_grad and ("_mean" in k or "_basis" in k):
                t.requires_grad_(True)
            out[k] = t
        else:
            out[k] = a
    return out


def project_maps(model: ReflectanceModel, albedo: np.ndarray, n_components: int | None = None) -> np.ndarray:
    """β (units of σ) of an albedo map: orthogonal projection onto the diffuse bases over the model domain."""
    m = model.n_components if n_components is None else min(n_components, model.n_components)
    d = model.mask
    x = (np.asarray(albedo, np.float64) - model.albedo_mean)[:, d].reshape(-1)
    B = model.albedo_basis[:m][:, :, d].reshape(m, -1).astype(np.float64)
    return (B @ x) / model.sigma[:m].astype(np.float64)


# --------------------------------------------------------------------------- per-vertex model

def sample_uv_bilinear(uv_map: np.ndarray, uv: np.ndarray) -> np.ndarray:
    """Bilinear lookup of a (C,S,S) map at (N,2) UV coordinates → (N,C).

    Texel convention of docs/pipeline.md: texel (row, col) has centre ``u = (col + 0.5)/S``, ``v = (row + 0.5)/S``
    (row 0 at the top, v grows downwards); coordinates are clamped to the texel centres at the border.
    """
    m = np.asarray(uv_map)
    if m.ndim != 3:
        raise ReflectmmError(f"sample_uv_bilinear: map must have shape (C,S,S), got {m.shape}")
    uv = np.asarray(uv, np.float64)
    if uv.ndim != 2 or uv.shape[1] != 2:
        raise ReflectmmError(f"sample_uv_bilinear: uv must have shape (N,2), got {uv.shape}")
    C, H, Wd = m.shape
    x = np.clip(uv[:, 0] * Wd - 0.5, 0, Wd - 1)
    y = np.clip(uv[:, 1] * H - 0.5, 0, H - 1)
    x0 = np.minimum(np.floor(x).astype(np.int64), Wd - 2 if Wd > 1 else 0)
    y0 = np.minimum(np.floor(y).astype(np.int64), H - 2 if H > 1 else 0)
    x1, y1 = np.minimum(x0 + 1, Wd - 1), np.minimum(y0 + 1, H - 1)
    fx, fy = (x - x0)[:, None], (y - y0)[:, None]
    mt = np.moveaxis(m, 0, -1)
    return ((1 - fy) * ((1 - fx) * mt[y0, x0] + fx * mt[y0, x1]) + fy * ((1 - fx) * mt[y1, x0] + fx * mt[y1, x1]))


def _sampler():
    """The geometry package's UV sampler if present (one convention for the whole toolkit), else ours."""
    try:
        from reflectmm_cli.geometry import sample_uv_map  # type: ignore

        return sample_uv_map, "reflectmm_cli.geometry.sample_uv_map"
    except ImportError:
        return sample_uv_bilinear, "reflectmm_cli.model.sample_uv_bilinear"


def add_vertex_model(model: ReflectanceModel, vertex_uv: np.ndarray) -> ReflectanceModel:
    """Sample the mean and every basis at the vertices' UVs (N,2) — sampling is linear, so the per-vertex model
    gives exactly the per-vertex values of the UV model's samples."""
    uv = np.asarray(vertex_uv, np.float64)
    if uv.ndim != 2 or uv.shape[1] != 2:
        raise ReflectmmError(f"build-pca: face model uv must have shape (N,2), got {uv.shape}")
    fn, name = _sampler()
    smp = lambda a: np.asarray(fn(np.asarray(a, np.float32), uv), np.float32)  # noqa: E731
    model.vertex_albedo_mean = smp(model.albedo_mean)
    model.vertex_weights_mean = smp(model.weights_mean)
    model.vertex_albedo_basis = np.stack([smp(b) for b in model.albedo_basis])
    model.vertex_weights_basis = np.stack([smp(b) for b in model.weights_basis])
    model.stats["vertex_sampler"] = name
    model.stats["n_vertices"] = int(uv.shape[0])
    return model


# --------------------------------------------------------------------------- artifact arrays

def model_arrays(model: ReflectanceModel) -> dict[str, np.ndarray]:
    out = {
        "albedo_mean": model.albedo_mean, "albedo_basis": model.albedo_basis,
        "weights_mean": model.weights_mean, "weights_basis": model.weights_basis,
        "sigma": model.sigma, "explained_variance": model.explained_variance,
        "explained_variance_ratio": model.explained_variance_ratio, "exponents": model.exponents,
        "mask": model.mask, "train_coeffs": model.train_coeffs, "ids": np.array(model.ids, dtype=str),
    }
    if model.has_vertex_model:
        out.update(vertex_albedo_mean=model.vertex_albedo_mean, vertex_albedo_basis=model.vertex_albedo_basis,
                   vertex_weights_mean=model.vertex_weights_mean, vertex_weights_basis=model.vertex_weights_basis)
    return out


def model_from_arrays(arrays: Mapping[str, np.ndarray], stats: Mapping[str, Any] | None = None,
                      path=None) -> ReflectanceModel:
    """Inverse of :func:`model_arrays` (e.g. ``model_from_arrays(read_artifact(p, MODEL_KIND).arrays)``).

    A model whose ``sigma`` is not > 0 everywhere is refused (one line naming ``path``): coefficients are in units
    of σ, so a component at σ = 0 can only give the mean and a negative one flips its basis."""
    g = lambda k: arrays[k] if k in arrays else None  # noqa: E731
    sigma = np.asarray(arrays["sigma"], np.float64)
    bad = ~(sigma > 0)
    if bad.any():
        k = int(np.flatnonzero(bad)[0])
        raise ReflectmmError(f"reflectance-model 'sigma' must be > 0: {int(bad.sum())} of its {sigma.size} values are "
                             f"not (first: component {k}, {sigma.flat[k]:g})", path)
    return ReflectanceModel(
        albedo_mean=arrays["albedo_mean"], albedo_basis=arrays["albedo_basis"],
        weights_mean=arrays["weights_mean"], weights_basis=arrays["weights_basis"],
        sigma=arrays["sigma"], explained_variance=arrays["explained_variance"],
        explained_variance_ratio=arrays["explained_variance_ratio"], exponents=arrays["exponents"],
        mask=np.asarray(arrays["mask"], bool), train_coeffs=arrays["train_coeffs"],
        ids=[str(x) for x in arrays["ids"]],
        vertex_albedo_mean=g("vertex_albedo_mean"), vertex_albedo_basis=g("vertex_albedo_basis"),
        vertex_weights_mean=g("vertex_weights_mean"), vertex_weights_basis=g("vertex_weights_basis"),
        stats=dict(stats or {}))
