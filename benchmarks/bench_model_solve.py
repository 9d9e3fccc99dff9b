"""The least-squares model update (``finetune --solver ls``) and its constrained variants, measured on a finished
demo workspace (docs/benchmarks.md, "The least-squares model update").

Usage:
    python benchmarks/bench_model_solve.py --workspace work --variant NAME[:key=value,...] [--variant ...]
        [--rounds 1] [--max-pixels 1000] [--cg-iterations 100] [--shard-images 0] [--threads 1] [--jsonl out.jsonl]

A variant is a name and :class:`~reflectmm_cli.finetune.model_solve.SolveConfig` fields (``pull``, ``harmonics``,
``robust``, ``update_bases``, ``pull_scale``, ...); ``initial`` (no update) and ``sgd`` (the workspace's finetuned model) are the
reference rows. With ``--load DIR`` the variants are not solved but read from ``DIR/NAME.npz`` (written by
``--save`` on another workspace): models made on one population, measured on another. Every variant runs with the same data, rounds, pixels and CG iterations. Measures, per row:

- expressive power: the relative residual of the held-out wild identities' true per-vertex diffuse albedo and lobe
  weights after projection onto the model (``evaluate expressive``'s measure, prior 1e-3), and the gap to the
  oracle (a model of the same size from the training identities' truth) closed from the initial model (the
  per-identity residuals are kept for paired CIs, ``--pair``);
- the refined PSNR / SSIM of the test images from zero coefficients (the model alone, no encoder), and the gain
  over the initial model per image with its 95 % CI;
- the model update's CPU time (``time.process_time``, all threads) and wall time, and per round the solver's
  relative residual (the CG's where it stopped; the Cholesky solve's).

How each round is solved (:func:`solve_variant`): by the one-process CG of
:func:`~reflectmm_cli.finetune.model_solve.alternate` (``--cg-iterations``, tolerance 1e-4), or, with
``--shard-images N`` (or a variant's ``shard_images=N``) and harmonics, exactly: the map-reduce of
:func:`~reflectmm_cli.finetune.model_mapreduce.alternate_sharded` run serially in this process (groups of N
training images, the same refinement, pixels and pull), whose reduced normal equations are solved by Cholesky.
Only the solve differs between the two.

The model of the last round is measured (``keep_best=False``), whatever the validation split says; the report records
the validation objective of every round.

The truth is read only by the measures, never by the update.
"""
from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np


def _variant(spec: str) -> tuple[str, dict]:
    name, _, rest = spec.partition(":")
    kw = {}
    for item in filter(None, rest.split(",")):
        k, _, v = item.partition("=")
        kw[k] = float(v) if k in ("pull", "robust", "cg_tol") else v if k == "pull_scale" else int(v)
    return name, kw


def solve_variant(model, light, shards, cfg, mesh, *, threads: int = 1, log=None) -> tuple[dict, object]:
    """One variant's update with the bench's settings: :func:`~reflectmm_cli.finetune.model_solve.alternate` (the
    CG), or with ``cfg.shard_images > 0`` the exact map-reduce (:func:`~reflectmm_cli.finetune.model_mapreduce.
    alternate_sharded`, serial executor, ``threads`` torch threads). The last round is kept (``keep_best=False``).

    Returns:
        (``vertex_*`` arrays, float32, the :class:`~reflectmm_cli.finetune.model_solve.SolveReport`).
    """
    from reflectmm_cli.errors import ReflectmmError
    from reflectmm_cli.finetune.model_mapreduce import alternate_sharded
    from reflectmm_cli.finetune.model_solve import alternate

    if cfg.shard_images <= 0:
        return alternate(model, light, shards, cfg, mesh=mesh, log=log, keep_best=False)
    if cfg.harmonics <= 0:
        raise ReflectmmError("bench_model_solve: the exact solve (shard_images) needs harmonics > 0; "
                             "per vertex the map-reduce runs the same CG")
    return alternate_sharded(model, light, shards, cfg, mesh=mesh, log=log, keep_best=False, executor="serial",
                             jobs=1, threads=threads)


