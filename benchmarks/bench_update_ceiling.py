"""Why the model update closes none of the expressive-power gap: what limits it, measured against ceilings
(docs/benchmarks.md, "What limits the model update").

On a finished demo workspace (its synth wild truth is read only by the measures and by the ceiling rows, which say
so):

1. **The coefficients the images give.** Every training image is refined with the initial model (the update's
   first step) and its β is compared with its identity's true coefficients: the projection of the identity's
   true per-vertex diffuse albedo onto the initial model (one free scale, prior 1e-3, as ``evaluate
   expressive``). Per component the correlation over images and over identities (the mean β of each identity's
   images), the relative error, and the spread of β within an identity against the true spread between
   identities.
2. **The update given better inputs.** A round of the exact harmonic update (``--ls-harmonics Q
   --ls-shard-images``' Cholesky solve, pull λ; ``--harmonics 0``: per vertex, the one-process CG) from the same
   refined images (``--light-components N``: the refinements fit only the first N light components; ``--w-coef``:
   their coefficient prior), with β
   * ``image``: each image's own (the solver as it is);
   * ``shared``: one β per identity, refined jointly over the identity's images with each image's own γ, z
     (Levenberg–Marquardt on the summed per-image objectives; the synthetic wild set has 4 images per identity
     under different skies);
   * ``truebeta`` (ceiling; reads the truth): β held at the identity's true coefficients, γ and z refined;
   * ``matched`` (ceiling; reads the truth): every training image's skin pixels replaced by the model's own
     shading (spherical harmonics light, Blinn–Phong lobes, no shadow) of its identity's true albedo and lobe
     weights under the image's refined light, noise-free; β, γ, z refined again from zero on these targets. A
     world the model explains exactly: what the update does when the images hold no error of the shading model;
   * ``matched_truebeta`` (ceiling): the matched images with β held at the true coefficients;
   * ``matched_truth`` (ceiling): the matched images with the true β and the light that rendered them, its
     intensity times the identity's albedo scale s (no refinement): only the update's own solve is left to err;
   ``--matched-weights model`` renders the matched images with the model's lobe weights at the true coefficients
   instead of the true ones, so that the only thing the images hold outside the model is the albedo;
   with ``--rounds N`` each variant alternates N times (refine from the previous values with the current model,
   then solve from the current model, the pull towards the initial one);
   then the expressive power of the held-out identities and the refined PSNR / SSIM of the test images, as
   ``bench_model_solve.py``.
3. **The update's form, given the truth** (ceiling; no images): the best change of the form the solver can make
   (per vertex, or ``Φ U`` with Q mesh harmonics) fitted by least squares to the training identities' *true*
   albedo with their true coefficients; its expressive power says how much of the gap an update of that form
   could close with perfect data.

    python benchmarks/bench_update_ceiling.py --workspace work [--pull 30] [--harmonics 200]
        [--variants image,shared,truebeta,matched,matched_truebeta,matched_truth] [--rounds 1]
        [--matched-weights truth|model] [--light-components N] [--w-coef W] [--forms 0,50,200,800] [--jsonl out.jsonl]
    python benchmarks/bench_update_ceiling.py --summarise out.jsonl
"""
from __future__ import annotations

import argparse
import json
import math
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))  # its sibling bench_model_solve, also when loaded by path


def true_coefficients(mean, basis, sigma, albedo, skin, prior: float = 1e-3) -> tuple[float, np.ndarray]:
    """(scale s, β) of one identity's true albedo projected onto a model part, ``albedo ≈ s (mean + Σ β_m σ_m B_m)``
    over its skin vertices: ``evaluate expressive``'s projection
    (:func:`~reflectmm_cli.evaluation.expressive.projection_coefficients`, its prior)."""
    from reflectmm_cli.evaluation.expressive import projection_coefficients

    x = projection_coefficients(mean, basis, sigma, np.asarray(albedo, np.float64)[None], np.asarray(skin, bool),
                                prior=prior)[0]
    return float(x[0]), x[1:] / x[0]


