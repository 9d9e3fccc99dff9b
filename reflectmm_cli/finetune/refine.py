"""Per-image analysis-by-synthesis: β, γ and z fitted to each image by Levenberg–Marquardt, the model fixed.

Shapes: B images, P_b face pixels of image b (S_b of them skin), M reflectance coefficients, N_L light coefficients,
K lobes, n = (L+1)² SH coefficients per channel. β and γ are in units of σ (as everywhere in finetune/).

Objective of image b, the finetuning losses (finetune/losses.py) in their least-squares form:

    E_b(β, γ, z) = 1/(3 S_b) Σ_{p ∈ skin} Σ_c ρ(I_pc − T_pc)  +  w_coef (‖β‖² + ‖γ‖²)
                   + w_light · 1/(3n) Σ_{c,j} (K_cj − K̄_j)²

with ``ρ(x) = x²`` (``loss="l2"``) or the L1 norm of training reached by iteratively reweighted least squares
(``loss="l1"``: ρ(x) ≈ |x| with weights 1/max(|x|, ε) refreshed every iteration), T the linear target, and the
image formation of the shading contract (docs/shading.md) evaluated on the shard's G-buffer:

    K_c  = z_c (μ_c + Σ_k γ_k σ_k ℓ_k,c)                                   lighting (model/light.py)
    a_p  = ā_p + Σ_k β_k σ_k a_k,p,   w_p = w̄_p + Σ_k β_k σ_k w_k,p         reflectance at the pixel
    I_pc = a_pc · (Y_d(n_p) · K_c) + Σ_i w_pi · (Y_s,i(r_p) · K_c)

where ``Y_d(n) = A_l/π · Y_lm(n)`` and ``Y_s,i(r) = B_l^i · Y_lm(r)`` (0 where n·v ≤ 0) are fixed per pixel: the
light transport of the pixel. I is linear in β for a fixed light and linear in K for a fixed reflectance, so the
Jacobian is exact and cheap (no automatic differentiation):

    ∂I_pc/∂β_k = σ_k (D_pc a_k,pc + Σ_i S_i,pc w_k,pi),   D_pc = Y_d(n_p)·K_c,  S_i,pc = Y_s,i(r_p)·K_c
    ∂I_pc/∂γ_k = z_c σ_k (a_pc Y_d(n_p)·ℓ_k,c + W_p·ℓ_k,c),  W_p = Σ_i w_pi Y_s,i(r_p)
    ∂I_pc/∂z_c = a_pc Y_d(n_p)·x_c + W_p·x_c,                x_c = μ_c + Σ_k γ_k σ_k ℓ_k,c

Each image is an independent problem of M + N_L + 3 unknowns (about 170 with the paper's sizes); its normal
equations are formed in float64 and solved with an adaptive damping ``λ diag(JᵀJ)`` (Marquardt). A step is kept only
if it lowers E_b, so E_b never increases. The result is deterministic (no sampling; fixed summation order).
"""
from __future__ import annotations

import logging
import math
from dataclasses import dataclass, field

import numpy as np

from reflectmm_cli.errors import ReflectmmError

log = logging.getLogger("reflectmm")

__all__ = ["RefineConfig", "RefineResult", "PixelTransport", "pixel_transport", "refine_batch", "image_objective"]

LOSSES = ("l2", "l1")