def held_out_image_metrics(ss, encoder, model, light, refine=None) -> tuple[np.ndarray, np.ndarray]:
    """Per-image PSNR and SSIM (float64) of the shards' test images reconstructed with ``model`` and ``light``: by
    ``encoder`` (None: from zero coefficients) and, with ``refine``, refined per image."""
    from reflectmm_cli.evaluation.reconstruction_eval import image_metrics_table
    from reflectmm_cli.finetune.reconstruct import reconstruct

    rec = reconstruct(ss, encoder, model, light, split="test", refine=refine)
    fm = image_metrics_table(rec.full, rec.image, rec.face_mask, str(rec.encoding[0]))["per_image"]
    return np.asarray(fm.per_image["psnr"], np.float64), np.asarray(fm.per_image["ssim"], np.float64)


def _measure(model, light, ss, truth, oracle, refine) -> dict:
    from reflectmm_cli.evaluation.expressive import projection_residuals

    out = {}
    for part, key in (("albedo", "vertex_albedo"), ("weights", "vertex_weights")):
        for name, m in (("model", model), ("oracle", oracle)):
            if m is None:
                continue
            mean = m[f"{key}_mean"] if isinstance(m, dict) else getattr(m, f"{key}_mean")
            basis = m[f"{key}_basis"] if isinstance(m, dict) else getattr(m, f"{key}_basis")
            sigma = m["sigma"] if isinstance(m, dict) else m.sigma
            r = projection_residuals(mean, basis, sigma, truth[part], truth["skin"], prior=1e-3)
            out[f"{part}_residual" + ("" if name == "model" else "_oracle")] = float(r.mean())
            if name == "model":
                out[f"{part}_residuals"] = r.astype(np.float64).tolist()
    psnr, ssim = held_out_image_metrics(ss, None, model, light, refine)
    out["psnr"], out["ssim"] = psnr.tolist(), ssim.tolist()
    return out


def _ci(d) -> str:
    from reflectmm_cli.evaluation.face_metrics import mean_ci

    c = mean_ci(np.asarray(d, np.float64))
    return f"{c['mean']:+.2f} ± {c['half_width']:.2f}" if abs(c["mean"]) >= 0.05 or c["half_width"] >= 0.05 \
        else f"{c['mean']:+.4f} ± {c['half_width']:.4f}"


def summarise(paths: list[Path]) -> str:
    """The markdown table of JSON-lines files written by ``--jsonl`` (the row ``initial`` is the reference)."""
    rows = [json.loads(line) for p in paths for line in open(p) if line.strip()]
    ini = next(r for r in rows if r["variant"] == "initial")
    out = ["| update | config | rounds | training objective | validation objective | pixels left out | albedo "
           "residual (gap closed) | lobe-weight residual (gap closed) | refined test PSNR | Δ PSNR vs initial | "
           "SSIM | Δ SSIM vs initial | solve (relative residual) | CPU s |", "|" + "---|" * 14]
    for r in rows:
        gap = [(ini[k] - r[k]) / (ini[k] - r[k + "_oracle"]) for k in ("albedo_residual", "weights_residual")]
        rep = r.get("report", {}).get("rounds", [])
        tr = f"{rep[-1]['solve_start']:.5f} → {rep[-1]['solve_end']:.5f}" if len(rep) > 1 else "–"
        va = " → ".join(f"{x['val_objective']:.5f}" for x in rep) if rep else "–"
        lo = f"{100 * rep[-1].get('pixels_left_out', 0):.1f} %" if len(rep) > 1 else "–"
        cfg = ", ".join(f"{k} {v:g}" if not isinstance(v, str) else f"{k} {v}" for k, v in r["config"].items()) \
            or "–"
        dp = np.subtract(r["psnr"], ini["psnr"])
        ds = np.subtract(r["ssim"], ini["ssim"])
        same = r is ini or not (dp.any() or ds.any())
        cpu = f"{r['cpu_s']:.0f}" if "cpu_s" in r else "–"
        sol = "–" if len(rep) < 2 else ", ".join(
            (f"CG {x['cg_iterations']}" if x["cg_iterations"] else "Cholesky") + f" ({x['cg_rel_residual']:.1e})"
            for x in rep[1:])
        out.append(f"| {r['variant']} | {cfg} | {r['rounds'] if rep else '–'} | {tr} | {va} | {lo} | "
                   f"{r['albedo_residual']:.3f} ({100 * gap[0]:+.0f} %) | {r['weights_residual']:.3f} "
                   f"({100 * gap[1]:+.0f} %) | {np.mean(r['psnr']):.2f} | {'–' if same else _ci(dp)} | "
                   f"{np.mean(r['ssim']):.3f} | {'–' if same else _ci(ds)} | {sol} | {cpu} |")
    oracle = rows[0]
    out.append(f"| oracle | – | – | – | – | – | {oracle['albedo_residual_oracle']:.3f} | "
               f"{oracle['weights_residual_oracle']:.3f} | – | – | – | – | – | – |")
    return "\n".join(out)


