"""The model update as a linear least-squares problem (docs/design.md §10): with every training image's β, γ, z
fixed (refined per image, finetune/refine.py), the rendered pixels are linear in the model's means and bases.

Shapes: V vertices, M components, K lobes, P fitted pixels over all images (at most ``max_pixels`` skin pixels per
image), C = 3 colour channels.

For pixel p of image b, with barycentrics ``bary_pt`` over its triangle's vertices ``v_pt`` and the image's fixed
light transport ``D_pc = Y_d(n_p)·K_b,c`` and ``S_i,pc = Y_s,i(r_p)·K_b,c`` (the terms of finetune/refine.py):

    I_pc = Σ_t bary_pt [ D_pc (ā_v,c + Σ_k β_bk σ_k A_k,v,c) + Σ_i S_i,pc (w̄_v,i + Σ_k β_bk σ_k W_k,v,i) ]

The model solve minimises, over θ = (ā, A, w̄, W),

    F(θ) = mean_b [ 1/(3 S_b) Σ_{p,c} (I_pc − T_pc)² ] + λ Σ_parts mean((x − x₀)²)

(an L2 pull to the initial model x₀; each part averaged over its elements so that λ does not scale with V·M).
F is quadratic; its minimiser solves the symmetric positive-definite normal equations ``H θ = g``, solved here by
conjugate gradients preconditioned with the exact diagonal of H (matrix-free: one product H·v is one pass of the
linear renderer and its adjoint). Vertices no image sees keep their initial values.

``alternate`` runs the EM-like loop: refine every training image's (β, γ, z) with the current model, solve the model,
repeat; the objective on a validation split is recorded after each round and the best round is kept.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from reflectmm_cli.errors import ReflectmmError

__all__ = ["SolveConfig", "SolveProblem", "build_problem", "merge_problems", "solve_model", "alternate", "SolveReport"]


@dataclass(frozen=True)
class SolveConfig:
    """Options of the least-squares model update.

    Attributes:
        rounds: refine → solve rounds.
        pull: λ of the L2 pull to the initial model (per-element mean squared change).
        cg_iterations: conjugate-gradient iterations per solve; cg_tol: stop at this relative residual.
        max_pixels: skin pixels per image entering the solve (even stride; 0 = all).
        refine_iterations: Levenberg–Marquardt iterations of the per-image refinement in each round.
    """

    rounds: int = field(default=3, metadata={"help": "refine -> solve rounds.", "range": (1, 100)})
    pull: float = field(default=1.0, metadata={"help": "L2 pull to the initial model (per-element mean square)."})
    cg_iterations: int = field(default=150, metadata={"help": "CG iterations per model solve.", "range": (1, 100000)})
    cg_tol: float = field(default=1e-4, metadata={"help": "CG stops at this relative residual."})
    max_pixels: int = field(default=2000, metadata={"help": "Skin pixels per image in the solve (0 = all).",
                                                    "range": (0, None)})
    refine_iterations: int = field(default=12, metadata={"help": "Refinement iterations per image and round.",
                                                         "range": (1, 1000)})

    def __post_init__(self):
        for k in ("pull", "cg_tol"):
            v = float(getattr(self, k))
            if not (math.isfinite(v) and v >= 0):
                raise ReflectmmError(f"model solve: {k} must be finite and ≥ 0, got {v}")
        if int(self.rounds) < 1 or int(self.cg_iterations) < 1:
            raise ReflectmmError("model solve: rounds and cg_iterations must be ≥ 1")


@dataclass
class SolveProblem:
    """The fixed data of one model solve (torch, float64), all images' fitted pixels packed.

    Attributes:
        vid: (P, 3) vertex ids; bary: (P, 3); coef: (P, M) β·σ of each pixel's image; D: (P, 3); S: (K, P, 3);
        target: (P, 3); weight: (P,) 1/(3 S_b B) of each pixel's image (B images).
    """

    vid: "torch.Tensor"  # noqa: F821
    bary: "torch.Tensor"  # noqa: F821
    coef: "torch.Tensor"  # noqa: F821
    D: "torch.Tensor"  # noqa: F821
    S: "torch.Tensor"  # noqa: F821
    target: "torch.Tensor"  # noqa: F821
    weight: "torch.Tensor"  # noqa: F821


@dataclass
class SolveReport:
    """Per round: training objective before/after the solve, validation refined objective, CG iterations."""

    rounds: list = field(default_factory=list)
    best_round: int = 0


def build_problem(params, light, gb, beta, gamma, z, *, max_pixels: int = 2000) -> SolveProblem:
    """The :class:`SolveProblem` of one G-buffer batch (all its images) with fixed coefficients.

    Args:
        params: :class:`~reflectmm_cli.finetune.render.ModelParams` (for σ, the exponents and M).
        light: the light model; gb: :class:`~reflectmm_cli.finetune.render.GBufferBatch` with ``target``.
        beta: (B, M); gamma: (B, N_L); z: (B, 3) torch (the refined coefficients).
    """
    import torch

    from .refine import _light_tensors, pixel_transport

    dt = torch.float64
    B = gb.n_images
    lt = _light_tensors(light, int(gamma.shape[1]), dt, gb.bary.device)
    parts = {k: [] for k in ("vid", "bary", "coef", "D", "S", "target", "weight")}
    sig = params.sigma[:beta.shape[1]].to(dt)
    for b in range(B):
        s0, s1 = int(gb.offsets[b]), int(gb.offsets[b + 1])
        sel = torch.nonzero(gb.skin[s0:s1]).reshape(-1) + s0
        if sel.numel() == 0:
            continue
        if max_pixels and sel.numel() > max_pixels:
            sel = sel[torch.linspace(0, sel.numel() - 1, max_pixels, device=sel.device).round().long()]
        tr = pixel_transport(gb.normal[sel].to(dt), gb.view[sel].to(dt), params.exponents, light.order)
        K = z[b].to(dt)[:, None] * (lt.mu + torch.einsum("k,kcn->cn", gamma[b].to(dt), lt.L))
        n = sel.numel()
        parts["vid"].append(gb.vert_ids[sel])
        parts["bary"].append(gb.bary[sel].to(dt))
        parts["coef"].append((beta[b].to(dt) * sig).expand(n, -1))
        parts["D"].append(tr.Yd @ K.T)
        parts["S"].append(tr.Ys @ K.T)
        parts["target"].append(gb.target[sel].to(dt))
        parts["weight"].append(torch.full((n,), 1.0 / (3 * n), dtype=dt))
    if not parts["vid"]:
        raise ReflectmmError("model solve: no skin pixel in the training images")
    cat = {k: torch.cat(v, 1 if k == "S" else 0) for k, v in parts.items()}
    return SolveProblem(**cat)


def merge_problems(problems: list[SolveProblem], n_images: int) -> SolveProblem:
    """One problem of several batches' (each weight is then divided by the number of images: a mean over images)."""
    import torch

    cat = {k: torch.cat([getattr(p, k) for p in problems], 1 if k == "S" else 0)
           for k in ("vid", "bary", "coef", "D", "S", "target", "weight")}
    cat["weight"] = cat["weight"] / max(n_images, 1)
    return SolveProblem(**cat)