@dataclass(frozen=True)
class RefineConfig:
    """Options of the per-image refinement.

    Attributes:
        iterations: Levenberg–Marquardt iterations per image (a rejected step counts as one).
        loss: ``"l2"`` squared error, or ``"l1"`` the training's L1 by IRLS.
        w_coef: weight of the coefficient prior ‖β‖² + ‖γ‖² (β, γ in units of σ).
        w_light: weight of the monochrome-light term (mean over the 3n lighting coefficients).
        damping: initial Marquardt damping λ (relative to diag(JᵀJ)).
        tol: stop an image when a kept step lowers E_b by less than this fraction.
        l1_eps: IRLS floor ε of |residual| (linear radiance) for ``loss="l1"``.
        max_pixels: at most this many skin pixels per image enter the fit (an even stride over the skin pixels;
            0 = all). The rendered layers always cover every face pixel.
    """

    iterations: int = field(default=12, metadata={"help": "Levenberg-Marquardt iterations per image.",
                                                  "range": (0, 1000)})
    loss: str = field(default="l2", metadata={"help": "Data term: squared error, or the training's L1 by IRLS.",
                                              "choices": LOSSES})
    w_coef: float = field(default=1e-5, metadata={"help": "Coefficient-prior weight (beta, gamma in units of sigma)."})
    w_light: float = field(default=1e-3, metadata={"help": "Monochrome-light weight."})
    damping: float = field(default=1e-3, metadata={"help": "Initial Marquardt damping (relative to diag(J^T J))."})
    tol: float = field(default=1e-6, metadata={"help": "Stop when a step lowers the objective by less than this "
                                                       "fraction."})
    l1_eps: float = field(default=1e-3, metadata={"help": "IRLS floor of |residual| (loss l1)."})
    max_pixels: int = field(default=2000, metadata={"help": "Skin pixels per image in the fit (an even stride; 0 = "
                                                           "all); the renders cover every face pixel.",
                                                   "range": (0, None)})

    def __post_init__(self):
        if self.loss not in LOSSES:
            raise ReflectmmError(f"refine: loss must be one of {', '.join(LOSSES)}, got {self.loss!r}")
        if int(self.iterations) < 0 or int(self.max_pixels) < 0:
            raise ReflectmmError("refine: iterations and max_pixels must be ≥ 0")
        for k in ("w_coef", "w_light", "damping", "tol", "l1_eps"):
            v = float(getattr(self, k))
            if not (math.isfinite(v) and v >= 0):
                raise ReflectmmError(f"refine: {k} must be finite and ≥ 0, got {v}")
        if self.loss == "l1" and not self.l1_eps > 0:
            raise ReflectmmError("refine: l1_eps must be > 0 with loss l1")


@dataclass
class RefineResult:
    """Refined coefficients (torch, on the input's device) and the per-image trace (numpy).

    Attributes:
        beta: (B, M); gamma: (B, N_L); z: (B, 3).
        objective_start, objective_end: (B,) E_b before and after.
        steps: (B,) kept steps per image.
    """

    beta: "torch.Tensor"  # noqa: F821
    gamma: "torch.Tensor"  # noqa: F821
    z: "torch.Tensor"  # noqa: F821
    objective_start: np.ndarray
    objective_end: np.ndarray
    steps: np.ndarray


@dataclass
class PixelTransport:
    """The fixed light transport of one image's pixels (torch, one dtype).

    Attributes:
        Yd: (P, n) ``A_l/π Y_lm(n_p)`` (diffuse irradiance per unit lighting coefficient).
        Ys: (K, P, n) ``B_l^i Y_lm(r_p)``, 0 where n·v ≤ 0 (lobe i per unit lighting coefficient).
    """

    Yd: "torch.Tensor"  # noqa: F821
    Ys: "torch.Tensor"  # noqa: F821


