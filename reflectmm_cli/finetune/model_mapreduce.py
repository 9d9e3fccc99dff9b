"""The least-squares model update as a map-reduce over groups of training images (``finetune --solver ls
--ls-shard-images N``; docs/finetune.md, "Map-reduce over shards").

The objective F of finetune/model_solve.py is a mean over images plus the pull, so each round splits into
independent map tasks, one per group of ``N`` consecutive training images (a "shard" of the round):

- map: refine the group's (β, γ, z) with the current model (from the previous round's values), pack its fitted
  pixels (:func:`~reflectmm_cli.finetune.model_solve.build_problem`, weights already divided by the number of
  training images), leave out its robust outliers, and return either
  * with ``harmonics`` Q: the explicit normal equations of the group in the reduced unknowns
    (:func:`normal_equations`: ``H_s = J_sᵀ W J_s``, ``g_s = J_sᵀ W r_s``, ``f_s = r_sᵀ W r_s``), or
  * per vertex: the packed pixels themselves;
- reduce: sum the groups' ``(H_s, g_s, f_s)`` in the groups' order (the same sum on every executor), or concatenate
  their pixels in order;
- solve: with harmonics, add the pull and solve ``H u = −g`` by Cholesky (:func:`solve_normal_equations`, exact);
  per vertex, the same preconditioned CG as one process (:func:`~reflectmm_cli.finetune.model_solve.solve_model`).

Why the per-vertex path does not reduce normal equations: its Hessian couples the three vertices of every
pixel's triangle, so it is not block-diagonal per vertex; held explicitly it is a sparse matrix of
(M+1)·(3+K) = 54 unknowns per vertex with about 7 neighbours each — some 7·10⁸ non-zeros for the demo's 35k
vertices, far more than the pixels it is made of. The pixels (≈ 2000 per image, 26 numbers each) are the smaller
exact summary there, and the CG on them is the one-process solve.

Layout of the reduced unknowns: ``U (M+1, Q, A)`` with A = 3 + K; row 0 is the means, row m ≥ 1 basis m − 1;
columns a < 3 the albedo channels, a ≥ 3 the lobe weights; ``θ = θ_start + Φ U`` part by part. For pixel p of
image b with ``c_b = (1, β_b σ)``, ``φ_p = Σ_t bary_pt Φ_{v_pt}`` and ``t_pc ∈ R^A`` (``D_pc`` at a = c, ``S_i,pc`` at
a = 3 + i) the rendered value is ``I_pc = I_pc(θ_start) + Σ c_bm φ_pq t_pc,a U_mqa``, so
``H = Σ_b (c_b c_bᵀ) ⊗ Y_b`` with ``Y_b = Σ_{p∈b} w_p φ_p φ_pᵀ ⊗ (Σ_c t_pc t_pcᵀ)``: one (QA)² matrix per image and
one product over the images, never a Jacobian. The dense H has ((M+1)QA)² entries: 58 MB at Q = 50, 0.93 GB at
Q = 200 (M = 8, K = 3), per map task, and the reduce holds every task's until it has summed them.
"""
from __future__ import annotations

import math
import time
from dataclasses import dataclass

import numpy as np

from reflectmm_cli.errors import ReflectmmError
from reflectmm_cli.recipes.executors import OrderedMap
from reflectmm_cli.threads import torch_threads

from .model_solve import (SolveConfig, SolveProblem, SolveReport, _expand, _fit_coefficients, _harmonic_basis,
                          _pixel_basis, _render, _theta, fitted_problem, merge_problems, pull_norms, robust_weights,
                          round_record, solve_model, vertex_arrays, warn_no_progress, warn_robust_no_effect)

__all__ = ["ShardTask", "run_shard", "normal_equations", "solve_normal_equations", "alternate_sharded",
           "shard_groups"]