def pairs(paths: list[Path], specs: list[str]) -> str:
    """:func:`pair_table` of the rows of the ``--jsonl`` files (a later row of a variant replaces an earlier one)."""
    return pair_table([json.loads(line) for p in paths for line in open(p) if line.strip()], specs)


def pair_table(row_list: list[dict], specs: list[str]) -> str:
    """``A − B`` for each ``A:B`` of ``specs`` (rows named by their ``variant``): the per-test-image gain in refined
    PSNR and SSIM, the per-held-out-identity change of the albedo and lobe-weight residuals (negative: closer to the
    truth) and the change of the gap closed, each as mean ± 95 % CI (Student t)."""
    rows = {r["variant"]: r for r in row_list}
    ini = rows.get("initial")
    out = ["| pair | Δ PSNR | Δ SSIM | Δ albedo residual | Δ lobe-weight residual | Δ albedo gap closed | "
           "Δ lobe-weight gap closed |", "|---|---|---|---|---|---|---|"]
    for spec in specs:
        an, _, bn = spec.partition(":")
        A, B = rows[an], rows[bn]
        cells = [_ci(np.subtract(A[k], B[k])) for k in ("psnr", "ssim")]
        for k in ("albedo", "weights"):
            d = np.subtract(A[f"{k}_residuals"], B[f"{k}_residuals"])
            cells.append(_ci4(d))
        for k in ("albedo", "weights"):
            if ini is None:
                cells.append("–")
                continue
            span = np.mean(ini[f"{k}_residuals"]) - A[f"{k}_residual_oracle"]
            d = np.subtract(B[f"{k}_residuals"], A[f"{k}_residuals"]) / span
            c = _mean_ci(d)
            cells.append(f"{100 * c['mean']:+.1f} ± {100 * c['half_width']:.1f} %")
        out.append(f"| {an} − {bn} | " + " | ".join(cells) + " |")
    return "\n".join(out)


def _mean_ci(d) -> dict:
    from reflectmm_cli.evaluation.face_metrics import mean_ci

    return mean_ci(np.asarray(d, np.float64))


def _ci4(d) -> str:
    c = _mean_ci(d)
    return f"{c['mean']:+.4f} ± {c['half_width']:.4f}"


def encoder_table(ws: Path, specs: list[str]) -> str:
    """Table 2's encoder-only PSNR / SSIM of the test images for ``NAME=MODEL,ENCODER`` rows (the first row is the
    reference of the per-image gains)."""
    from reflectmm_cli.finetune.encoder import load_encoder
    from reflectmm_cli.finetune.shards import load_shards
    from reflectmm_cli.finetune.train import load_models

    ss = load_shards(sorted((ws / "prepare-wild").glob("shard_*.npz")))
    out = ["| method | model | encoder | PSNR | Δ PSNR | SSIM | Δ SSIM |", "|---|---|---|---|---|---|---|"]
    ref = None
    for spec in specs:
        name, _, paths = spec.partition("=")
        mp, ep = paths.split(",")
        m, lt = load_models(mp, ws / "build-light-pca" / "build-light-pca.npz")
        ps, ss_ = held_out_image_metrics(ss, load_encoder(ep, "cpu")[0], m, lt)
        ref = ref or (ps, ss_)
        gain = ("–", "–") if ps is ref[0] else (_ci(ps - ref[0]), _ci(ss_ - ref[1]))
        out.append(f"| {name} | {Path(mp).name} | {Path(ep).name} | {ps.mean():.2f} | {gain[0]} | {ss_.mean():.3f} | "
                   f"{gain[1]} |")
    return "\n".join(out)


