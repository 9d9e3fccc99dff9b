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
With ``pull_scale = "relative"`` the pull is instead λ Σ_arrays ‖x − x₀‖² / ‖x₀‖² over the two means and every
basis k of both parts separately: a relative change of one array costs the same whatever its size, so a basis
that is small at the start (the lobe weights') cannot grow several-fold for little cost.
F is quadratic; its minimiser solves the symmetric positive-definite normal equations ``H θ = g``, solved here by
conjugate gradients preconditioned with the exact diagonal of H (matrix-free: one product H·v is one pass of the
linear renderer and its adjoint). Vertices no image sees keep their initial values.

Constraints on what may change (:class:`SolveConfig`): with ``harmonics`` Q the change of every part is
``Φ u`` (Φ (V, Q) the mesh's lowest manifold harmonics; the unknowns are u, and F is the same quadratic in u); with
``update_bases`` R only the means and the first R bases are unknowns; with ``robust`` k the pixels whose residual
after the refinement is an outlier of their image (k · 1.4826 · MAD) get weight 0 (:func:`robust_weights`).

``alternate`` runs the EM-like loop: refine every training image's (β, γ, z) with the current model, solve the model,
repeat; the objective on a validation split is recorded after each round and the best round is kept.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from reflectmm_cli.errors import ReflectmmError

__all__ = ["PULL_SCALES", "SolveConfig", "pull_norms", "SolveProblem", "build_problem", "merge_problems",
           "robust_weights", "solve_model", "alternate", "SolveReport", "with_solved", "warn_robust_no_effect"]

#: Scales of the L2 pull (:class:`SolveConfig`.pull_scale).
PULL_SCALES = ("element", "relative")
_FIELDS = ("vid", "bary", "coef", "D", "S", "target", "weight", "image")


def _check_pull_scale(pull_scale: str) -> None:
    if pull_scale not in PULL_SCALES:
        raise ReflectmmError(f"model solve: pull_scale must be one of {', '.join(PULL_SCALES)}, got {pull_scale!r}")


@dataclass(frozen=True)
class SolveConfig:
    """Options of the least-squares model update.

    Attributes:
        rounds: refine → solve rounds.
        pull: λ of the L2 pull to the initial model (per-element mean squared change).
        cg_iterations: conjugate-gradient iterations per solve; cg_tol: stop at this relative residual.
        max_pixels: skin pixels per image entering the solve (even stride; 0 = all).
        refine_iterations: Levenberg–Marquardt iterations of the per-image refinement in each round.
        harmonics: Q > 0 restricts the change of the mean and of every basis to the Q smoothest functions on the
            mesh (:func:`~reflectmm_cli.geometry.harmonics.mesh_harmonics`); 0 = a free value per vertex.
        robust: k > 0 leaves out of the solve every pixel whose residual after the refinement is more than k robust
            standard deviations (1.4826 · MAD of its image) from its image's median residual; 0 = all pixels.
        update_bases: only the means and the first ``update_bases`` bases change (−1: all).
        pull_scale: ``"element"``: the pull on each part is λ × its mean squared change; ``"relative"``: λ × each
            array's (a mean, or one basis) squared change over its initial squared norm (:func:`pull_norms`).
        shard_images: > 0 runs each round as a map-reduce over groups of this many training images (rounded up to
            a multiple of the refinement batch; finetune/model_mapreduce.py); 0 = one process (:func:`alternate`).
    """

    rounds: int = field(default=3, metadata={"help": "refine -> solve rounds.", "range": (1, 100)})
    pull: float = field(default=1.0, metadata={"help": "L2 pull to the initial model (per-element mean square)."})
    cg_iterations: int = field(default=150, metadata={"help": "CG iterations per model solve.", "range": (1, 100000)})
    cg_tol: float = field(default=1e-4, metadata={"help": "CG stops at this relative residual."})
    max_pixels: int = field(default=2000, metadata={"help": "Skin pixels per image in the solve (0 = all).",
                                                    "range": (0, None)})
    refine_iterations: int = field(default=12, metadata={"help": "Refinement iterations per image and round.",
                                                         "range": (1, 1000)})
    harmonics: int = field(default=0, metadata={"help": "Restrict the model's change to this many smoothest "
                                                        "functions on the mesh (0 = per vertex).",
                                                "range": (0, 100000)})
    robust: float = field(default=0.0, metadata={"help": "Leave out pixels whose residual is beyond this many "
                                                         "robust standard deviations (MAD) of their image (0 = off)."})
    update_bases: int = field(default=-1, metadata={"help": "Update the means and only the first N bases (-1 = all).",
                                                    "range": (-1, 100000)})
    pull_scale: str = field(default="element", metadata={"help": "Scale of the L2 pull: element = per-element mean "
                                                                 "square of each part; relative = each mean and basis "
                                                                 "over its own initial squared norm.",
                                                         "choices": PULL_SCALES})
    shard_images: int = field(default=0, metadata={"help": "Run each round as a map-reduce over groups of this many "
                                                           "training images, on --jobs / --executor / --scheduler "
                                                           "(0 = one process).", "range": (0, 10000000)})

    def __post_init__(self):
        for k in ("pull", "cg_tol", "robust"):
            v = float(getattr(self, k))
            if not (math.isfinite(v) and v >= 0):
                raise ReflectmmError(f"model solve: {k} must be finite and ≥ 0, got {v}")
        if int(self.rounds) < 1 or int(self.cg_iterations) < 1:
            raise ReflectmmError("model solve: rounds and cg_iterations must be ≥ 1")
        if int(self.harmonics) < 0 or int(self.update_bases) < -1 or int(self.shard_images) < 0:
            raise ReflectmmError("model solve: harmonics and shard_images must be ≥ 0 and update_bases ≥ −1")
        _check_pull_scale(self.pull_scale)


@dataclass
class SolveProblem:
    """The fixed data of one model solve (torch, float64), all images' fitted pixels packed.

    Attributes:
        vid: (P, 3) vertex ids; bary: (P, 3); coef: (P, M) β·σ of each pixel's image; D: (P, 3); S: (K, P, 3);
        target: (P, 3); weight: (P,) 1/(3 S_b B) of each pixel's image (B images); image: (P,) int64 the
        pixel's image (0..B−1).
    """

    vid: "torch.Tensor"  # noqa: F821
    bary: "torch.Tensor"  # noqa: F821
    coef: "torch.Tensor"  # noqa: F821
    D: "torch.Tensor"  # noqa: F821
    S: "torch.Tensor"  # noqa: F821
    target: "torch.Tensor"  # noqa: F821
    weight: "torch.Tensor"  # noqa: F821
    image: "torch.Tensor"  # noqa: F821


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
    parts = {k: [] for k in _FIELDS}
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
        parts["image"].append(torch.full((n,), b, dtype=torch.int64))
    if not parts["vid"]:
        raise ReflectmmError("model solve: no skin pixel in the training images")
    cat = {k: torch.cat(v, 1 if k == "S" else 0) for k, v in parts.items()}
    return SolveProblem(**cat)


def merge_problems(problems: list[SolveProblem], n_images: int) -> SolveProblem:
    """One problem of several batches' (each weight is then divided by the number of images: a mean over images)."""
    import torch

    cat = {k: torch.cat([getattr(p, k) for p in problems], 1 if k == "S" else 0) for k in _FIELDS if k != "image"}
    cat["weight"] = cat["weight"] / max(n_images, 1)
    ids, k = [], 0
    for p in problems:  # image numbers made unique across the batches
        ids.append(p.image + k)
        k += int(p.image.max()) + 1 if p.image.numel() else 0
    return SolveProblem(image=torch.cat(ids), **cat)


def robust_weights(prob: SolveProblem, theta: list, k: float) -> tuple["torch.Tensor", float]:  # noqa: F821
    """Pixel weights with the outliers of each image left out: the residual r (P, 3) of the model θ; per image,
    its per-channel median m_c and robust scale s = 1.4826 · median |r − m| (over its pixels and channels); a pixel
    is an outlier when any |r_pc − m_c| > k s. The image's inliers share its weight (each image keeps its share
    of the mean). No ground truth is involved: only the images and the current fit.

    Returns:
        ((P,) weights, fraction of pixels left out).
    """
    import torch

    with torch.no_grad():
        r = _render(prob, *theta) - prob.target
    w = prob.weight.clone()
    out = torch.zeros(r.shape[0], dtype=torch.bool)
    for b in torch.unique(prob.image):
        sel = torch.nonzero(prob.image == b).reshape(-1)
        rb = r[sel]
        dev = (rb - rb.median(0).values).abs()
        s = 1.4826 * dev.reshape(-1).median()
        bad = (dev > k * s).any(1) if s > 0 else torch.zeros(sel.numel(), dtype=torch.bool)
        if bool(bad.all()):  # never drop a whole image
            continue
        out[sel] = bad
        w[sel] = torch.where(bad, torch.zeros_like(w[sel]), w[sel] * sel.numel() / float((~bad).sum()))
    return w, float(out.to(torch.float64).mean())


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


def pull_norms(theta0: list, pull_scale: str = "element") -> list:
    """Per-part divisors d of the pull ``λ Σ_parts Σ (x − x₀)² / d`` (each broadcastable to its part).

    Args:
        theta0: [am (V,3), ab (M,V,3), wm (V,K), wb (M,V,K)] the initial model.
        pull_scale: ``"element"``: d = the part's element count (an int); ``"relative"``: d = ‖x₀‖² of the mean
            (a float) and of each basis k (an (M, 1, 1) tensor). An array that is zero at the start gets the
            squared norm 1e-12 × the largest of its part (it is held where it is).
    """
    import torch

    if pull_scale == "element":
        return [t.numel() for t in theta0]
    _check_pull_scale(pull_scale)
    out = []
    for part, t in enumerate(theta0):
        sq = (t.detach().to(torch.float64) ** 2).reshape(t.shape[0] if part % 2 else 1, -1).sum(1)
        sq = torch.clamp(sq, min=max(1e-12 * float(sq.max()), 1e-300))
        out.append(float(sq[0]) if part % 2 == 0 else sq.reshape(-1, 1, 1).to(t.dtype))
    return out


def _objective_and_grad_u(prob: SolveProblem, start: list, u: list, theta0: list, pull: float, norms: list, basis):
    """(F, ∇_u F) at θ = start + u (per-vertex), or θ = start + Φu (``basis`` Φ (V, Q)); ``norms``:
    :func:`pull_norms`."""
    import torch

    u = [t.detach().requires_grad_(True) for t in u]
    x = [s + d for s, d in zip(start, _expand(basis, u))]
    r = _render(prob, *x) - prob.target
    f = (prob.weight[:, None] * r * r).sum()
    for xi, x0, d in zip(x, theta0, norms):
        sq = (xi - x0) ** 2
        f = f + (pull * sq.sum() / d if isinstance(d, (int, float)) else pull * (sq / d).sum())
    g = torch.autograd.grad(f, u)
    return float(f.detach()), [gi.detach() for gi in g]


def _pixel_basis(prob: SolveProblem, basis, s0: int, s1: int):
    """(n, Q) the harmonics interpolated at packed pixels s0:s1: ``Σ_t bary_pt Φ_{v_pt}``."""
    return (basis[prob.vid[s0:s1]] * prob.bary[s0:s1, :, None]).sum(1)


def _diag(prob: SolveProblem, shapes: list, pull: float, norms: list, basis=None, chunk: int = 20000) -> list:
    """The exact diagonal of H (½ the Hessian of F) in the unknowns' space (per-vertex values, or harmonic
    coefficients when ``basis`` Φ (V, Q) is given), for the Jacobi preconditioner; ``norms``:
    :func:`pull_norms` (the element counts of the parts by default)."""
    import torch

    P = prob.vid.shape[0]
    w = prob.weight[:, None]
    # per-pixel, per-channel squared sensitivity of the rendered value to one interpolated entry
    sens = [w * prob.D ** 2, w * (prob.S ** 2).sum(-1).T]  # ∂I_pc/∂a_c = D_pc; Σ_c S_i,pc² for lobe i
    coef2 = prob.coef ** 2
    out = [torch.zeros(shape, dtype=prob.D.dtype) for shape in shapes]
    for s0 in range(0, P, chunk):
        s1 = min(s0 + chunk, P)
        for part in range(4):
            sn = sens[part // 2][s0:s1]  # (n, C)
            if basis is None:  # a pixel touches its 3 vertices with weights bary²
                b2 = prob.bary[s0:s1, :, None] ** 2  # (n, 3, 1)
                ids = prob.vid[s0:s1].reshape(-1)
                if part % 2 == 0:
                    out[part].index_add_(0, ids, (b2 * sn[:, None]).reshape(-1, sn.shape[1]))
                else:
                    for m in range(shapes[part][0]):
                        c = b2 * (sn * coef2[s0:s1, m:m + 1])[:, None]
                        out[part][m].index_add_(0, ids, c.reshape(-1, sn.shape[1]))
            else:  # a pixel touches harmonic q with weight (Σ_t bary_t Φ_tq)²
                f2 = _pixel_basis(prob, basis, s0, s1) ** 2  # (n, Q)
                if part % 2 == 0:
                    out[part] += f2.T @ sn
                else:
                    out[part] += torch.einsum("pq,pm,pc->mqc", f2, coef2[s0:s1], sn)
    reg = [pull / n for n in norms]
    if basis is not None:
        phi2 = (basis ** 2).sum(0)[:, None]  # (Q, 1): the pull ‖Φu‖² on each coefficient
        return [o + r * phi2 for o, r in zip(out, reg)]
    return [o + r for o, r in zip(out, reg)]


def _pcg(Hv, rhs: list, dinv: list, iterations: int, tol: float) -> tuple[list, int, float]:
    """Preconditioned conjugate gradients on ``H δ = rhs`` from δ = 0 (lists of tensors); (δ, iterations, relative
    residual)."""
    dot = lambda a, b: sum(float((x * y).sum()) for x, y in zip(a, b))  # noqa: E731
    r = [t.clone() for t in rhs]
    zvec = [d * ri for d, ri in zip(dinv, r)]
    p = [zi.clone() for zi in zvec]
    delta = [t * 0 for t in rhs]
    rz = dot(r, zvec)
    r0 = math.sqrt(max(dot(r, r), 1e-300))
    it, rel = 0, 1.0
    for it in range(1, iterations + 1):
        Hp = Hv(p)
        pHp = dot(p, Hp)
        if not (pHp > 0 and math.isfinite(pHp)):
            break
        a = rz / pHp
        delta = [d + a * pi for d, pi in zip(delta, p)]
        r = [ri - a * hi for ri, hi in zip(r, Hp)]
        rel = math.sqrt(max(dot(r, r), 0.0)) / r0
        if rel < tol:
            break
        zvec = [d * ri for d, ri in zip(dinv, r)]
        rz_new = dot(r, zvec)
        beta = rz_new / rz
        rz = rz_new
        p = [zi + beta * pi for zi, pi in zip(zvec, p)]
    return delta, it, rel


def _expand(basis, u: list) -> list:
    """Per-vertex changes of the unknowns u: u itself, or ``Φ u`` per part with Φ (V, Q)."""
    import torch

    if basis is None:
        return u
    return [torch.einsum("vq,...qc->...vc", basis, x) for x in u]


def _free_mask(shapes: list, update_bases: int, dtype) -> list:
    """1 for unknowns that may change, 0 for the bases from ``update_bases`` on (−1: all change)."""
    import torch

    out = []
    for part, shape in enumerate(shapes):
        m = torch.ones(shape, dtype=dtype)
        if part % 2 == 1 and update_bases >= 0:
            m[update_bases:] = 0
        out.append(m)
    return out


def solve_model(prob: SolveProblem, theta0: list, theta_start: list | None = None, *, pull: float = 1.0,
                cg_iterations: int = 150, cg_tol: float = 1e-4, basis=None, update_bases: int = -1,
                pull_scale: str = "element") -> tuple[list, dict]:
    """Minimise F (module docstring) by preconditioned CG from ``theta_start`` (default θ₀).

    Args:
        prob: the fixed data; theta0: [am (V,3), ab (M,V,3), wm (V,K), wb (M,V,K)] float64 torch, the initial
            model (the pull's target).
        basis: optional Φ (V, Q) float64 torch: the change of every part is restricted to ``Φ u`` (smooth
            functions on the mesh, :func:`~reflectmm_cli.geometry.harmonics.mesh_harmonics`); unknowns u (…, Q, C).
        update_bases: only the means and the first ``update_bases`` bases change (−1: all).
        pull_scale: ``"element"`` or ``"relative"`` (:func:`pull_norms`).
    Returns:
        (θ, info) with ``info = {"f_start", "f_end", "iterations", "rel_residual"}``.
    """
    norms = pull_norms(theta0, pull_scale)
    start = [t.clone() for t in (theta_start or theta0)]
    shapes = [t.shape if basis is None else t.shape[:-2] + (basis.shape[1], t.shape[-1]) for t in start]
    mask = _free_mask(shapes, int(update_bases), start[0].dtype)

    def F(u):  # objective and gradient in the unknowns' space, frozen unknowns' gradient zeroed
        f, g = _objective_and_grad_u(prob, start, u, theta0, pull, norms, basis)
        return f, [gi * m for gi, m in zip(g, mask)]

    zero = [start[0].new_zeros(sh) for sh in shapes]
    f0, g = F(zero)  # F is quadratic: ∇F(u) − ∇F(0) = 2 H u

    def Hv(v):
        return [(a - b) / 2 for a, b in zip(F(v)[1], g)]

    dinv = [m / d for m, d in zip(mask, _diag(prob, shapes, pull, norms, basis))]
    delta, it, rel = _pcg(Hv, [-gi / 2 for gi in g], dinv, cg_iterations, cg_tol)
    f1, _ = F(delta)
    if not math.isfinite(f1):
        raise ReflectmmError("model solve: the objective became non-finite")
    if f1 > f0:  # CG on an SPD system never raises a quadratic; guard against round-off all the same
        return start, {"f_start": f0, "f_end": f0, "iterations": it, "rel_residual": rel}
    theta = [t + d for t, d in zip(start, _expand(basis, delta))]
    return theta, {"f_start": f0, "f_end": f1, "iterations": it, "rel_residual": rel}


def _harmonic_basis(cfg: SolveConfig, mesh, V: int, say):
    """Φ (V, Q) float64 torch of ``cfg.harmonics`` (None when 0)."""
    import torch

    from reflectmm_cli.geometry.harmonics import mesh_harmonics

    if not cfg.harmonics:
        return None
    if mesh is None:
        raise ReflectmmError("model solve: harmonics need the face mesh (no face model found)")
    if np.shape(mesh[0])[0] != V:
        raise ReflectmmError(f"model solve: the face mesh has {np.shape(mesh[0])[0]} vertices, the model {V}")
    phi, lam = mesh_harmonics(mesh[0], mesh[1], cfg.harmonics)
    say(f"model solve: {cfg.harmonics} mesh harmonics (eigenvalues {lam[1]:.3g} … {lam[-1]:.3g})")
    return torch.as_tensor(phi, dtype=torch.float64)


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


def fitted_problem(params, light, gbs, beta, gamma, z, max_pixels: int, n_images: int) -> SolveProblem:
    """The packed pixels of the refined images (:func:`build_problem` per refinement batch ``gbs``, in order, with
    their (β, γ, z) rows) merged with weights over ``n_images``."""
    probs, k = [], 0
    for gb in gbs:
        n = gb.n_images
        probs.append(build_problem(params, light, gb, beta[k:k + n], gamma[k:k + n], z[k:k + n],
                                   max_pixels=max_pixels))
        k += n
    return merge_problems(probs, n_images)


def warn_no_progress(rnd: int, info: dict) -> None:
    """One warning line when a round's solve did not lower the training objective: the model it writes is then
    the one it started from (``--ls-pull 0`` leaves the normal equations singular, for one)."""
    if not info["f_end"] < info["f_start"]:
        import logging

        logging.getLogger("reflectmm").warning(
            "model solve: round %d did not lower the training objective (%.5g -> %.5g): the model is unchanged by "
            "it; check --ls-pull (> 0) and --ls-cg-iterations", rnd, info["f_start"], info["f_end"])


def warn_robust_no_effect(robust: float, report: SolveReport) -> None:
    """One warning line when ``robust`` k > 0 left no pixel out in any round: with k so small that every pixel of
    an image is an outlier, the image is kept whole (:func:`robust_weights` never drops a whole image), and with k
    so large that none is, nothing is dropped either; the option then changed nothing."""
    rounds = [r for r in report.rounds if "pixels_left_out" in r]
    if robust > 0 and rounds and not any(r["pixels_left_out"] > 0 for r in rounds):
        import logging

        logging.getLogger("reflectmm").warning(
            "model solve: --ls-robust %g left no pixel out in any round, so it had no effect (an image whose pixels "
            "all lie beyond it is kept whole)", robust)


def round_record(rnd: int, train_objective: np.ndarray, info: dict, val_objective: float, left_out: float) -> dict:
    """One round's entry of :attr:`SolveReport.rounds`."""
    return {"round": rnd, "train_refined_objective": float(np.mean(train_objective)), "solve_start": info["f_start"],
            "solve_end": info["f_end"], "cg_iterations": info["iterations"], "cg_rel_residual": info["rel_residual"],
            "val_objective": val_objective, "pixels_left_out": left_out}


def vertex_arrays(theta: list) -> dict:
    """The ``vertex_*`` arrays (float32 numpy) of θ = [am, ab, wm, wb]."""
    am, ab, wm, wb = (t.detach().cpu().numpy().astype(np.float32) for t in theta)
    return {"vertex_albedo_mean": am, "vertex_albedo_basis": ab, "vertex_weights_mean": wm,
            "vertex_weights_basis": wb}


def with_solved(model, arrays: dict):
    """A copy of ``model`` with the arrays :func:`alternate` solved put in: each mean replaced, and the first rows
    of each ``*basis`` (the components the solve saw) replaced, the later ones kept (basis arrays float32 like the model)."""
    import copy

    out = copy.deepcopy(model)
    for k, v in arrays.items():
        full = np.array(getattr(model, k), np.float32)
        if k.endswith("basis"):
            full[:v.shape[0]] = v
        else:
            full = v
        setattr(out, k, full)
    return out


def alternate(model, light, shards, config: SolveConfig | None = None, *, refine=None, batch_size: int = 8,
              device="cpu", log=None, mesh=None, keep_best: bool = True) -> tuple[dict, SolveReport]:
    """The least-squares model update: ``config.rounds`` times, refine every training image's (β, γ, z) with the
    current model (from the previous round's values), then solve the model (:func:`solve_model`); after each round
    the validation images are refined from zero with the new model and their mean objective recorded. The round
    with the lowest validation objective is kept (the last one without a validation split).

    ``mesh`` = (vertices (V, 3), triangles (F, 3)) of the model's topology is needed with ``config.harmonics``.
    ``keep_best=False`` keeps the last round whatever the validation says (to measure the update itself).

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
    basis = _harmonic_basis(cfg, mesh, theta0[0].shape[0], say)

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
        prob = fitted_problem(params, light, gbs, beta, gamma, z, cfg.max_pixels, len(train))
        left_out = 0.0
        if cfg.robust > 0:
            prob.weight, left_out = robust_weights(prob, _theta(params), cfg.robust)
        theta, info = solve_model(prob, theta0, _theta(params), pull=cfg.pull, cg_iterations=cfg.cg_iterations,
                                  cg_tol=cfg.cg_tol, basis=basis, update_bases=cfg.update_bases,
                                  pull_scale=cfg.pull_scale)
        params.albedo_mean, params.albedo_basis, params.weights_mean, params.weights_basis = theta
        v = val_objective()
        report.rounds.append(round_record(rnd, obj, info, v, left_out))
        say(f"model solve: round {rnd}: training objective {info['f_start']:.5g} -> {info['f_end']:.5g} "
            f"({info['iterations']} CG iterations), validation objective {v:.5g}")
        warn_no_progress(rnd, info)
        if not (v >= best[0]) or not keep_best:  # lower, or no validation split (NaN): keep this round
            best = (v, [t.clone() for t in theta], rnd)
    report.best_round = best[2]
    warn_robust_no_effect(cfg.robust, report)
    return vertex_arrays(best[1]), report