@dataclass(frozen=True)
class ShardTask:
    """One map task: a group of images and everything needed to refine them and summarise them for the solve.

    Attributes:
        data: the shard files (str paths, opened in the worker) or a :class:`~reflectmm_cli.finetune.shards.ShardSet`.
        index: (n,) int the images' indices in the set; model: the reflectance model (σ, exponents); light: the light
        model; theta: the current (am (V,3), ab (M,V,3), wm (V,K), wb (M,V,K)) float64 numpy.
        refine: :class:`~reflectmm_cli.finetune.refine.RefineConfig`; batch_size: images per refinement batch.
        start: (β (n,M), γ (n,N_L), z (n,3)) float64 numpy to refine from, or None (from zero).
        mode: ``"val"`` (refine only), ``"pixels"`` (return the packed pixels) or ``"normal"`` (normal equations).
        n_train: images F averages over; max_pixels, robust: :class:`SolveConfig`'s; basis: Φ (V, Q) float64 numpy
        (``"normal"``); threads: torch threads of the task (fixed, so that results do not depend on the executor).
    """

    data: object
    index: np.ndarray
    model: object
    light: object
    theta: tuple
    refine: object
    batch_size: int
    start: tuple | None = None
    mode: str = "val"
    n_train: int = 1
    max_pixels: int = 2000
    robust: float = 0.0
    basis: np.ndarray | None = None
    threads: int = 1


def _numpy(t):
    return t.detach().cpu().numpy()


def run_shard(task: ShardTask) -> dict:
    """The map step (module docstring): ``{"objective": (n,), "cpu_s": the task's CPU seconds}`` plus, unless
    ``mode == "val"``, ``beta``, ``gamma``, ``z`` (refined, numpy), ``pixels`` and ``left_out`` (the fraction of
    pixels the robust weights leave out), and ``problem`` (the packed pixels as numpy, ``"pixels"``) or ``H``,
    ``g``, ``f`` (``"normal"``)."""
    import torch

    from .render import ModelParams
    from .shards import load_shards

    cpu = time.process_time()
    with torch_threads(task.threads), torch.no_grad():
        ss = load_shards(task.data) if isinstance(task.data, (list, tuple)) else task.data
        params = ModelParams(task.model, "cpu", dtype=torch.float64)
        params.albedo_mean, params.albedo_basis, params.weights_mean, params.weights_basis = (
            torch.as_tensor(t) for t in task.theta)
        with torch.enable_grad():
            beta, gamma, z, obj, gbs = _fit_coefficients(params, task.light, ss, task.index, task.refine,
                                                         task.batch_size, "cpu", task.start)
        out = {"objective": np.asarray(obj)}
        if task.mode == "val":
            return out | {"cpu_s": time.process_time() - cpu}
        prob = fitted_problem(params, task.light, gbs, beta, gamma, z, task.max_pixels, 1)
        out.update(beta=_numpy(beta), gamma=_numpy(gamma), z=_numpy(z), pixels=int(prob.vid.shape[0]), left_out=0.0)
        if task.mode == "pixels":
            out["problem"] = {k: _numpy(v) for k, v in vars(prob).items()}
            return out | {"cpu_s": time.process_time() - cpu}
        prob.weight = prob.weight / task.n_train
        if task.robust > 0:
            prob.weight, out["left_out"] = robust_weights(prob, _theta(params), task.robust)
        H, g, f = normal_equations(prob, _theta(params), torch.as_tensor(task.basis))
        out.update(H=H, g=g, f=f, cpu_s=time.process_time() - cpu)
        return out