def changes_table(ws: Path, load: Path, names: list[str]) -> str:
    """The relative change ‖x − x₀‖ / ‖x₀‖ of each mean and basis of the variants saved in ``load`` (by ``--save``)
    against the workspace's initial model, in per cent."""
    from reflectmm_cli.finetune.train import load_models

    model, _ = load_models(ws / "build-pca" / "build-pca.npz", ws / "build-light-pca" / "build-light-pca.npz")
    out = ["| variant | albedo mean | albedo bases 0…M−1 | lobe-weight mean | lobe-weight bases 0…M−1 |",
           "|---|---|---|---|---|"]
    for name in names:
        saved = dict(np.load(load / f"{name}.npz"))
        cells = []
        for key in ("vertex_albedo_mean", "vertex_albedo_basis", "vertex_weights_mean", "vertex_weights_basis"):
            x0 = np.asarray(getattr(model, key), np.float64)
            x = np.asarray(saved[key], np.float64)
            if key.endswith("basis"):
                x0 = x0[:x.shape[0]]
                rel = np.linalg.norm((x - x0).reshape(len(x), -1), axis=1) / np.linalg.norm(x0.reshape(len(x), -1),
                                                                                              axis=1)
                cells.append(" ".join(f"{100 * r:.0f}" for r in rel))
            else:
                cells.append(f"{100 * np.linalg.norm(x - x0) / np.linalg.norm(x0):.3g}")
        out.append(f"| {name} | " + " | ".join(cells) + " |")
    return "\n".join(out)


def append_jsonl(path: Path | None, row: dict) -> None:
    """Append ``row`` as one JSON line to ``path`` (nothing when None): the ``--jsonl`` files of the benchmarks."""
    if path is not None:
        with open(path, "a") as f:
            f.write(json.dumps(row) + "\n")


