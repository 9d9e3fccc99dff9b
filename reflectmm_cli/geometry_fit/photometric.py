"""Photometric term: per-view order-2 SH lighting × per-vertex albedo against bilinearly sampled images."""

from __future__ import annotations

import math

import numpy as np
import torch
import torch.nn.functional as F

from reflectmm_cli.geometry.camera import project
from reflectmm_cli.shading import lambert_sh_coeffs, sh_basis

SH_ORDER = 2
N_SH = (SH_ORDER + 1) ** 2


def sh_kernel(dtype=torch.float64, device="cpu") -> torch.Tensor:
    """(9,) clamped-cosine factor A_l / π per SH coefficient (order 2): diffuse shading = c · Y(n) @ (k ⊙ K_lm)."""
    A = lambert_sh_coeffs(SH_ORDER)
    k = np.concatenate([[A[l]] * (2 * l + 1) for l in range(SH_ORDER + 1)]) / math.pi
    return torch.as_tensor(k, dtype=dtype, device=device)


def sample_images(images: torch.Tensor, uv: torch.Tensor) -> torch.Tensor:
    """Bilinear samples of (V, C, H, W) images at (V, M, 2) pixel coordinates → (V, M, C).

    Pixel centres are at integer coordinates (docs/pipeline.md), i.e. ``align_corners=True`` in
    ``grid_sample``'s normalised coordinates; outside the image the border value is returned (callers mask
    those samples out).
    """
    V, C, H, W = images.shape
    gx = uv[..., 0] * (2.0 / max(W - 1, 1)) - 1.0
    gy = uv[..., 1] * (2.0 / max(H - 1, 1)) - 1.0
    grid = torch.stack([gx, gy], -1)[:, None]  # (V, 1, M, 2)
    out = F.grid_sample(images, grid, mode="bilinear", padding_mode="border", align_corners=True)
    return out[:, :, 0].transpose(1, 2)


def inside_image(uv: np.ndarray, width: int, height: int, margin: float = 1.0) -> np.ndarray:
    return ((uv[..., 0] >= margin) & (uv[..., 0] <= width - 1 - margin)
            & (uv[..., 1] >= margin) & (uv[..., 1] <= height - 1 - margin))


def shade(normals: torch.Tensor, albedo: torch.Tensor, sh: torch.Tensor, kernel: torch.Tensor) -> torch.Tensor:
    """Lambertian SH shading: (M, 3) unit normals, (M, 3) albedo, (V, 9, 3) SH radiance coefficients
    → (V, M, 3) linear radiance ``c/π · Σ_l A_l Σ_m K_lm Y_lm(n)``."""
    Y = sh_basis(normals, SH_ORDER, normalize=False)  # (M, 9)
    E = torch.einsum("mk,vkc->vmc", Y * kernel, sh)
    return albedo[None] * E


def solve_lighting(Y: np.ndarray, albedo: np.ndarray, obs: np.ndarray, vis: np.ndarray, kernel: np.ndarray,
                   ridge: float = 1e-6) -> np.ndarray:
    """Least-squares SH lighting per view and channel: min Σ_m vis (c_m · (Y_m k) · L − obs_m)².

    Y (M, 9), albedo (M, 3), obs (V, M, 3), vis (V, M) → (V, 9, 3).
    """
    V = obs.shape[0]
    out = np.zeros((V, N_SH, 3))
    Yk = Y * kernel
    for v in range(V):
        w = vis[v]
        if w.sum() < N_SH:
            continue
        for c in range(3):
            A = Yk[w] * albedo[w, c:c + 1]
            b = obs[v, w, c]
            AtA = A.T @ A
            out[v, :, c] = np.linalg.solve(AtA + ridge * np.trace(AtA) / N_SH * np.eye(N_SH), A.T @ b)
    return out