def normal_equations(prob: SolveProblem, start: list, basis, image_chunk: int = 8) -> tuple[np.ndarray, np.ndarray,
                                                                                             float]:
    """The data term of F in the reduced unknowns U (module docstring) around θ = ``start``:
    ``F_data(U) = f + 2 gᵀu + uᵀ H u`` with u = U flattened.

    Args:
        prob: the packed pixels (weights as in F); start: [am (V,3), ab (M,V,3), wm (V,K), wb (M,V,K)] float64
            torch; basis: Φ (V, Q) float64 torch.
    Returns:
        H ((M+1)QA, (M+1)QA), g ((M+1)QA,) float64 numpy and f (float).
    """
    import torch

    dt = torch.float64
    P, M = prob.coef.shape
    K = prob.S.shape[0]
    A, Q, M1 = 3 + K, basis.shape[1], M + 1
    r0 = _render(prob, *start) - prob.target  # (P, 3)
    w = prob.weight
    f = float((w[:, None] * r0 * r0).sum())
    phi = _pixel_basis(prob, basis, 0, P)  # (P, Q)
    t = torch.zeros((P, 3, A), dtype=dt)  # t_pc,a: ∂I_pc / ∂(interpolated unknown a)
    for c in range(3):
        t[:, c, c] = prob.D[:, c]
    t[:, :, 3:] = prob.S.permute(1, 2, 0)
    cfull = torch.cat([torch.ones((P, 1), dtype=dt), prob.coef], 1)  # (P, M+1)
    e = torch.einsum("p,pc,pca->pa", w, r0, t)
    g = torch.einsum("pm,pq,pa->mqa", cfull, phi, e).reshape(-1)
    At = torch.einsum("pca,pcb->pab", t, t) * w[:, None, None]  # (P, A, A) w_p Σ_c t tᵀ
    H4 = torch.zeros((M1 * M1, (Q * A) ** 2), dtype=dt)
    images = torch.unique(prob.image)  # sorted: a fixed order
    for i0 in range(0, len(images), image_chunk):
        Ys, Cs = [], []
        for b in images[i0:i0 + image_chunk]:
            sel = torch.nonzero(prob.image == b).reshape(-1)
            pb = phi[sel]
            Ys.append(torch.einsum("pq,pab,pr->qarb", pb, At[sel], pb).reshape(-1))
            cb = cfull[sel[0]]
            Cs.append(torch.outer(cb, cb).reshape(-1))
        H4 += torch.stack(Cs).T @ torch.stack(Ys)
    H = H4.reshape(M1, M1, Q, A, Q, A).permute(0, 2, 3, 1, 4, 5).reshape(M1 * Q * A, M1 * Q * A)
    del H4  # H is a copy in U's order (the permutation is not a view)
    return H.numpy(), g.numpy(), f


def _pull_terms(start: list, theta0: list, pull: float, norms: list):
    """(ρ (M+1, A) the pull's weight of each unknown column, D (M+1, V, A) = θ_start − θ₀ in U's layout)."""
    import torch

    am, ab, wm, wb = (s - s0 for s, s0 in zip(start, theta0))
    D = torch.cat([torch.cat([am[None], ab]), torch.cat([wm[None], wb])], -1)
    M1, A = D.shape[0], D.shape[2]
    rho = torch.zeros((M1, A), dtype=D.dtype)
    for part, d in enumerate(norms):
        cols = slice(0, 3) if part < 2 else slice(3, A)
        rows = slice(0, 1) if part % 2 == 0 else slice(1, M1)
        val = pull / torch.as_tensor(d, dtype=D.dtype).reshape(-1, 1) if not isinstance(d, (int, float)) \
            else torch.full((1, 1), pull / d, dtype=D.dtype)
        rho[rows, cols] = val
    return rho, D


