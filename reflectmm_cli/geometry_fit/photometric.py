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