def solve_albedo(Y: np.ndarray, sh: np.ndarray, obs: np.ndarray, vis: np.ndarray, kernel: np.ndarray,
                 fallback: np.ndarray) -> np.ndarray:
    """Per-vertex least-squares albedo given the lighting: c = Σ_v vis E obs / Σ_v vis E² (fallback where unseen)."""
    E = np.einsum("mk,vkc->vmc", Y * kernel, sh)  # (V, M, 3)
    w = vis[..., None].astype(np.float64)
    num = (w * E * obs).sum(0)
    den = (w * E * E).sum(0)
    ok = den > 1e-12 * max(float(den.max()), 1e-300)
    out = np.where(ok, num / np.where(ok, den, 1.0), fallback)
    return np.clip(out, 0.0, None)


def charbonnier(x: torch.Tensor, eps: float) -> torch.Tensor:
    """Smooth L1: sqrt(x² + ε²) − ε."""
    return torch.sqrt(x * x + eps * eps) - eps


def photometric_loss(vertices: torch.Tensor, normals: torch.Tensor, sample: torch.Tensor, vis: torch.Tensor,
                     K: torch.Tensor, R: torch.Tensor, t: torch.Tensor, images: torch.Tensor,
                     albedo: torch.Tensor, sh: torch.Tensor, kernel: torch.Tensor, scale: float,
                     eps: float = 0.02) -> tuple[torch.Tensor, torch.Tensor]:
    """Mean Charbonnier photometric residual over visible (view, vertex) pairs.

    Args:
        vertices, normals: (N, 3) current mesh; sample: (M,) vertex ids; vis: (V, M) float weights (0/1).
        K, R: (V, 3, 3); t: (V, 3); images: (V, 3, H, W) linear; albedo (M, 3); sh (V, 9, 3).
        scale: intensity scale the residuals are divided by (so the weight does not depend on exposure).
    Returns:
        (loss, residual (V, M, 3) in linear units).
    """
    p = vertices[sample]
    uv, _ = project(p[None].expand(K.shape[0], -1, -1), K, R, t)
    obs = sample_images(images, uv)
    pred = shade(normals[sample], albedo, sh, kernel)
    r = pred - obs
    rho = charbonnier(r / scale, eps).sum(-1)
    loss = (rho * vis).sum() / vis.sum().clamp_min(1.0)
    return loss, r