def _render(prob: SolveProblem, am, ab, wm, wb):
    """(P, 3) predicted radiance of the packed pixels for model parts am (V,3), ab (M,V,3), wm (V,K), wb (M,V,K)."""
    import torch

    ids = prob.vid.reshape(-1)
    P = prob.vid.shape[0]

    def at_pixels(mean, basis):  # per-pixel interpolated mean + Σ coef·basis, (P, C)
        g = mean.index_select(0, ids).view(P, 3, -1)
        gb = basis.index_select(1, ids).view(basis.shape[0], P, 3, -1)
        val = g + torch.einsum("pm,mptc->ptc", prob.coef, gb)
        return (val * prob.bary[..., None]).sum(1)

    alb = at_pixels(am, ab)
    wts = at_pixels(wm, wb)
    return alb * prob.D + torch.einsum("pi,ipc->pc", wts, prob.S)


def _objective_and_grad(prob: SolveProblem, theta: list, theta0: list, pull: float, sizes: list):
    import torch

    x = [t.detach().requires_grad_(True) for t in theta]
    r = _render(prob, *x) - prob.target
    f = (prob.weight[:, None] * r * r).sum()
    for xi, x0, n in zip(x, theta0, sizes):
        f = f + pull * ((xi - x0) ** 2).sum() / n
    g = torch.autograd.grad(f, x)
    return float(f.detach()), [gi.detach() for gi in g]


