"""Per-texel shading design of the linear reflectance problem (docs/design.md §2–§3, docs/fit-reflectance.md).

For one texel (position x, unit normal n) and one (view, flash) pair j the model of docs/design.md §2 reads, per
colour channel c,

    I_jc = C_c · d_j + Σ_i W_i · s_ji

with the *design columns*

    d_j  = E_j · max(n·l_j, 0) / π                       (diffuse column)
    s_ji = E_j · f_i · max(n·h_j, 0)^p_i                  (lobe columns, f_i = (p_i+2) / (4π(2 − 2^(−p_i/2))))

where ``l_j = normalize(flash_pos − x)``, ``v_j = normalize(cam_center − x)``, ``h_j = normalize(l_j + v_j)``
and ``E_j = flash_intensity / |flash_pos − x|²`` (point flash, docs/pipeline.md).  Both columns are zero
where the pair is unobserved, where ``n·l ≤ 0`` or where ``n·v ≤ 0`` (as ``shade_directional``).

Conditioning (the exact definition used everywhere in the toolkit):

* ``G = Σ_j a_j a_jᵀ`` over the observed pairs, ``a_j = (d_j, s_j1, …, s_jK)`` — the (1+K)×(1+K) Gram matrix
  of the design columns (the three colour channels share it).  With mirror pooling (``mirror_weight`` w)
  ``G_t + w · G_mirror(t)``.
* ``Ĝ = D^(−1/2) G D^(−1/2)`` with ``D = diag(G)`` (scale-free: unit diagonal).
* ``conditioning = λ_min(Ĝ) / λ_max(Ĝ)`` ∈ [0, 1]: 1 for orthogonal columns, 0 when a column is identically
  zero (e.g. no observation) or the columns are linearly dependent.  It measures collinearity (the p = 1 lobe
  against the diffuse term) but not signal strength.
* ``observability[i] = max_j max(n·h_j, 0)^p_i`` over observed pairs ∈ [0, 1]: the largest fraction of
  lobe i's peak any observation reaches.  On a Multi-PIE-like rig the half vectors lie near one plane, so
  for many texels the p = 64 lobe is never seen near its peak (observability ≪ 1) even when ``conditioning``
  is fine.

Memory: texels are processed in chunks (``chunk`` texels × P pairs), never the whole (S², P, K) block.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Iterator, Mapping, Sequence

import numpy as np

from reflectmm_cli.errors import ReflectmmError
from reflectmm_cli.shading.brdf import DEFAULT_EXPONENTS
from reflectmm_cli.shading.sh import blinn_phong_norm

__all__ = [
    "Design",
    "check_observations",
    "conditioning",
    "conditioning_from_obs",
    "design_columns",
    "design_rows",
    "columns_from_scalars",
    "design_rows_grad",
    "iter_chunks",
    "mirror_index",
    "pair_irradiance",
    "DEFAULT_CHUNK",
]

DEFAULT_CHUNK = 4096


def iter_chunks(n: int, size: int = DEFAULT_CHUNK) -> Iterator[slice]:
    """Slices covering ``range(n)`` in blocks of ``size``."""
    size = max(int(size), 1)
    for a in range(0, n, size):
        yield slice(a, min(a + size, n))


def mirror_index(size: int) -> np.ndarray:
    """Flat index of the mirror texel ``(row, S−1−col)`` of each flat texel ``row·S + col`` (docs/pipeline.md)."""
    idx = np.arange(size * size).reshape(size, size)
    return np.ascontiguousarray(idx[:, ::-1]).reshape(-1)


@dataclass
class Design:
    """Design columns of a block of N texels and P pairs.

    Attributes:
        diffuse: (N, P) ``d = E·max(n·l,0)/π``, 0 where invalid.
        lobes: (N, P, K) ``s_i = E·f_i·max(n·h,0)^p_i``, 0 where invalid.
        cos_l: (N, P) ``max(n·l, 0)``, 0 where invalid (the paper's per-observation loss weight).
        ndh: (N, P) ``max(n·h, 0)``, 0 where invalid.
        valid: (N, P) observed ∧ n·l > 0 ∧ n·v > 0.
    """

    diffuse: np.ndarray
    lobes: np.ndarray
    cos_l: np.ndarray
    ndh: np.ndarray
    valid: np.ndarray


def _normalize(x: np.ndarray) -> np.ndarray:
    n = np.linalg.norm(x, axis=-1, keepdims=True)
    return x / np.where(n > 0, n, 1.0)


def pair_irradiance(flash_intensity, n_flash: int, override=None) -> np.ndarray:
    """(F,) radiant intensity per flash: the artifact's values, or ``override`` (scalar or (F,)) if given."""
    if override is not None:
        I = np.asarray(override, dtype=np.float64).reshape(-1)
        if I.size == 1:
            I = np.full(n_flash, float(I[0]))
    else:
        I = np.asarray(flash_intensity, dtype=np.float64).reshape(-1)
    what = "--flash-intensity" if override is not None else "the observations' flash_intensity"
    if I.shape != (n_flash,):
        raise ReflectmmError(f"{what} has {I.size} values, expected 1 or {n_flash} (one per flash)")
    if not np.all(np.isfinite(I)) or np.any(I <= 0):
        raise ReflectmmError(f"{what} must be finite and > 0, got {I.tolist()}")
    return I


def design_columns(position: np.ndarray, normal: np.ndarray, cam_centers: np.ndarray, flash_pos: np.ndarray,
                   flash_intensity: np.ndarray, pair_view: np.ndarray, pair_flash: np.ndarray,
                   exponents: Sequence[float], observed: np.ndarray | None = None,
                   dtype=np.float64) -> Design:
    """Design columns for N texels and P pairs (see the module docstring).

    Args:
        position: (N, 3) texel positions (model space, mm).
        normal: (N, 3) normals (normalised here).
        cam_centers: (V, 3); flash_pos: (F, 3); flash_intensity: (F,) radiant intensity I (E = I/d²).
        pair_view, pair_flash: (P,) integer indices into the views / flashes.
        exponents: (K,) lobe exponents p_i > 0.
        observed: (N, P) bool or None (all observed).
    Returns:
        :class:`Design` with arrays of ``dtype``.
    """
    x = np.asarray(position, dtype=np.float64)
    n = _normalize(np.asarray(normal, dtype=np.float64))
    p = np.asarray(exponents, dtype=np.float64).reshape(-1)
    pv = np.asarray(pair_view, dtype=np.int64)
    pf = np.asarray(pair_flash, dtype=np.int64)
    fpos = np.asarray(flash_pos, dtype=np.float64)[pf]  # (P,3)
    cpos = np.asarray(cam_centers, dtype=np.float64)[pv]
    I = np.asarray(flash_intensity, dtype=np.float64).reshape(-1)[pf]  # (P,)
    dl = fpos[None, :, :] - x[:, None, :]  # (N,P,3)
    dv = cpos[None, :, :] - x[:, None, :]
    d2 = np.einsum("npk,npk->np", dl, dl)
    v2 = np.einsum("npk,npk->np", dv, dv)
    il = 1.0 / np.sqrt(np.where(d2 > 0, d2, 1.0))
    iv = 1.0 / np.sqrt(np.where(v2 > 0, v2, 1.0))
    ndl = np.einsum("nk,npk->np", n, dl) * il
    ndv = np.einsum("nk,npk->np", n, dv) * iv
    ldv = np.einsum("npk,npk->np", dl, dv) * il * iv
    # n·h with h = (l+v)/|l+v| and |l+v| = sqrt(2 + 2 l·v): no half vector is formed
    hl2 = 2.0 + 2.0 * ldv
    ndh = (ndl + ndv) / np.sqrt(np.where(hl2 > 0, hl2, 1.0))
    valid = (ndl > 0) & (ndv > 0) & (d2 > 0)
    if observed is not None:
        valid &= np.asarray(observed, dtype=bool)
    E = np.where(valid, I[None, :] / np.where(d2 > 0, d2, 1.0), 0.0)
    cos_l = np.where(valid, ndl, 0.0)
    ndh = np.where(valid, np.clip(ndh, 0.0, 1.0), 0.0)
    diffuse = E * cos_l / np.pi
    f = blinn_phong_norm(p)
    # ndh^p via exp(p·log ndh): finite for huge p (underflows to 0) and tiny p; exactly 0 where ndh = 0.
    with np.errstate(divide="ignore"):
        logh = np.log(np.where(ndh > 0, ndh, 1.0))
    lobes = np.exp(logh[..., None] * p) * (E[..., None] * f)
    lobes = np.where((ndh > 0)[..., None], lobes, 0.0)
    return Design(diffuse.astype(dtype, copy=False), lobes.astype(dtype, copy=False),
                  cos_l.astype(dtype, copy=False), ndh.astype(dtype, copy=False), valid)


def design_rows(x: np.ndarray, n: np.ndarray, flash: np.ndarray, cam: np.ndarray, intensity: np.ndarray,
                exponents: Sequence[float]) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Design columns of R individual observations (the same formulas as :func:`design_columns`).

    Args:
        x, n: (R, 3) texel position and unit normal; flash, cam: (R, 3) flash and camera positions;
        intensity: (R,) flash radiant intensity; exponents: (K,).
    Returns:
        (d (R,), s (R, K), cos_l (R,), ndh (R,)), all 0 where n·l ≤ 0 or n·v ≤ 0.
    """
    dl = flash - x
    dv = cam - x
    d2 = np.einsum("rk,rk->r", dl, dl)
    v2 = np.einsum("rk,rk->r", dv, dv)
    return columns_from_scalars(np.einsum("rk,rk->r", n, dl), np.einsum("rk,rk->r", n, dv),
                                np.einsum("rk,rk->r", dl, dv), d2, v2, intensity, exponents)


def columns_from_scalars(nl: np.ndarray, nv: np.ndarray, lv: np.ndarray, d2: np.ndarray, v2: np.ndarray,
                         intensity: np.ndarray, exponents: Sequence[float]
                         ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Design columns from the unnormalised scalars of R observations (unit normal n, unnormalised
    ``L = flash − x``, ``V = cam − x``): ``nl = n·L``, ``nv = n·V``, ``lv = L·V``, ``d2 = |L|²``, ``v2 = |V|²``.

    Returns (d, s (R,K), cos_l, ndh) as :func:`design_rows`.
    """
    p = np.asarray(exponents, dtype=np.float64).reshape(-1)
    il = 1.0 / np.sqrt(np.where(d2 > 0, d2, 1.0))
    iv = 1.0 / np.sqrt(np.where(v2 > 0, v2, 1.0))
    ndl = nl * il
    ndv = nv * iv
    hl2 = 2.0 + 2.0 * lv * il * iv
    ok = (ndl > 0) & (ndv > 0) & (d2 > 0) & (v2 > 0)
    ndh = np.where(ok, np.clip((ndl + ndv) / np.sqrt(np.where(hl2 > 0, hl2, 1.0)), 0.0, 1.0), 0.0)
    E = np.where(ok, intensity * (il * il), 0.0)
    cos_l = np.where(ok, ndl, 0.0)
    d = E * cos_l / np.pi
    with np.errstate(divide="ignore"):
        logh = np.log(np.where(ndh > 0, ndh, 1.0))
    s = np.exp(logh[:, None] * p) * (E[:, None] * blinn_phong_norm(p))
    s = np.where((ndh > 0)[:, None], s, 0.0)
    return d, s, cos_l, ndh


def design_rows_grad(x: np.ndarray, n: np.ndarray, flash: np.ndarray, cam: np.ndarray, intensity: np.ndarray,
                     exponents: Sequence[float]
                     ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Design columns of R observations and their derivatives with respect to the normal n (analytic).

    The columns of :func:`design_rows` as functions of the (unit) normal n, with l, v, h, E fixed:
    ``d = E·(n·l)/π`` and ``s_i = E·f_i·(n·h)^p_i`` inside the valid set (n·l > 0, n·v > 0), so

        ∂d/∂n   = E·l/π
        ∂s_i/∂n = E·f_i·p_i·(n·h)^(p_i−1)·h

    and both are 0 outside it (the valid set is held fixed: the derivative of the cut is not taken; the
    columns are continuous at n·l = 0 for d but not for s, like the model).  For p_i < 1 the derivative is
    unbounded as n·h → 0; it is set to 0 where n·h = 0.

    Args / returns as :func:`design_rows`, plus ``dd (R, 3)`` and ``ds (R, K, 3)``.
    """
    p = np.asarray(exponents, dtype=np.float64).reshape(-1)
    d, s, cos_l, ndh = design_rows(x, n, flash, cam, intensity, p)
    ok = cos_l > 0  # design_rows' valid set: cos_l is n·l there and 0 elsewhere
    dl = flash - x
    dv = cam - x
    d2 = np.einsum("rk,rk->r", dl, dl)
    v2 = np.einsum("rk,rk->r", dv, dv)
    il = 1.0 / np.sqrt(np.where(d2 > 0, d2, 1.0))
    iv = 1.0 / np.sqrt(np.where(v2 > 0, v2, 1.0))
    l = dl * il[:, None]
    h = l + dv * iv[:, None]
    hn = np.sqrt(np.einsum("rk,rk->r", h, h))
    h /= np.where(hn > 0, hn, 1.0)[:, None]
    E = np.where(ok, intensity * (il * il), 0.0)
    pos = ndh > 0
    with np.errstate(divide="ignore"):
        logh = np.log(np.where(pos, ndh, 1.0))
    dd = (E / np.pi)[:, None] * l
    dsc = np.where(pos[:, None], np.exp(logh[:, None] * (p - 1.0)) * (E[:, None] * blinn_phong_norm(p) * p), 0.0)
    ds = dsc[:, :, None] * h[:, None, :]  # (R, K, 3)
    return d, s, cos_l, ndh, dd, ds


def gram_conditioning(G: np.ndarray) -> np.ndarray:
    """(N,) ``λ_min/λ_max`` of the unit-diagonal normalisation of (N, m, m) Gram matrices (0 if a diagonal is 0)."""
    diag = np.einsum("nii->ni", G)
    ok = np.all(diag > 0, axis=1) & np.all(np.isfinite(G), axis=(1, 2))
    s = 1.0 / np.sqrt(np.where(diag > 0, diag, 1.0))
    Gn = G * s[:, :, None] * s[:, None, :]
    Gn = np.where(ok[:, None, None], Gn, np.eye(G.shape[1]))
    ev = np.linalg.eigvalsh(Gn)
    rc = np.clip(ev[:, 0], 0.0, None) / np.maximum(ev[:, -1], 1e-300)
    return np.where(ok, rc, 0.0)


def design_gram(des: Design) -> np.ndarray:
    """(N, 1+K, 1+K) Gram matrix ``Σ_j a_j a_jᵀ`` of ``a_j = (d_j, s_j1..s_jK)``."""
    A = np.concatenate([des.diffuse[..., None], des.lobes], axis=-1)
    return np.einsum("npa,npb->nab", A, A)


@dataclass
class Conditioning:
    """Conditioning maps: ``conditioning (S,S)``, ``observability (K,S,S)``, ``obs_count (S,S)`` (valid pairs)."""

    conditioning: np.ndarray
    observability: np.ndarray
    obs_count: np.ndarray
    exponents: np.ndarray


def conditioning(position: np.ndarray, normal: np.ndarray, cam_centers: np.ndarray, flash_pos: np.ndarray,
                 flash_intensity: np.ndarray, pair_view: np.ndarray, pair_flash: np.ndarray,
                 observed: np.ndarray, exponents: Sequence[float] = DEFAULT_EXPONENTS,
                 mask: np.ndarray | None = None, mirror_weight: float = 0.0,
                 chunk: int = DEFAULT_CHUNK) -> Conditioning:
    """Per-texel conditioning of the 3+K unknowns (definition in the module docstring).

    Args:
        position, normal: (S, S, 3) UV maps. observed: (P, S, S) bool. mask: (S, S) bool or None (all).
        mirror_weight: pool each texel's Gram matrix with its mirror texel's, weighted (0 = off).
    Returns:
        :class:`Conditioning`; texels outside ``mask`` get conditioning 0, observability 0, count 0.
    """
    pos = np.asarray(position)
    if pos.ndim != 3 or pos.shape[0] != pos.shape[1] or pos.shape[2] != 3:
        raise ReflectmmError(f"conditioning: position must be (S,S,3), got {pos.shape}")
    S = pos.shape[0]
    obs = np.asarray(observed, dtype=bool)
    P = obs.shape[0]
    if obs.shape != (P, S, S):
        raise ReflectmmError(f"conditioning: observed must be (P,{S},{S}), got {obs.shape}")
    p = np.asarray(exponents, dtype=np.float64).reshape(-1)
    K = p.size
    m = np.ones((S, S), bool) if mask is None else np.asarray(mask, dtype=bool)
    idx = np.flatnonzero(m.reshape(-1))
    pos_f = pos.reshape(-1, 3)
    nrm_f = np.asarray(normal).reshape(-1, 3)
    obs_f = obs.reshape(P, -1)
    G = np.zeros((S * S, 1 + K, 1 + K))
    vis = np.zeros((S * S, K))
    cnt = np.zeros(S * S, np.int32)
    for sl in iter_chunks(idx.size, chunk):
        t = idx[sl]
        des = design_columns(pos_f[t], nrm_f[t], cam_centers, flash_pos, flash_intensity, pair_view, pair_flash,
                             p, obs_f[:, t].T)
        G[t] = design_gram(des)
        with np.errstate(under="ignore"):
            vis[t] = np.max(np.where(des.valid[..., None], des.ndh[..., None] ** p, 0.0), axis=1)
        cnt[t] = des.valid.sum(1)
    if mirror_weight:
        G = G + float(mirror_weight) * G[mirror_index(S)]
    rc = np.zeros(S * S)
    rc[idx] = gram_conditioning(G[idx])
    return Conditioning(rc.reshape(S, S), vis.T.reshape(K, S, S), cnt.reshape(S, S), p)


def check_observations(obs: Mapping[str, np.ndarray], path=None) -> int:
    """Validate a uv-observations mapping (shapes, finiteness); return S. Raises ReflectmmError naming the problem."""
    need = ("position", "normal", "mask", "cam_centers", "flash_pos", "flash_intensity", "pair_view",
            "pair_flash", "radiance", "observed")
    missing = [k for k in need if k not in obs]
    if missing:
        raise ReflectmmError(f"uv-observations is missing arrays: {', '.join(missing)}", path)
    pos = np.asarray(obs["position"])
    if pos.ndim != 3 or pos.shape[0] != pos.shape[1] or pos.shape[2] != 3:
        raise ReflectmmError(f"uv-observations 'position' must be (S,S,3), got {pos.shape}", path)
    S = pos.shape[0]
    P = np.asarray(obs["pair_view"]).shape[0]
    V = np.asarray(obs["cam_centers"]).shape[0]
    F = np.asarray(obs["flash_pos"]).shape[0]
    shapes = {"normal": (S, S, 3), "mask": (S, S), "radiance": (P, S, S, 3), "observed": (P, S, S),
              "pair_flash": (P,), "cam_centers": (V, 3), "flash_pos": (F, 3), "flash_intensity": (F,)}
    for k, shp in shapes.items():
        if np.asarray(obs[k]).shape != shp:
            raise ReflectmmError(f"uv-observations '{k}' has shape {np.asarray(obs[k]).shape}, expected {shp}", path)
    pv = np.asarray(obs["pair_view"])
    pf = np.asarray(obs["pair_flash"])
    if P and (pv.min() < 0 or pv.max() >= V or pf.min() < 0 or pf.max() >= F):
        raise ReflectmmError(f"uv-observations pair_view/pair_flash index out of range (V={V}, F={F})", path)
    for k in ("position", "normal", "cam_centers", "flash_pos", "flash_intensity"):
        a = np.asarray(obs[k], dtype=np.float64)
        m = np.asarray(obs["mask"], bool) if k in ("position", "normal") else None
        bad = ~np.isfinite(a) if m is None else (~np.isfinite(a)) & m[..., None]
        if bad.any():
            raise ReflectmmError(f"uv-observations '{k}' has {int(bad.sum())} NaN/inf values", path)
    fi = np.asarray(obs["flash_intensity"], dtype=np.float64)
    if np.any(fi <= 0):
        raise ReflectmmError(f"uv-observations 'flash_intensity' must be > 0, got {fi.tolist()}", path)
    rad = np.asarray(obs["radiance"])
    obsm = np.asarray(obs["observed"], bool)
    bad = ~np.isfinite(rad) & obsm[..., None]
    if bad.any():
        raise ReflectmmError(f"uv-observations 'radiance' has {int(bad.sum())} NaN/inf values in observed texels",
                             path)
    if P == 0:
        raise ReflectmmError("uv-observations has no observed texel (no view-flash pair): nothing to fit; check "
                             "unwrap-uv's --views and --flashes and the geometry", path)
    seen = rad[obsm]
    neg = int((seen < -NEGATIVE_RADIANCE_TOL * max(float(np.abs(seen).max()), 1e-12)).sum()) if seen.size else 0
    if neg:
        raise ReflectmmError(f"uv-observations 'radiance' has {neg} negative values in observed texels (linear "
                             "radiance is ≥ 0): a capture in another encoding, or a corrupt file", path)
    return S


#: Observed radiance below −this × the largest observed magnitude is refused (linear radiance is ≥ 0; a little
#: below 0 is left for noise that a camera pipeline kept).
NEGATIVE_RADIANCE_TOL = 0.01


def conditioning_from_obs(obs: Mapping[str, np.ndarray], exponents: Sequence[float] = DEFAULT_EXPONENTS,
                          mirror_weight: float = 0.0, chunk: int = DEFAULT_CHUNK,
                          flash_intensity=None) -> Conditioning:
    """:func:`conditioning` of a uv-observations mapping (artifact arrays)."""
    F = np.asarray(obs["flash_pos"]).shape[0]
    I = pair_irradiance(obs["flash_intensity"], F, flash_intensity)
    return conditioning(obs["position"], obs["normal"], obs["cam_centers"], obs["flash_pos"], I,
                        obs["pair_view"], obs["pair_flash"], obs["observed"], exponents, mask=obs["mask"],
                        mirror_weight=mirror_weight, chunk=chunk)