def point_irradiance(points: torch.Tensor, normals: torch.Tensor, light_pos: torch.Tensor,
                     light_int: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Irradiance of point lights on surface points: ``I · max(n·l, 0) / d²``, elementwise with broadcasting.

    points, normals (..., 3); light_pos (..., 3); light_int (...) radiant intensity → (E (...), unit l (..., 3)).
    E.g. (M, 3) points against (P, 3) lights: pass ``points[None]``, ``normals[None]``, ``light_pos[:, None]``,
    ``light_int[:, None]`` for (P, M).
    """
    d = light_pos - points
    r2 = (d * d).sum(-1)
    r = torch.sqrt(r2)
    cos = ((normals * d).sum(-1) / r).clamp_min(0.0)
    return light_int * cos / r2, d / r[..., None]


def gather_bilinear(images: torch.Tensor, pair: torch.Tensor, uv: torch.Tensor) -> torch.Tensor:
    """Bilinear samples of channels-last images (P, h, w, C) at (K, 2) pixel coordinates of image ``pair`` (K,)
    → (K, C) in ``uv``'s dtype; pixel centres at integer coordinates, clamped at the border (the convention of
    :func:`sample_images`).  Differentiable in ``uv``; only the K samples are touched."""
    P, h, w, C = images.shape
    flat = images.reshape(P * h * w, C)
    u = uv[:, 0].clamp(0.0, w - 1.0)
    v = uv[:, 1].clamp(0.0, h - 1.0)
    x0 = torch.floor(u).clamp(max=w - 2 if w > 1 else 0)
    y0 = torch.floor(v).clamp(max=h - 2 if h > 1 else 0)
    fx = (u - x0)[:, None]
    fy = (v - y0)[:, None]
    base = pair * (h * w) + y0.long() * w + x0.long()
    dx = 1 if w > 1 else 0
    dy = w if h > 1 else 0

    def at(off):
        return flat.index_select(0, base + off).to(uv.dtype)

    top = at(0) * (1 - fx) + at(dx) * fx
    bottom = at(dy) * (1 - fx) + at(dy + dx) * fx
    return top * (1 - fy) + bottom * fy


def flash_loss(vertices: torch.Tensor, normals: torch.Tensor, sample: torch.Tensor, weight: torch.Tensor,
               K: torch.Tensor, R: torch.Tensor, t: torch.Tensor, images: torch.Tensor, pair_view: torch.Tensor,
               light_pos: torch.Tensor, light_int: torch.Tensor, scale: float, eps: float = 0.02,
               residual: bool = True, index: tuple[torch.Tensor, torch.Tensor] | None = None
               ) -> tuple[torch.Tensor, torch.Tensor | None, torch.Tensor]:
    """Point-light Lambertian photometric term of flash images, the albedo eliminated per vertex.

    Each (view, flash) pair ``p`` is an image of the surface lit by one point light.  The Lambertian prediction
    of vertex ``m`` is ``c_m/π · E_pm`` with ``E = I·max(n·l, 0)/d²``; the albedo ``c_m`` (per channel) is the
    weighted least-squares value over the pairs that see the vertex, ``c/π = Σ_p w E O / Σ_p w E²``, computed
    inside the loss (variable projection), so the term measures only how well the *shape* explains the change of
    brightness between flashes — photometric stereo with known lights — and the image positions between views.

    Args:
        vertices, normals: (N, 3) current (sub-)mesh; sample (M,) vertex ids; weight (P, M) ≥ 0: 0 leaves a sample out
            (camera and flash visibility, no highlight, not saturated), else its weight in the albedo and the loss
            (1, or a pair's view weight).
        K, R (V, 3, 3), t (V, 3): cameras (K in the images' pixel frame); images (P, h, w, 3) linear
            (channels last, any float dtype: only the samples are converted);
            pair_view (P,) view index of each pair; light_pos (P, 3) and light_int (P,) the pair's flash.
        scale: intensity scale of the residuals; eps: Charbonnier ε (relative to ``scale``).
        residual: also return the residuals (else None: the optimiser's closure needs only the loss).
        index: ``torch.nonzero(weight > 0, as_tuple=True)`` when the caller holds it (a weight fixed over many
            evaluations); computed here otherwise.
    Returns:
        (loss, residual (P, M, 3) — 0 where the weight is 0, albedo/π (M, 3)).
    Only the (pair, vertex) samples of non-zero weight are evaluated.
    """
    p = vertices[sample]
    n = normals[sample]
    uv, _ = project(p[None].expand(K.shape[0], -1, -1), K, R, t)  # (V, M, 2)
    # only the samples that count: (pair, vertex) index lists
    sp, sm = torch.nonzero(weight > 0, as_tuple=True) if index is None else index
    w = weight[sp, sm]
    obs = gather_bilinear(images, sp, uv[pair_view[sp], sm])  # (S, 3)
    E, _ = point_irradiance(p[sm], n[sm], light_pos[sp], light_int[sp])  # (S,)
    M = p.shape[0]
    wE = w * E
    num = torch.zeros(M, 3, dtype=p.dtype, device=p.device).index_add(0, sm, wE[:, None] * obs)
    den = torch.zeros(M, dtype=p.dtype, device=p.device).index_add(0, sm, wE * E)[:, None]
    ok = den > 0
    c = torch.where(ok, num / torch.where(ok, den, torch.ones_like(den)), torch.zeros_like(num))
    r = c[sm] * E[:, None] - obs
    loss = (charbonnier(r / scale, eps).sum(-1) * w).sum() / w.sum().clamp_min(1.0)
    if not residual:
        return loss, None, c
    dense = torch.zeros(*weight.shape, 3, dtype=r.dtype, device=r.device)
    return loss, dense.index_put((sp, sm), r), c