def pixel_transport(normal, view, exponents, order: int) -> PixelTransport:
    """:class:`PixelTransport` of pixels with unit normals ``normal`` and view directions ``view`` (P, 3) torch,
    lobes of ``exponents`` (K,), lighting up to SH order ``order`` — the terms of docs/shading.md, built from the
    project's SH basis and Funk–Hecke coefficients (shading/sh.py)."""
    import torch

    from reflectmm_cli.shading.sh import blinn_phong_sh_coeffs, lambert_sh_coeffs, sh_basis

    if normal.ndim != 2 or normal.shape[-1] != 3 or view.shape != normal.shape:
        raise ReflectmmError(f"refine: normal and view must be (P, 3), got {tuple(normal.shape)} and "
                             f"{tuple(view.shape)}")
    dt, dev = normal.dtype, normal.device
    nrm = torch.nn.functional.normalize(normal, dim=-1)
    v = torch.nn.functional.normalize(view, dim=-1)
    ndv = (nrm * v).sum(-1, keepdim=True)
    r = 2.0 * ndv * nrm - v
    lvl = np.repeat(np.arange(order + 1), 2 * np.arange(order + 1) + 1)
    A = torch.as_tensor(lambert_sh_coeffs(order)[lvl] / math.pi, dtype=dt, device=dev)
    p = np.asarray(exponents.detach().cpu() if hasattr(exponents, "detach") else exponents, np.float64).reshape(-1)
    Bc = torch.as_tensor(blinn_phong_sh_coeffs(p, order)[:, lvl], dtype=dt, device=dev)  # (K, n)
    Yd = sh_basis(nrm, order, normalize=False) * A
    Yr = sh_basis(r, order, normalize=False) * (ndv > 0).to(dt)
    return PixelTransport(Yd=Yd, Ys=Yr[None] * Bc[:, None, :])


@dataclass
class _Image:
    """One image's fixed data: the reflectance bases and light bases at its fitted pixels, the target."""

    a0: "torch.Tensor"  # (S, 3) mean albedo
    Ba: "torch.Tensor"  # (M, S, 3) σ-scaled albedo bases
    w0: "torch.Tensor"  # (S, K)
    Bw: "torch.Tensor"  # (M, S, K)
    tr: PixelTransport  # (S pixels)
    YdL: "torch.Tensor"  # (S, N_L, 3): Y_d · ℓ_k,c
    target: "torch.Tensor"  # (S, 3)


@dataclass
class _Light:
    """The light model as torch tensors: μ (3, n), σ-scaled bases ℓ (N_L, 3, n)."""

    mu: "torch.Tensor"  # noqa: F821
    L: "torch.Tensor"  # noqa: F821


@dataclass
class _State:
    beta: "torch.Tensor"  # noqa: F821
    gamma: "torch.Tensor"  # noqa: F821
    z: "torch.Tensor"  # noqa: F821
    n_beta: int = field(default=0)

    def vector(self):
        import torch

        return torch.cat([self.beta, self.gamma, self.z])

    def moved(self, delta) -> "_State":
        m, k = self.beta.numel(), self.gamma.numel()
        return _State(self.beta + delta[:m], self.gamma + delta[m:m + k], self.z + delta[m + k:])


def _light_tensors(light, n_light: int, dt, dev) -> _Light:
    import torch

    n = light.n_coeffs
    mu = torch.as_tensor(np.asarray(light.mean, np.float64).reshape(3, n), dtype=dt, device=dev)
    L = np.asarray(light.bases[:n_light], np.float64) * np.asarray(light.sigma[:n_light], np.float64)[:, None]
    return _Light(mu=mu, L=torch.as_tensor(L.reshape(n_light, 3, n), dtype=dt, device=dev))


def _interp_bases(params, vert_ids, bary, n_beta: int):
    """Mean and σ-scaled bases of the model at pixels: ``(a0 (P,3), Ba (M,P,3), w0 (P,K), Bw (M,P,K))``."""
    am, ab, wm, wb = params.effective()
    ids = vert_ids.reshape(-1)
    P = vert_ids.shape[0]
    bw = bary.to(am.dtype)

    def interp(table):  # (..., V, C) → (..., P, C)
        g = table.index_select(-2, ids)
        g = g.reshape(g.shape[:-2] + (P, 3, g.shape[-1]))
        return (g * bw[..., None]).sum(-2)

    s = params.sigma[:n_beta].to(am.dtype)
    with_grad_off = [x.detach() for x in (interp(am), interp(ab[:n_beta]), interp(wm), interp(wb[:n_beta]))]
    a0, Ba, w0, Bw = with_grad_off
    return a0, Ba * s[:, None, None], w0, Bw * s[:, None, None]