def refine_identity_groups(params, light, gbs, beta, gamma, z, groups, cfg, batch_size: int, fixed=None):
    """β shared by the images of each group (list of index arrays into the refined images), refined jointly with each
    image's own γ, z by Levenberg–Marquardt on the sum of the images' objectives (finetune/refine.py's E_b);
    ``fixed``: {group number: β} holds β and refines only γ, z. Returns (β, γ, z) torch (rows per image)."""
    import torch

    from reflectmm_cli.finetune.refine import _energy, _image, _light_tensors, _normal_equations, _State

    dt = torch.float64
    lt = _light_tensors(light, int(gamma.shape[1]), dt, "cpu")
    M, NL = int(beta.shape[1]), int(gamma.shape[1])
    beta, gamma, z = (t.clone().to(dt) for t in (beta, gamma, z))
    for gi, ks in enumerate(groups):
        imgs = [_image(params, lt, gbs[k // batch_size], k % batch_size, M, light.order, dt, cfg.max_pixels)
                for k in ks]
        b0 = beta[ks].mean(0) if fixed is None else torch.as_tensor(fixed[gi], dtype=dt)
        sts = [_State(b0, gamma[k], z[k]) for k in ks]

        def energy(states):
            return sum(_energy(im, lt, s, cfg) for im, s in zip(imgs, states))

        e, lam, n = energy(sts), cfg.damping, len(ks)
        U = M + n * (NL + 3)
        for _ in range(cfg.iterations):
            H = torch.zeros((U, U), dtype=dt)
            g = torch.zeros(U, dtype=dt)
            for j, (im, s) in enumerate(zip(imgs, sts)):
                Hb, gb, _ = _normal_equations(im, lt, s, cfg, None)
                sl = slice(M + j * (NL + 3), M + (j + 1) * (NL + 3))
                H[:M, :M] += Hb[:M, :M]
                H[:M, sl] += Hb[:M, M:]
                H[sl, :M] += Hb[M:, :M]
                H[sl, sl] += Hb[M:, M:]
                g[:M] += gb[:M]
                g[sl] += gb[M:]
            if fixed is not None:  # β held: no step along its unknowns
                H[:M], H[:, :M], g[:M] = 0, 0, 0
                H[range(M), range(M)] = 1.0
            diag = H.diagonal().clamp_min(1e-12)
            kept, rel = False, 0.0
            while lam < 1e10:
                d = -torch.linalg.solve(H + lam * torch.diag(diag), g)
                cand = [_State(sts[0].beta + d[:M], s.gamma + d[M + j * (NL + 3):M + j * (NL + 3) + NL],
                               s.z + d[M + j * (NL + 3) + NL:M + (j + 1) * (NL + 3)]) for j, s in enumerate(sts)]
                ec = energy(cand)
                if math.isfinite(ec) and ec < e:
                    rel, sts, e, lam, kept = (e - ec) / e, cand, ec, max(lam * 0.3, 1e-9), True
                    break
                lam *= 10.0
            if not kept or rel < cfg.tol:
                break
        for j, k in enumerate(ks):
            beta[k], gamma[k], z[k] = sts[j].beta, sts[j].gamma, sts[j].z
    return beta, gamma, z


def matched_batches(params, light, gbs, gamma, z, ident, truth_albedo, truth_weights):
    """The G-buffer batches with every skin pixel's target replaced by the model's own shading of the image's
    identity's *true* per-vertex albedo and lobe weights, lit by the image's refined light (γ, z): a world the
    shading model explains exactly (no environment map, shadow or GGX lobe), noise-free. The light transport is
    the model solve's (:func:`~reflectmm_cli.finetune.model_solve.build_problem` over every skin pixel)."""
    import dataclasses

    import torch

    from reflectmm_cli.finetune.model_solve import build_problem

    out, k = [], 0
    for gb in gbs:
        n = gb.n_images
        prob = build_problem(params, light, gb, torch.zeros((n, params.n_components), dtype=torch.float64),
                             gamma[k:k + n], z[k:k + n], max_pixels=0)
        shaded = torch.empty_like(prob.D)
        for b in range(n):
            p = prob.image == b
            bw = prob.bary[p][..., None]
            a = (torch.as_tensor(truth_albedo[ident[k + b]], dtype=bw.dtype)[prob.vid[p]] * bw).sum(1)
            w = (torch.as_tensor(truth_weights[ident[k + b]], dtype=bw.dtype)[prob.vid[p]] * bw).sum(1)
            shaded[p] = a * prob.D[p] + torch.einsum("pi,ipc->pc", w, prob.S[:, p])
        new = gb.target.clone()
        new[torch.nonzero(gb.skin).reshape(-1)] = shaded.to(new.dtype)  # the packed pixels: each image's skin, in order
        out.append(dataclasses.replace(gb, target=new))
        k += n
    return out


def refine_batches(params, light, gbs, cfg, start=None):
    """(β, γ, z) of every image of ``gbs`` refined from zero, or from ``start`` (β, γ, z) (finetune/refine.py)."""
    import torch

    from reflectmm_cli.finetune.refine import initial_z, refine_batch

    bs, gs, zs, k = [], [], [], 0
    for gb in gbs:
        n = gb.n_images
        if start is None:
            b0 = gb.bary.new_zeros((n, params.n_components))
            g0 = gb.bary.new_zeros((n, light.n_components))
            z0 = initial_z(params, light, gb, g0)
        else:
            b0, g0, z0 = (t[k:k + n].to(gb.bary.dtype) for t in start)
        k += n
        res = refine_batch(params, light, gb, b0, g0, z0, cfg)
        bs.append(res.beta), gs.append(res.gamma), zs.append(res.z)
    return torch.cat(bs), torch.cat(gs), torch.cat(zs)


def coefficient_table(beta: np.ndarray, true: np.ndarray, ident: np.ndarray) -> str:
    """Markdown: refined β (images) against the identities' true coefficients (rows of ``true`` per image)."""
    u = np.unique(ident)
    mb = np.stack([beta[ident == g].mean(0) for g in u])
    tb = np.stack([true[ident == g][0] for g in u])
    M = beta.shape[1]
    rows = ["| component | " + " | ".join(str(m) for m in range(M)) + " |", "|---|" + "---|" * M,
            "| corr. over images | " + " | ".join(f"{np.corrcoef(beta[:, m], true[:, m])[0, 1]:+.2f}"
                                              for m in range(M)) + " |",
            "| corr. over identities (mean β) | " + " | ".join(f"{np.corrcoef(mb[:, m], tb[:, m])[0, 1]:+.2f}"
                                                           for m in range(M)) + " |"]
    rel_i = np.median(np.linalg.norm(beta - true, axis=1) / np.linalg.norm(true, axis=1))
    rel_m = np.median(np.linalg.norm(mb - tb, axis=1) / np.linalg.norm(tb, axis=1))
    within = float(np.mean([np.linalg.norm(beta[ident == g].std(0)) for g in u]))
    between = float(np.linalg.norm(tb.std(0)))
    return "\n".join(rows) + (f"\n\nrelative error ‖β − β_true‖ / ‖β_true‖, median: {rel_i:.2f} per image, "
                              f"{rel_m:.2f} "
                              f"for the identity's mean β; spread of β within an identity {within:.2f} against the "
                              f"true spread between identities {between:.2f} (norms over the {M} components)")


def form_ceiling(mean, basis, sigma, train_albedo, train_skin, held_albedo, held_skin, forms, mesh) -> list[dict]:
    """Section 3 of the module docstring: per form (0 = per vertex, Q = harmonics) the held-out residual of the
    best change fitted to the training identities' truth."""
    from reflectmm_cli.evaluation.expressive import projection_residuals
    from reflectmm_cli.geometry.harmonics import mesh_harmonics

    M, V = basis.shape[:2]
    C, R = [], []
    for a, s in zip(train_albedo, train_skin):
        sc, b = true_coefficients(mean, basis, sigma, a, s)
        R.append((a / sc - (mean + np.einsum("m,mvc->vc", b * sigma, basis))) * np.asarray(s, bool)[:, None])
        C.append(np.r_[1.0, b])
    C, R = np.array(C), np.array(R)
    G = C.T @ C + 1e-6 * np.eye(M + 1)
    rhs = np.einsum("im,ivc->mvc", C, R)
    out = []
    for Q in forms:
        if Q == 0:
            dU = np.linalg.solve(G, rhs.reshape(M + 1, -1)).reshape(M + 1, V, 3)
        else:
            Phi, _ = mesh_harmonics(*mesh, int(Q))
            PtP = Phi.T @ Phi
            PtP += 1e-9 * np.trace(PtP) / Q * np.eye(Q)
            Uq = np.linalg.solve(PtP, np.einsum("vq,mvc->qmc", Phi, np.linalg.solve(G, rhs.reshape(M + 1, -1))
                                               .reshape(M + 1, V, 3)).reshape(Q, -1)).reshape(Q, M + 1, 3)
            dU = np.einsum("vq,qmc->mvc", Phi, Uq)
        r = projection_residuals(mean + dU[0], basis + dU[1:] / sigma[:, None, None], sigma, held_albedo, held_skin,
                                 prior=1e-3)
        out.append({"form": "per vertex" if Q == 0 else f"harmonics {Q}", "albedo_residuals": r.tolist()})
    return out


def _default_w_light() -> float:
    from reflectmm_cli.finetune.refine import RefineConfig

    return RefineConfig().w_light


def _default_w_coef() -> float:
    from reflectmm_cli.finetune.refine import RefineConfig

    return RefineConfig().w_coef


def _form(q: int) -> str:
    return f"harmonics {q}" if q else "per vertex"


def summarise(path: Path) -> str:
    """The rows of a ``--jsonl`` file: the form ceilings, then the updates with their paired differences against
    ``image`` (bench_model_solve.py's CIs: per test image, per held-out identity)."""
    from bench_model_solve import pair_table

    rows = [json.loads(line) for line in open(path) if line.strip()]
    forms = [r for r in rows if r["kind"] == "form"]
    out = ["| ceiling: update form fitted to the training identities' true albedo | albedo residual | gap closed |",
           "|---|---|---|"] if forms else []
    out += [f"| {r['form']} | {r['albedo_residual']:.4f} | {100 * r['gap_closed']:+.0f} % |" for r in forms]
    upd = [r for r in rows if r["kind"] == "update"]
    out += ["", "| update (rounds) | albedo residual (gap closed) | lobe-weight residual | refined test PSNR | "
            "SSIM | CPU s |", "|---|---|---|---|---|---|"]
    out += [f"| {r['variant']} (pull {r['pull']:g}, {_form(r['harmonics'])}, {r.get('rounds', 1)}) | "
            f"{r['albedo_residual']:.4f} "
            f"({100 * r['gap_closed']:+.0f} %) | {r['weights_residual']:.4f} | {np.mean(r['psnr']):.2f} | "
            f"{np.mean(r['ssim']):.4f} | {r['cpu_s']:.0f} |" for r in upd]
    names = [r["variant"] for r in upd]
    specs = [f"{n}:image" for n in names if n != "image"] if "image" in names else []
    return "\n".join(out) + ("\n\n" + pair_table(upd, specs) if specs else "")


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--workspace", type=Path, default=Path("work"))
    ap.add_argument("--pull", type=float, default=30.0)
    ap.add_argument("--harmonics", type=int, default=200, help="Q of the update (0: per vertex, solved by CG)")
    ap.add_argument("--max-pixels", type=int, default=1000)
    ap.add_argument("--cg-iterations", type=int, default=100, help="per vertex (--harmonics 0): CG iterations")
    ap.add_argument("--variants", default="image,shared,truebeta")
    ap.add_argument("--forms", default="0,50,200,800", help="update forms of the ceiling (0 = per vertex)")
    ap.add_argument("--rounds", type=int, default=1, help="rounds of refine-then-solve per variant")
    ap.add_argument("--matched-weights", choices=("truth", "model"), default="truth",
                    help="lobe weights of the matched images: the identities' true ones, or the model's at the true "
                         "coefficients (times the albedo scale): no specular residual, the albedo's alone")
    ap.add_argument("--w-light", type=float, default=_default_w_light(),
                    help="the monochrome-light weight of the update's refinements (reconstruct --refine's "
                         "default); the test images are refined with the default")
    ap.add_argument("--w-coef", type=float, default=_default_w_coef(),
                    help="the refinement's coefficient prior on β and γ (reconstruct --refine's default)")
    ap.add_argument("--light-components", type=int, default=0,
                    help="the update's refinements (and the matched images' light) use only the first N components "
                         "of the light model (0: all); the test images are refined with all")
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--jsonl", type=Path, default=None)
    ap.add_argument("--summarise", type=Path, default=None,
                    help="print the tables of a --jsonl file, with every update paired against image, and exit")
    a = ap.parse_args()
    if a.summarise is not None:
        print(summarise(a.summarise))
        return 0
    import torch

    from bench_model_solve import _measure, append_jsonl, load_workspace

    from reflectmm_cli.artifacts import read_artifact
    from reflectmm_cli.evaluation.expressive import gap_closed, projection_residuals
    from reflectmm_cli.finetune.model_mapreduce import normal_equations, solve_normal_equations
    from reflectmm_cli.finetune.model_solve import (SolveConfig, _fit_coefficients, _harmonic_basis, _theta,
                                                    fitted_problem, solve_model, vertex_arrays, with_solved)
    from reflectmm_cli.finetune.refine import RefineConfig
    from reflectmm_cli.finetune.render import ModelParams

    torch.set_num_threads(a.threads)
    ws = a.workspace
    say = lambda s: print(s, file=sys.stderr, flush=True)  # noqa: E731
    model, light_full, ss, fm, tr, truth, oracle = load_workspace(ws)
    light = light_full
    if a.light_components:  # the update's refinements fit only the first N light components (the test's all)
        import dataclasses

        n = int(a.light_components)
        light = dataclasses.replace(light_full, bases=light_full.bases[:n], sigma=light_full.sigma[:n],
                                    explained_variance=light_full.explained_variance[:n],
                                    explained_variance_ratio=light_full.explained_variance_ratio[:n])
    man = read_artifact(ws / "synth-wild" / "manifest.npz")
    ident_of = dict(zip(np.asarray(man["names"]).astype(str).tolist(),
                        np.asarray(man["identity"]).astype(int).tolist()))
    mu = np.asarray(model.vertex_albedo_mean, np.float64)
    B = np.asarray(model.vertex_albedo_basis, np.float64)
    sg = np.asarray(model.sigma, np.float64)
    r_init = projection_residuals(mu, B, sg, truth["albedo"], truth["skin"], prior=1e-3)
    r_orc = projection_residuals(oracle["vertex_albedo_mean"], oracle["vertex_albedo_basis"], oracle["sigma"],
                                 truth["albedo"], truth["skin"], prior=1e-3)
    gap = lambda r: gap_closed(float(r_init.mean()), float(np.mean(r)), float(r_orc.mean()))  # noqa: E731

    def emit(row):
        print(json.dumps(row), flush=True)
        append_jsonl(a.jsonl, row)

    # 3. the form's ceiling (truth only)
    for row in form_ceiling(mu, B, sg, [tr["albedo"][i] for i in tr["train"]], [tr["skin"][i] for i in tr["train"]],
                            truth["albedo"], truth["skin"], [int(q) for q in a.forms.split(",") if q],
                            (fm.mean_shape, fm.triangles)):
        r = np.asarray(row["albedo_residuals"])
        emit(row | {"kind": "form", "albedo_residual": float(r.mean()), "gap_closed": gap(r)})

    # 1. the coefficients the images give
    refine = RefineConfig(w_coef=a.w_coef, w_light=a.w_light)
    train = ss.indices("train")
    ident = np.array([ident_of[str(n)] for n in ss.names[train]])
    groups_ids = sorted(set(ident.tolist()))
    groups = [np.flatnonzero(ident == g) for g in groups_ids]
    true_sb = {g: true_coefficients(mu, B, sg, tr["albedo"][g], tr["skin"][g]) for g in groups_ids}
    true_b = {g: v[1] for g, v in true_sb.items()}
    true_s = {g: v[0] for g, v in true_sb.items()}
    say("albedo scale of the training identities against the initial model (true_coefficients): "
        + " ".join(f"{true_s[g]:.2f}" for g in groups_ids))
    params = ModelParams(model, "cpu", dtype=torch.float64)
    theta0 = [t.clone() for t in _theta(params)]
    t0 = time.process_time()
    with torch.enable_grad():
        beta, gamma, z, _, gbs = _fit_coefficients(params, light, ss, train, refine, 8, "cpu")
    t_refine = time.process_time() - t0
    say(f"refined {len(train)} training images of {len(groups)} identities in {t_refine:.0f} CPU s")
    print(coefficient_table(beta.numpy(), np.stack([true_b[g] for g in ident]), ident), flush=True)

    # 2. one exact harmonic round from each set of coefficients
    cfg = SolveConfig(rounds=1, max_pixels=a.max_pixels, harmonics=a.harmonics, pull=a.pull)
    basis = _harmonic_basis(cfg, (fm.mean_shape, fm.triangles), theta0[0].shape[0], say)
    if a.matched_weights == "model":  # the lobe weights in the model's span: s (w̄ + Σ β σ W), no specular residual
        wm = np.asarray(model.vertex_weights_mean, np.float64)
        wb = np.asarray(model.vertex_weights_basis, np.float64)
        m_weights = {g: true_s[g] * (wm + np.einsum("m,mvk->vk", true_b[g] * sg, wb)) for g in groups_ids}
    else:
        m_weights = tr["weights"]
    mg = matched_batches(params, light, gbs, gamma, z, ident, tr["albedo"], m_weights) \
        if any(v.startswith("matched") for v in a.variants.split(",")) else None
    fixed = [true_b[gid] for gid in groups_ids]

    def coefficients(name, theta, prev):
        """(β, γ, z) of the variant's images with the model θ, refined from ``prev`` (None: the first round)."""
        params.albedo_mean, params.albedo_basis, params.weights_mean, params.weights_basis = theta
        if name in ("image", "shared", "truebeta"):
            if prev is None:
                b, g, zz, batches = beta, gamma, z, gbs
            else:
                with torch.enable_grad():
                    b, g, zz, _, batches = _fit_coefficients(params, light, ss, train, refine, 8, "cpu",
                                                             tuple(t.numpy() for t in prev))
        elif name == "matched_truth":  # the true β and the light that rendered the matched images: no fit
            tb = torch.as_tensor(np.stack([true_b[gid] for gid in ident]), dtype=beta.dtype)
            # the light's intensity carries the identity's albedo scale s (albedo ≈ s (mean + Σ β σ B))
            sc = torch.as_tensor([true_s[gid] for gid in ident], dtype=z.dtype)[:, None]
            return tb, gamma, z * sc, mg
        else:
            batches = mg
            if prev is None:
                b, g, zz = refine_batches(params, light, mg, refine)
                print("coefficients of the matched images:\n" + coefficient_table(
                    b.numpy(), np.stack([true_b[gid] for gid in ident]), ident), flush=True)
            else:
                b, g, zz = prev
        if name in ("shared", "truebeta", "matched_truebeta"):
            b, g, zz = refine_identity_groups(params, light, batches, b, g, zz, groups, refine, 8,
                                              fixed=fixed if name.endswith("truebeta") else None)
        elif name == "matched" and prev is not None:
            b, g, zz = refine_batches(params, light, mg, refine, start=prev)
        return b, g, zz, batches

    for name in a.variants.split(","):
        if name not in ("image", "shared", "truebeta", "matched", "matched_truebeta", "matched_truth"):
            raise SystemExit(f"unknown variant {name!r}")
        t1 = time.process_time()
        theta, prev, infos = [t.clone() for t in theta0], None, []
        for _ in range(a.rounds):
            b, g, zz, batches = coefficients(name, theta, prev)
            prev = (b, g, zz)
            with torch.no_grad():
                prob = fitted_problem(params, light, batches, b, g, zz, a.max_pixels, len(train))
                if basis is None:  # per vertex: the one-process CG (finetune/model_solve.py; autograd products)
                    with torch.enable_grad():
                        theta, info = solve_model(prob, theta0, theta, pull=a.pull, cg_iterations=a.cg_iterations)
                else:
                    H, gv, f = normal_equations(prob, theta, basis)
                    theta, info = solve_normal_equations(H, gv, f, theta, theta0, basis, pull=a.pull)
            r_round = projection_residuals(theta[0].detach().numpy(), theta[1].detach().numpy(), sg,
                                           truth["albedo"], truth["skin"], prior=1e-3).mean()
            infos.append({"f_start": info["f_start"], "f_end": info["f_end"], "albedo_residual": float(r_round),
                          "gap_closed": gap([r_round])})
            say(f"{name}: round {len(infos)}: objective {info['f_start']:.5g} -> {info['f_end']:.5g}, albedo "
                f"residual {r_round:.4f} (gap closed {100 * gap([r_round]):+.0f} %)")
        cpu = time.process_time() - t1 + t_refine
        row = {"kind": "update", "variant": name, "initial_albedo_residual": float(r_init.mean()), "pull": a.pull,
               "w_coef": a.w_coef, "w_light": a.w_light, "matched_weights": a.matched_weights,
               "light_components": light.n_components, "harmonics": a.harmonics, "rounds": a.rounds, "cpu_s": cpu,
               "solves": infos}
        row.update(_measure(with_solved(model, vertex_arrays(theta)), light_full, ss, truth, oracle, RefineConfig()))
        row["gap_closed"] = gap(np.asarray(row["albedo_residuals"]))
        emit(row)
    print(f"initial albedo residual {r_init.mean():.4f}, oracle {r_orc.mean():.4f}", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