def solve_normal_equations(H: np.ndarray, g: np.ndarray, f: float, start: list, theta0: list, basis, *,
                           pull: float = 1.0, update_bases: int = -1, pull_scale: str = "element"
                           ) -> tuple[list, dict]:
    """Minimise F (finetune/model_solve.py) from the reduced normal equations of its data term (:func:`normal_equations`
    summed over the shards): the pull ``Σ ρ ‖Φ U_{·,a} + D_{·,a}‖²`` is added and ``H u = −g`` solved by Cholesky over
    the free unknowns (``update_bases``). Exact up to round-off, where the CG of
    :func:`~reflectmm_cli.finetune.model_solve.solve_model` stops at its tolerance.

    Args:
        H, g, f: the reduced data term; start, theta0: θ_start and θ₀ (float64 torch, as solve_model's);
            basis: Φ (V, Q).
    Returns:
        (θ, info) as :func:`~reflectmm_cli.finetune.model_solve.solve_model` (``iterations`` 0).
    """
    import scipy.linalg
    import torch

    norms = pull_norms(theta0, pull_scale)
    rho, D = _pull_terms(start, theta0, pull, norms)
    M1, Q, A = rho.shape[0], basis.shape[1], rho.shape[1]
    PtP = (basis.T @ basis).numpy()
    Hp = H.reshape(M1, Q, A, M1, Q, A).copy()
    gp = g.reshape(M1, Q, A) + (rho[:, None, :] * torch.einsum("vq,mva->mqa", basis, D)).numpy()
    for m in range(M1):
        for a in range(A):
            Hp[m, :, a, m, :, a] += float(rho[m, a]) * PtP
    f0 = f + float((rho[:, None, :] * D * D).sum())
    Hp, gp = Hp.reshape(M1 * Q * A, -1), gp.reshape(-1)
    free = np.ones((M1, Q, A), bool)
    if update_bases >= 0:
        free[1 + update_bases:] = False
    free = free.reshape(-1)
    u = np.zeros_like(gp)
    Hf = Hp if free.all() else Hp[np.ix_(free, free)]
    try:
        cf = scipy.linalg.cho_factor(Hf, lower=True, check_finite=True)
    except (np.linalg.LinAlgError, ValueError):
        raise ReflectmmError("model solve: the reduced normal equations are not positive definite "
                             "(no pull and harmonics no image sees? give --ls-pull > 0)") from None
    u[free] = -scipy.linalg.cho_solve(cf, gp[free])
    f1 = f0 + 2 * float(gp @ u) + float(u @ (Hp @ u))
    if not math.isfinite(f1):
        raise ReflectmmError("model solve: the objective became non-finite")
    if f1 > f0:  # a minimiser never raises a quadratic; guard against round-off all the same
        return [t.clone() for t in start], {"f_start": f0, "f_end": f0, "iterations": 0, "rel_residual": 0.0}
    U = torch.as_tensor(u.reshape(M1, Q, A))
    parts = [U[0, :, :3], U[1:, :, :3], U[0, :, 3:], U[1:, :, 3:]]
    theta = [s + d for s, d in zip(start, _expand(basis, parts))]
    res = float(np.linalg.norm(Hf @ u[free] + gp[free]) / max(np.linalg.norm(gp[free]), 1e-300))
    return theta, {"f_start": f0, "f_end": f1, "iterations": 0, "rel_residual": res}