def _forward(img: _Image, light: _Light, st: _State):
    """Render the fitted pixels: ``(I (S,3), a (S,3), w (S,K), x (3,n), K (3,n), D (S,3), S_i (K,S,3),
    W (S,n))``."""
    import torch

    x = light.mu + torch.einsum("k,kcn->cn", st.gamma, light.L)
    K = st.z[:, None] * x
    a = img.a0 + torch.einsum("k,kpc->pc", st.beta, img.Ba)
    w = img.w0 + torch.einsum("k,kpi->pi", st.beta, img.Bw)
    D = img.tr.Yd @ K.T  # (S, 3)
    Si = img.tr.Ys @ K.T  # (K, S, 3)
    W = torch.einsum("pi,ipn->pn", w, img.tr.Ys)  # (S, n)
    I = a * D + torch.einsum("pi,ipc->pc", w, Si)  # noqa: E741
    return I, a, w, x, K, D, Si, W


def _mono(K):
    return K - K.mean(0, keepdim=True)


def _energy(img: _Image, light: _Light, st: _State, cfg: RefineConfig, irls=None) -> float:
    """E_b (float) at the state; ``irls`` (S,3) weights replace ρ by the weighted square (the IRLS surrogate)."""
    I = _forward(img, light, st)[0]  # noqa: E741
    r = I - img.target
    S = max(r.shape[0], 1)
    if cfg.loss == "l1" and irls is None:
        data = r.abs().sum() / (3 * S)
    else:
        data = ((r * r) if irls is None else (irls * r * r)).sum() / (3 * S)
    K = st.z[:, None] * (light.mu + (st.gamma[:, None, None] * light.L).sum(0))
    prior = (st.beta * st.beta).sum() + (st.gamma * st.gamma).sum()
    e = data + cfg.w_coef * prior + cfg.w_light * (_mono(K) ** 2).mean()
    return float(e)


def _normal_equations(img: _Image, light: _Light, st: _State, cfg: RefineConfig, irls):
    """``(H (U,U), g (U,))`` float64 of the (weighted) least-squares objective at the state, U = M + N_L + 3."""
    import torch

    I, a, w, x, K, D, Si, W = _forward(img, light, st)  # noqa: E741
    S = I.shape[0]
    # photometric Jacobian, (S·3, U): columns β | γ | z
    Jb = D[None] * img.Ba + torch.einsum("ipc,kpi->kpc", Si, img.Bw)  # (M, S, 3)
    WL = torch.einsum("pn,kcn->pkc", W, light.L)  # (S, N_L, 3)
    Jg = (a[:, None, :] * img.YdL + WL) * st.z[None, None, :]  # (S, N_L, 3)
    Dx = img.tr.Yd @ x.T  # (S, 3)
    Jz_diag = a * Dx + W @ x.T  # (S, 3): ∂I_pc/∂z_c
    Jz = torch.diag_embed(Jz_diag)  # (S, 3, 3) [p, c, c']
    J = torch.cat([Jb.permute(1, 2, 0), Jg.permute(0, 2, 1), Jz], -1).reshape(S * 3, -1).double()
    r = (I - img.target).reshape(-1).double()
    wts = (irls.reshape(-1).double() if irls is not None else torch.ones_like(r)) / (3 * max(S, 1))
    Jw = J * wts[:, None]
    H = J.T @ Jw
    g = Jw.T @ r
    m, k = st.beta.numel(), st.gamma.numel()
    # coefficient prior
    idx = torch.arange(m + k, device=H.device)
    H[idx, idx] += cfg.w_coef
    g[:m + k] += cfg.w_coef * torch.cat([st.beta, st.gamma]).double()
    # monochrome light: residual (K_cj − K̄_j), K_cj = z_c x_cj
    n = K.shape[1]
    P3 = torch.eye(3, dtype=K.dtype, device=K.device) - 1.0 / 3.0  # centring over the channels
    dK_dg = light.L * st.z[None, :, None]  # (N_L, 3, n)
    dK_dz = torch.diag_embed(x.T).permute(1, 0, 2)  # (3, n, 3) → [c, j, c'] … as (c, j, c')
    Jm_g = torch.einsum("dc,kcn->dnk", P3, dK_dg)  # (3, n, N_L)
    Jm_z = torch.einsum("dc,cnz->dnz", P3, dK_dz)  # (3, n, 3)
    Jm = torch.cat([torch.zeros((3, n, m), dtype=K.dtype, device=K.device), Jm_g, Jm_z], -1).reshape(3 * n, -1)
    Jm = Jm.double()
    rm = _mono(K).reshape(-1).double()
    wm = cfg.w_light / (3 * n)
    H += wm * (Jm.T @ Jm)
    g += wm * (Jm.T @ rm)
    return H, g, r