def _diag(prob: SolveProblem, shapes: list, pull: float, sizes: list) -> list:
    """The exact diagonal of H (½ the Hessian of F) for the Jacobi preconditioner."""
    import torch

    P = prob.vid.shape[0]
    out = []
    w = prob.weight[:, None, None]  # (P,1,1)
    b2 = prob.bary[..., None] ** 2  # (P,3,1)
    for part, (shape, n) in enumerate(zip(shapes, sizes)):
        is_alb = part < 2
        # per-pixel, per-channel squared sensitivity of the rendered value to one vertex entry
        if is_alb:
            sens = (prob.D ** 2)[:, None, :]  # (P,1,3): ∂I_pc/∂ā_v,c = bary·D_pc
        else:
            sens = (prob.S ** 2).sum(-1).T[:, None, :]  # (P,1,K): Σ_c S_i,pc²
        contrib = w * b2 * sens  # (P,3,C)
        if part in (1, 3):  # bases: × coef²
            acc = torch.zeros(shape, dtype=contrib.dtype)
            for m in range(shape[0]):
                c = contrib * (prob.coef[:, m] ** 2)[:, None, None]
                acc[m].index_add_(0, prob.vid.reshape(-1), c.reshape(P * 3, -1))
        else:
            acc = torch.zeros(shape, dtype=contrib.dtype)
            acc.index_add_(0, prob.vid.reshape(-1), contrib.reshape(P * 3, -1))
        out.append(acc + pull / n)
    return out


def solve_model(prob: SolveProblem, theta0: list, theta_start: list | None = None, *, pull: float = 1.0,
                cg_iterations: int = 150, cg_tol: float = 1e-4) -> tuple[list, dict]:
    """Minimise F (module docstring) by preconditioned CG from ``theta_start`` (default θ₀).

    Args:
        prob: the fixed data; theta0: [am (V,3), ab (M,V,3), wm (V,K), wb (M,V,K)] float64 torch, the initial
            model (the pull's target).
    Returns:
        (θ, info) with ``info = {"f_start", "f_end", "iterations", "rel_residual"}``.
    """
    import torch

    sizes = [t.numel() for t in theta0]
    theta = [t.clone() for t in (theta_start or theta0)]
    f0, g = _objective_and_grad(prob, theta, theta0, pull, sizes)
    # F is quadratic: ∇F(θ + v) − ∇F(θ) = 2 H v
    zero = [torch.zeros_like(t) for t in theta]
    _, g_at = _objective_and_grad(prob, theta, theta0, pull, sizes)

    def Hv(v):
        _, gv = _objective_and_grad(prob, [t + vi for t, vi in zip(theta, v)], theta0, pull, sizes)
        return [(a - b) / 2 for a, b in zip(gv, g_at)]

    dinv = [1.0 / d for d in _diag(prob, [t.shape for t in theta], pull, sizes)]
    dot = lambda a, b: sum(float((x * y).sum()) for x, y in zip(a, b))  # noqa: E731
    # solve H δ = −g/2
    r = [-gi / 2 for gi in g]
    zvec = [d * ri for d, ri in zip(dinv, r)]
    p = [zi.clone() for zi in zvec]
    delta = zero
    rz = dot(r, zvec)
    r0 = math.sqrt(max(dot(r, r), 1e-300))
    it = 0
    rel = 1.0
    for it in range(1, cg_iterations + 1):
        Hp = Hv(p)
        pHp = dot(p, Hp)
        if not (pHp > 0 and math.isfinite(pHp)):
            break
        a = rz / pHp
        delta = [d + a * pi for d, pi in zip(delta, p)]
        r = [ri - a * hi for ri, hi in zip(r, Hp)]
        rel = math.sqrt(max(dot(r, r), 0.0)) / r0
        if rel < cg_tol:
            break
        zvec = [d * ri for d, ri in zip(dinv, r)]
        rz_new = dot(r, zvec)
        beta = rz_new / rz
        rz = rz_new
        p = [zi + beta * pi for zi, pi in zip(zvec, p)]
    theta = [t + d for t, d in zip(theta, delta)]
    f1, _ = _objective_and_grad(prob, theta, theta0, pull, sizes)
    if not math.isfinite(f1):
        raise ReflectmmError("model solve: the objective became non-finite")
    if f1 > f0:  # CG on an SPD system never raises a quadratic; guard against round-off all the same
        theta, f1 = [t.clone() for t in (theta_start or theta0)], f0
    return theta, {"f_start": f0, "f_end": f1, "iterations": it, "rel_residual": rel}


def _theta(params) -> list:
    return [params.albedo_mean, params.albedo_basis, params.weights_mean, params.weights_basis]