def shard_groups(idx: np.ndarray, shard_images: int, batch_size: int) -> list[np.ndarray]:
    """``idx`` cut into consecutive groups of ``shard_images`` rounded up to a multiple of ``batch_size`` (so that
    the refinement batches are those of one process)."""
    size = max(1, -(-int(shard_images) // int(batch_size))) * int(batch_size)
    return [idx[i:i + size] for i in range(0, len(idx), size)]


def _reduce(results: list[dict], train_n: int, theta: list, cfg: SolveConfig, basis, theta0: list):
    """The reduce and solve steps of one round: (θ, solve info, fraction of pixels left out)."""
    import torch

    if basis is None:
        probs = [SolveProblem(**{k: torch.as_tensor(v) for k, v in r["problem"].items()}) for r in results]
        prob = merge_problems(probs, train_n)
        left_out = 0.0
        if cfg.robust > 0:
            prob.weight, left_out = robust_weights(prob, theta, cfg.robust)
        th, info = solve_model(prob, theta0, theta, pull=cfg.pull, cg_iterations=cfg.cg_iterations,
                               cg_tol=cfg.cg_tol, update_bases=cfg.update_bases, pull_scale=cfg.pull_scale)
        return th, info, left_out
    H, g, f = results[0]["H"].copy(), results[0]["g"].copy(), results[0]["f"]
    for r in results[1:]:  # in the groups' order: the same sum on every executor
        H += r["H"]
        g += r["g"]
        f += r["f"]
    pixels = sum(r["pixels"] for r in results)
    left_out = sum(r["left_out"] * r["pixels"] for r in results) / max(pixels, 1)
    th, info = solve_normal_equations(H, g, f, theta, theta0, basis, pull=cfg.pull, update_bases=cfg.update_bases,
                                      pull_scale=cfg.pull_scale)
    return th, info, left_out


def alternate_sharded(model, light, shards, config: SolveConfig, *, refine=None, batch_size: int = 8, log=None,
                      mesh=None, keep_best: bool = True, executor: str = "serial", jobs: int = 1,
                      scheduler: str | None = None, threads: int = 1) -> tuple[dict, SolveReport]:
    """:func:`~reflectmm_cli.finetune.model_solve.alternate` with every round a map-reduce over groups of
    ``config.shard_images`` training images (module docstring), the map run by
    :class:`~reflectmm_cli.recipes.executors.OrderedMap` (``executor`` auto, serial, pool or dask, ``jobs``,
    ``scheduler``; its workers start once for all rounds). The validation refinements are mapped the same way. The
    result does not depend on the executor or the number of jobs (each task runs with ``threads`` torch threads,
    the reduce sums in order); per vertex it is :func:`alternate`'s, with harmonics the CG is replaced by the exact
    Cholesky solve.

    Returns:
        (``vertex_*`` arrays of the kept model, float32, :class:`SolveReport`) as :func:`alternate`.
    """
    import torch

    from .refine import RefineConfig
    from .render import ModelParams

    cfg = config
    if cfg.shard_images < 1:
        raise ReflectmmError("model solve: the map-reduce needs shard_images ≥ 1")
    params = ModelParams(model, "cpu", dtype=torch.float64)
    theta0 = [t.clone() for t in _theta(params)]
    train, val = shards.indices("train"), shards.indices("val")
    if len(train) == 0:
        raise ReflectmmError("model solve: the shards have no image in the 'train' split")
    basis = _harmonic_basis(cfg, mesh, theta0[0].shape[0], log or (lambda s: None))
    base = dict(data=[str(p) for p in shards.sources] if shards.sources else shards, model=model, light=light,
                refine=refine or RefineConfig(iterations=cfg.refine_iterations), batch_size=batch_size,
                n_train=len(train), max_pixels=cfg.max_pixels, robust=cfg.robust, threads=int(threads),
                basis=None if basis is None else basis.numpy())
    with OrderedMap(executor, jobs, scheduler) as mapper:
        def run(idx, mode, theta, start=None):
            th = tuple(_numpy(t) for t in theta)
            tasks, k = [], 0
            for gi in shard_groups(idx, cfg.shard_images, batch_size):
                st = None if start is None else tuple(a[k:k + len(gi)] for a in start)
                tasks.append(ShardTask(index=gi, theta=th, start=st, mode=mode, **base))
                k += len(gi)
            return mapper(run_shard, tasks)

        best = _rounds(run, train, val, theta0, basis, cfg, keep_best, log or (lambda s: None), batch_size)
    return vertex_arrays(best[1]), best[0]


def _rounds(run, train, val, theta0, basis, cfg: SolveConfig, keep_best: bool, say, batch_size: int):
    """The rounds of :func:`alternate_sharded` with ``run(indices, mode, θ, start)`` the map: (report, kept θ)."""

    def val_objective(theta):
        if len(val) == 0:
            return float("nan")
        return float(np.mean(np.concatenate([r["objective"] for r in run(val, "val", theta)])))

    best = (val_objective(theta0), [t.clone() for t in theta0], 0)
    report = SolveReport(rounds=[{"round": 0, "val_objective": best[0]}])
    say(f"model solve: round 0 (initial model): validation objective {best[0]:.5g}; map-reduce over "
        f"{len(shard_groups(train, cfg.shard_images, batch_size))} groups of training images")
    theta, start = [t.clone() for t in theta0], None
    for rnd in range(1, cfg.rounds + 1):
        res = run(train, "pixels" if basis is None else "normal", theta, start)
        start = tuple(np.concatenate([r[k] for r in res]) for k in ("beta", "gamma", "z"))
        obj = np.concatenate([r["objective"] for r in res])
        theta, info, left_out = _reduce(res, len(train), theta, cfg, basis, theta0)
        v = val_objective(theta)
        report.rounds.append(round_record(rnd, obj, info, v, left_out))
        say(f"model solve: round {rnd}: training objective {info['f_start']:.5g} -> {info['f_end']:.5g}, "
            f"validation objective {v:.5g}")
        warn_no_progress(rnd, info)
        if not (v >= best[0]) or not keep_best:
            best = (v, [t.clone() for t in theta], rnd)
    report.best_round = best[2]
    warn_robust_no_effect(cfg.robust, report)
    return report, best[1]