def load_workspace(ws: Path):
    """What the model-update benchmarks read from a finished demo workspace: (initial model, light model, shards,
    face model, the synth wild truth of :func:`~reflectmm_cli.stages.evaluate_expressive.load_wild_truth`, the
    held-out identities' truth {albedo, weights, skin} stacked, the oracle model of the training identities)."""
    from reflectmm_cli.evaluation.expressive import oracle_model
    from reflectmm_cli.finetune.shards import load_shards
    from reflectmm_cli.finetune.train import load_models
    from reflectmm_cli.geometry.face_model import load_face_model
    from reflectmm_cli.stages.evaluate_expressive import load_wild_truth

    model, light = load_models(ws / "build-pca" / "build-pca.npz", ws / "build-light-pca" / "build-light-pca.npz")
    ss = load_shards(sorted((ws / "prepare-wild").glob("shard_*.npz")))
    fm = load_face_model(ws / "synth-wild" / "face_model.npz")
    tr = load_wild_truth(ws / "synth-wild")
    held = tr["heldout"]
    truth = {"albedo": np.stack([tr["albedo"][i] for i in held]).astype(np.float64),
             "weights": np.stack([tr["weights"][i] for i in held]).astype(np.float64),
             "skin": np.stack([tr["skin"][i] for i in held]).astype(bool)}
    oracle = oracle_model(np.stack([tr["albedo"][i] for i in tr["train"]]),
                          np.stack([tr["weights"][i] for i in tr["train"]]), model.exponents, model.n_components)
    return model, light, ss, fm, tr, truth, oracle


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--workspace", type=Path, default=Path("work"))
    ap.add_argument("--variant", action="append", default=[], help="NAME[:key=value,...]; initial, sgd: references")
    ap.add_argument("--rounds", type=int, default=1)
    ap.add_argument("--max-pixels", type=int, default=1000)
    ap.add_argument("--cg-iterations", type=int, default=100)
    ap.add_argument("--shard-images", type=int, default=0,
                    help="solve every round exactly: the map-reduce in this process over groups of N training images "
                         "and a Cholesky solve (needs harmonics; a variant's shard_images=N overrides; 0: the CG)")
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--jsonl", type=Path, default=None, help="append one JSON line per row")
    ap.add_argument("--save", type=Path, default=None, help="write each solved variant's per-vertex arrays here")
    ap.add_argument("--encoder", action="append", default=[],
                    help="NAME=MODEL,ENCODER: print Table 2's encoder-only rows of the test images and exit")
    ap.add_argument("--summarise", type=Path, nargs="+", default=None,
                    help="print the markdown table of these --jsonl files and exit")
    ap.add_argument("--pair", action="append", default=[],
                    help="A:B with --summarise: also print A − B per test image (PSNR, SSIM) and per held-out "
                         "identity (residuals), mean ± 95 %% CI")
    ap.add_argument("--load", type=Path, default=None,
                    help="measure the variants saved here by --save (another population's run) instead of solving")
    ap.add_argument("--changes", action="store_true",
                    help="print the relative change (%%) of every mean and basis of the variants saved in --load DIR "
                         "against the workspace's initial model and exit")
    a = ap.parse_args()
    if a.changes:
        print(changes_table(a.workspace, a.load, [_variant(v)[0] for v in a.variant]))
        return 0
    if a.summarise:
        print(summarise(a.summarise))
        if a.pair:
            print("\n" + pairs(a.summarise, a.pair))
        return 0
    import torch

    torch.set_num_threads(a.threads)
    if a.encoder:
        print(encoder_table(a.workspace, a.encoder))
        return 0

    from reflectmm_cli.finetune.model_solve import SolveConfig, with_solved
    from reflectmm_cli.finetune.refine import RefineConfig
    from reflectmm_cli.finetune.train import load_models

    torch.set_num_threads(a.threads)
    ws = a.workspace
    model, light, ss, fm, tr, truth, oracle = load_workspace(ws)
    refine = RefineConfig()
    for spec in a.variant:
        name, kw = _variant(spec)
        row = {"variant": name, "config": kw, "rounds": a.rounds, "max_pixels": a.max_pixels,
               "cg_iterations": a.cg_iterations, "threads": a.threads}
        if name == "initial":
            m = model
        elif name == "sgd":
            m = load_models(ws / "finetune" / "finetune.npz", ws / "build-light-pca" / "build-light-pca.npz")[0]
        elif a.load is not None:
            m = with_solved(model, dict(np.load(a.load / f"{name}.npz")))
        else:
            cfg = SolveConfig(rounds=a.rounds, max_pixels=a.max_pixels, cg_iterations=a.cg_iterations,
                              **({"shard_images": a.shard_images} | kw))
            t, w = time.process_time(), time.perf_counter()
            arrays, rep = solve_variant(model, light, ss, cfg, (fm.mean_shape, fm.triangles), threads=a.threads,
                                        log=lambda s: print(s, file=sys.stderr, flush=True))
            row["cpu_s"], row["wall_s"] = time.process_time() - t, time.perf_counter() - w
            row["shard_images"] = cfg.shard_images
            row["report"] = {"rounds": rep.rounds, "best_round": rep.best_round}
            m = with_solved(model, arrays)
            if a.save is not None:
                a.save.mkdir(parents=True, exist_ok=True)
                np.savez(a.save / f"{name}.npz", **arrays)
        row.update(_measure(m, light, ss, truth, oracle, refine))
        print(json.dumps({k: v for k, v in row.items() if k not in ("psnr", "ssim")} |
                         {"psnr_mean": float(np.mean(row["psnr"])), "ssim_mean": float(np.mean(row["ssim"]))}),
              flush=True)
        append_jsonl(a.jsonl, row)
    return 0


if __name__ == "__main__":
    sys.exit(main())