def _fit_coefficients(params, light, shards, idx, refine, batch_size, device, start=None):
    """Refined (β, γ, z, objective) of the images ``idx`` with the current model (from zero, or ``start``)."""
    import torch

    from .refine import initial_z, refine_batch
    from .render import batch_gbuffer

    out_b, out_g, out_z, obj, gbs = [], [], [], [], []
    M, NL = params.n_components, light.n_components
    for s0 in range(0, len(idx), batch_size):
        ib = idx[s0:s0 + batch_size]
        gb = batch_gbuffer(shards.batch(ib), device)
        if start is None:
            b0 = gb.bary.new_zeros((len(ib), M))
            g0 = gb.bary.new_zeros((len(ib), NL))
            z0 = initial_z(params, light, gb, g0)
        else:
            b0, g0, z0 = (torch.as_tensor(a[s0:s0 + batch_size], dtype=gb.bary.dtype) for a in start)
        res = refine_batch(params, light, gb, b0, g0, z0, refine, names=[str(n) for n in shards.names[ib]])
        out_b.append(res.beta), out_g.append(res.gamma), out_z.append(res.z), obj.append(res.objective_end)
        gbs.append(gb)
    cat = lambda xs: torch.cat(xs).detach()  # noqa: E731
    return cat(out_b), cat(out_g), cat(out_z), np.concatenate(obj), gbs


def alternate(model, light, shards, config: SolveConfig | None = None, *, refine=None, batch_size: int = 8,
              device="cpu", log=None) -> tuple[dict, SolveReport]:
    """The least-squares model update: ``config.rounds`` times, refine every training image's (β, γ, z) with the
    current model (from the previous round's values), then solve the model (:func:`solve_model`); after each round
    the validation images are refined from zero with the new model and their mean objective recorded. The round
    with the lowest validation objective is kept (the last one without a validation split).

    Returns:
        (``vertex_*`` arrays of the kept model, float32, :class:`SolveReport`).
    """
    import torch

    from .refine import RefineConfig
    from .render import ModelParams

    cfg = config or SolveConfig()
    rcfg = refine or RefineConfig(iterations=cfg.refine_iterations)
    say = log or (lambda s: None)
    params = ModelParams(model, device, dtype=torch.float64)
    theta0 = [t.clone() for t in _theta(params)]
    train, val = shards.indices("train"), shards.indices("val")
    if len(train) == 0:
        raise ReflectmmError("model solve: the shards have no image in the 'train' split")
    report = SolveReport()

    def val_objective():
        if len(val) == 0:
            return float("nan")
        return float(np.mean(_fit_coefficients(params, light, shards, val, rcfg, batch_size, device)[3]))

    best = (val_objective(), [t.clone() for t in theta0], 0)
    report.rounds.append({"round": 0, "val_objective": best[0]})
    say(f"model solve: round 0 (initial model): validation objective {best[0]:.5g}")
    start = None
    for rnd in range(1, cfg.rounds + 1):
        beta, gamma, z, obj, gbs = _fit_coefficients(params, light, shards, train, rcfg, batch_size, device, start)
        start = (beta, gamma, z)
        probs, k = [], 0
        for gb in gbs:
            n = gb.n_images
            probs.append(build_problem(params, light, gb, beta[k:k + n], gamma[k:k + n], z[k:k + n],
                                       max_pixels=cfg.max_pixels))
            k += n
        prob = merge_problems(probs, len(train))
        theta, info = solve_model(prob, theta0, _theta(params), pull=cfg.pull, cg_iterations=cfg.cg_iterations,
                                  cg_tol=cfg.cg_tol)
        params.albedo_mean, params.albedo_basis, params.weights_mean, params.weights_basis = theta
        v = val_objective()
        rec = {"round": rnd, "train_refined_objective": float(np.mean(obj)), "solve_start": info["f_start"],
               "solve_end": info["f_end"], "cg_iterations": info["iterations"], "cg_rel_residual":
               info["rel_residual"], "val_objective": v}
        report.rounds.append(rec)
        say(f"model solve: round {rnd}: training objective {info['f_start']:.5g} -> {info['f_end']:.5g} "
            f"({info['iterations']} CG iterations), validation objective {v:.5g}")
        if not (v >= best[0]):  # lower, or no validation split (NaN): keep this round
            best = (v, [t.clone() for t in theta], rnd)
    report.best_round = best[2]
    am, ab, wm, wb = (t.detach().cpu().numpy().astype(np.float32) for t in best[1])
    return {"vertex_albedo_mean": am, "vertex_albedo_basis": ab, "vertex_weights_mean": wm,
            "vertex_weights_basis": wb}, report