def _irls_weights(img: _Image, light: _Light, st: _State, cfg: RefineConfig):
    """IRLS weights of the L1 data term: ``1/(2 max(|r|, ε))`` so that the weighted square has |r|'s gradient."""
    if cfg.loss != "l1":
        return None
    r = _forward(img, light, st)[0] - img.target
    return 0.5 / r.abs().clamp_min(cfg.l1_eps)


def image_objective(img: _Image, light: _Light, st: _State, cfg: RefineConfig) -> float:
    """E_b of the configured loss (module docstring)."""
    return _energy(img, light, st, cfg)


def _refine_one(img: _Image, light: _Light, st: _State, cfg: RefineConfig, name: str):
    """Levenberg–Marquardt on one image; returns ``(state, E_start, E_end, kept steps)``."""
    import torch

    e0 = e = _energy(img, light, st, cfg)
    if img.target.shape[0] == 0:  # nothing to fit: the start is kept, and said
        log.warning("refine: image %s has no skin pixel to fit (all saturated, or outside the face): not refined, "
                    "its start kept", name)
        return st, e0, e0, 0
    if not math.isfinite(e0):
        raise ReflectmmError(f"refine: image {name}: the objective is not finite at the start (NaN/inf in the "
                             f"model, the light model or the image)")
    lam = cfg.damping
    kept = 0
    it = 0
    while it < cfg.iterations:
        irls = _irls_weights(img, light, st, cfg)
        H, g, _ = _normal_equations(img, light, st, cfg, irls)
        if not (torch.isfinite(H).all() and torch.isfinite(g).all()):
            raise ReflectmmError(f"refine: image {name}: the normal equations became non-finite (diverged)")
        diag = H.diagonal().clamp_min(1e-12)
        improved = False
        while it < cfg.iterations:
            it += 1
            A = H + lam * torch.diag(diag)
            try:
                delta = -torch.linalg.solve(A, g)
            except RuntimeError:
                lam *= 10.0
                continue
            cand = st.moved(delta.to(st.beta.dtype))
            ec = _energy(img, light, cand, cfg)
            if math.isfinite(ec) and ec < e:
                rel = (e - ec) / max(abs(e), 1e-30)
                st, e = cand, ec
                lam = max(lam * 0.3, 1e-9)
                kept += 1
                improved = True
                break
            lam *= 10.0
            if lam > 1e10:
                break
        if not improved or rel < cfg.tol:
            break
    if not math.isfinite(e):
        raise ReflectmmError(f"refine: image {name}: the objective became non-finite")
    return st, e0, e, kept


def refine_batch(params, light, gb, beta, gamma, z, config: RefineConfig | None = None, *, names=None,
                 dtype=None) -> RefineResult:
    """Refine β, γ, z of the B images of a G-buffer batch, each image on its own.

    Args:
        params: :class:`~reflectmm_cli.finetune.render.ModelParams` (its first ``beta.shape[1]`` components are
            fitted; the model is not changed).
        light: the :class:`~reflectmm_cli.model.light.LightModel`.
        gb: :class:`~reflectmm_cli.finetune.render.GBufferBatch` with ``target`` (P, 3) linear radiance.
        beta: (B, M'), gamma: (B, N_L'), z: (B, 3) torch — the start (an encoder's prediction, or zeros and
            :func:`initial_z`).
        config: :class:`RefineConfig`; names: B image names for error messages.
        dtype: torch dtype of the per-pixel work (default: the G-buffer's).
    Returns:
        :class:`RefineResult`.
    """
    import torch

    cfg = config or RefineConfig()
    if gb.target is None:
        raise ReflectmmError("refine: the batch has no target image (load it with with_target=True)")
    B = gb.n_images
    if beta.shape[0] != B or gamma.shape[0] != B or tuple(z.shape) != (B, 3):
        raise ReflectmmError(f"refine: β, γ, z must have {B} rows and z 3 columns, got {tuple(beta.shape)}, "
                             f"{tuple(gamma.shape)}, {tuple(z.shape)}")
    if beta.shape[1] > params.n_components or gamma.shape[1] > light.n_components:
        raise ReflectmmError(f"refine: {beta.shape[1]} reflectance / {gamma.shape[1]} light coefficients, the "
                             f"models have {params.n_components} / {light.n_components}")
    dt = dtype or gb.bary.dtype
    dev = gb.bary.device
    lt = _light_tensors(light, int(gamma.shape[1]), dt, dev)
    order = light.order
    names = list(names) if names is not None else [str(i) for i in range(B)]
    out_b, out_g, out_z = [], [], []
    e_start, e_end, steps = np.zeros(B), np.zeros(B), np.zeros(B, np.int64)
    for b in range(B):
        img = _image(params, lt, gb, b, int(beta.shape[1]), order, dt, cfg.max_pixels)
        st = _State(beta[b].detach().to(dt), gamma[b].detach().to(dt), z[b].detach().to(dt))
        st, e_start[b], e_end[b], steps[b] = _refine_one(img, lt, st, cfg, names[b])
        out_b.append(st.beta)
        out_g.append(st.gamma)
        out_z.append(st.z)
    cast = lambda xs, ref: torch.stack(xs).to(ref.dtype)  # noqa: E731
    return RefineResult(beta=cast(out_b, beta), gamma=cast(out_g, gamma), z=cast(out_z, z),
                        objective_start=e_start, objective_end=e_end, steps=steps)


def _image(params, lt: _Light, gb, b: int, n_beta: int, order: int, dt, max_pixels: int) -> _Image:
    """The fixed data of image b's skin pixels (an even stride over them when there are more than max_pixels)."""
    import torch

    s0, s1 = int(gb.offsets[b]), int(gb.offsets[b + 1])
    sel = torch.nonzero(gb.skin[s0:s1]).reshape(-1) + s0
    if max_pixels and sel.numel() > max_pixels:
        sel = sel[torch.linspace(0, sel.numel() - 1, max_pixels, device=sel.device).round().long()]
    a0, Ba, w0, Bw = _interp_bases(params, gb.vert_ids[sel], gb.bary[sel], n_beta)
    tr = pixel_transport(gb.normal[sel].to(dt), gb.view[sel].to(dt), params.exponents, order)
    YdL = torch.einsum("pn,kcn->pkc", tr.Yd, lt.L)
    return _Image(a0=a0.to(dt), Ba=Ba.to(dt), w0=w0.to(dt), Bw=Bw.to(dt), tr=tr, YdL=YdL,
                  target=gb.target[sel].to(dt))


def initial_z(params, light, gb, gamma, dtype=None):
    """Per-channel light scale z (B, 3) that best explains each image with the mean reflectance and the lighting
    ``μ + Σ γ σ ℓ`` (the model is linear in z: one closed-form least-squares ratio per channel); for a start
    without an encoder."""
    import torch

    dt = dtype or gb.bary.dtype
    lt = _light_tensors(light, int(gamma.shape[1]), dt, gb.bary.device)
    out = []
    for b in range(gb.n_images):
        img = _image(params, lt, gb, b, 0, light.order, dt, 0)
        st = _State(torch.zeros(0, dtype=dt), gamma[b].detach().to(dt), torch.ones(3, dtype=dt))
        I = _forward(img, lt, st)[0]  # noqa: E741
        num = (I * img.target).sum(0)
        den = (I * I).sum(0).clamp_min(1e-30)
        out.append(num / den)
    return torch.stack(out)
