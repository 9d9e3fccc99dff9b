"""The two model updates of ``finetune`` at equal CPU time (issue 21 §3): the paper's joint SGD (phase 2 with the
model trainable) against the least-squares update (``--solver ls``: refine, solve, then the encoder trained on the
solved model), with the control (phase 2 with the model frozen) at every budget. docs/benchmarks.md, "The two
model updates at equal CPU time".

Usage:
    python benchmarks/bench_update_budget.py --workspace work --scratch /tmp/budget --seeds 0,1,2 \\
        --run control2:model-lr=0,epochs2=2 --run sgd2:epochs2=2 ... \\
        --run ls1:solver=ls,ls-harmonics=200,ls-pull=300,ls-rounds=1,ls-shard-images=128,model-lr=0,epochs2=2 \\
        --jsonl budget.jsonl
    python benchmarks/bench_update_budget.py --summarise budget.jsonl [--workspace work]

Every run is one ``reflectmm finetune`` process with the demo's settings (``--common``; recipes/synthetic.toml's
finetune stage), one torch thread, no preview PNGs, started at phase 2 from the same seed's phase-1 encoder. That
encoder is made once per seed by a control run of one phase-2 epoch (a run that trains phase 1 itself; its phase-1
encoder is then shared, which ``finetune`` tests to equal training it again). A run's CPU time is the user + system
time of its process (``resource.getrusage`` of the children), so it counts start-up, data loading and writing the
outputs alike for every method; the phase-1 encoder's time is left out of every run. A run given ``phase1=own``
trains its own phase 1 instead (with ``solver=ls``: on the solved model, as recipes/synthetic.toml's finetune
stage does), and its CPU time counts it. A run given ``model=oracle`` starts from the oracle (below; ``reflectmm
build-baseline --kind oracle``) instead of the workspace's build-pca model; with ``model-lr=0,phase1=own`` that is
the control's schedule on the oracle, the ceiling of the encoder-only gain (what an encoder of this budget gains
from a model that already is the training population's).

Measures per run (the truth is read only here, never by a run):

- encoder only: PSNR / SSIM of the test images reconstructed by the run's encoder with the run's model (Table 2);
- the model alone: the test images refined from zero coefficients with the run's model (PSNR / SSIM), and the
  expressive power of ``evaluate expressive`` (the held-out wild identities' true albedo and lobe weights
  projected onto the model; the gap to the oracle closed from the initial model).

``--oracle`` adds the oracle's row (the expressive-power measure's model of the same size, built from the training
identities' truth, refined from zero like the runs' models). ``--summarise`` prints the table of every run (median CPU over the seeds; measures as the mean over seeds) and, for
each ``--pair A:B``, A − B per test image and seed (PSNR, SSIM) and per held-out identity and seed (albedo residual),
mean ± 95 % CI, with the ratio of the median CPU times.
"""
from __future__ import annotations

import argparse
import json
import os
import resource
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))

#: recipes/synthetic.toml's finetune settings (the demo's) but the phase-2 epochs; a control run sets model_lr 0,
#: a least-squares run solver ls and its options.
COMMON = dict(arch="resnet18", width=32, batch_size=8, epochs1=6, lr1=1e-3, lr2=1e-4, model_lr=1e-4, w_upd=1.0)


def _run_spec(spec: str) -> tuple[str, dict]:
    name, _, rest = spec.partition(":")
    kw = {}
    for item in filter(None, rest.split(",")):
        k, _, v = item.partition("=")
        kw[k] = v
    return name, kw


def phase1_mode(name: str, kw: dict) -> tuple[dict, bool]:
    """A run's options without ``phase1``, and whether it trains its own phase 1 (``phase1=own``; default
    ``shared``: phase 2 from the seed's shared phase-1 encoder)."""
    opts = dict(kw)
    mode = opts.pop("phase1", "shared")
    if mode not in ("shared", "own"):
        raise SystemExit(f"bench_update_budget: run {name}: phase1 must be shared or own, got {mode!r}")
    return opts, mode == "own"


def model_mode(name: str, kw: dict) -> tuple[dict, str]:
    """A run's options without ``model``, and the model it starts from (``initial``, the default: the workspace's
    build-pca; ``oracle``: the oracle model of :func:`write_oracle_model`)."""
    opts = dict(kw)
    mode = opts.pop("model", "initial")
    if mode not in ("initial", "oracle"):
        raise SystemExit(f"bench_update_budget: run {name}: model must be initial or oracle, got {mode!r}")
    return opts, mode


def write_oracle_model(ws: Path, out: Path) -> Path:
    """The oracle as a ``reflectance-model`` artifact of the size of the workspace's build-pca model, made by the
    project's own ``reflectmm build-baseline --kind oracle`` (the model ``evaluate expressive`` measures against,
    array for array)."""
    cmd = ["reflectmm", "-q", "build-baseline", "--kind", "oracle", "--truth", str(ws / "synth-wild"),
           "--like", str(ws / "build-pca" / "build-pca.npz"),
           "--face-model", str(ws / "synth-wild" / "face_model.npz"), "--no-preview", "-w", str(out.parent),
           "-o", str(out)]
    r = subprocess.run(cmd, capture_output=True, text=True)
    if r.returncode != 0:
        raise SystemExit(f"bench_update_budget: {' '.join(cmd)} failed:\n{r.stderr[-2000:]}")
    return out


def _args(kw: dict) -> list[str]:
    out = []
    for k, v in kw.items():
        out += [f"--{k.replace('_', '-')}", str(v)]
    return out


def _finetune(ws: Path, out: Path, kw: dict, *, phase1: Path | None, log, model: Path | None = None) -> float:
    """One ``reflectmm finetune`` process; returns its CPU seconds (user + system)."""
    cmd = ["reflectmm", "finetune", "-w", str(ws), "--output", str(out), "--threads", "1", "--samples", "0"]
    cmd += _args(COMMON | kw)
    if model is not None:
        cmd += ["--model", str(model)]
    if phase1 is not None:
        cmd += ["--phase1-encoder", str(phase1)]
    if (ws / "synth-wild" / "face_model.npz").is_file():  # the mesh of --ls-harmonics
        cmd += ["--face-model", str(ws / "synth-wild" / "face_model.npz")]
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    t = time.perf_counter()
    r = subprocess.run(cmd, capture_output=True, text=True)
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    if r.returncode != 0:
        raise SystemExit(f"bench_update_budget: {' '.join(cmd)} failed:\n{r.stderr[-2000:]}")
    cpu = (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime)
    log(f"  {out.name}: {cpu:.1f} CPU s, {time.perf_counter() - t:.1f} s wall")
    return cpu


def _measure_model(model, light, ss, truth, oracle) -> dict:
    from bench_model_solve import _measure

    from reflectmm_cli.finetune.refine import RefineConfig

    m = _measure(model, light, ss, truth, oracle, RefineConfig())
    return {"refined_psnr": m.pop("psnr"), "refined_ssim": m.pop("ssim")} | m


def _measure_encoder(model, light, ss, encoder_path: Path) -> dict:
    from bench_model_solve import held_out_image_metrics

    from reflectmm_cli.finetune.encoder import load_encoder

    psnr, ssim = held_out_image_metrics(ss, load_encoder(encoder_path, "cpu")[0], model, light)
    return {"psnr": psnr.tolist(), "ssim": ssim.tolist()}


def oracle_as_model(model, oracle: dict):
    """A copy of ``model`` whose per-vertex means, bases and σ are the oracle's
    (:func:`~reflectmm_cli.evaluation.expressive.oracle_model`), so that it renders and refines like any model."""
    import copy

    out = copy.deepcopy(model)
    for k in ("vertex_albedo_mean", "vertex_albedo_basis", "vertex_weights_mean", "vertex_weights_basis", "sigma"):
        setattr(out, k, np.asarray(oracle[k], np.float32))
    return out


def run(a) -> int:
    import torch

    from bench_model_solve import append_jsonl, load_workspace

    from reflectmm_cli.finetune.train import load_models

    torch.set_num_threads(1)
    log = lambda s: print(s, file=sys.stderr, flush=True)  # noqa: E731
    ws = a.workspace.resolve()
    model0, light, ss, fm, tr, truth, oracle = load_workspace(ws)
    lpath = ws / "build-light-pca" / "build-light-pca.npz"
    a.scratch.mkdir(parents=True, exist_ok=True)
    model_cache: dict[str, dict] = {}
    if a.oracle:  # the oracle of the expressive-power measure, refined like the runs' models (no encoder)
        log("oracle: a model of the same size from the training identities' truth, refined on the test images")
        row = {"run": "oracle", "seed": None, "options": {}, "cpu_s": None, "workspace": str(ws)}
        row.update(_measure_model(oracle_as_model(model0, oracle), light, ss, truth, oracle))
        append_jsonl(a.jsonl, row)
    for seed in a.seeds:
        sd = a.scratch / f"seed{seed}"
        sd.mkdir(exist_ok=True)
        p1 = sd / "phase1.npz"
        phase1 = sd / "phase1_encoder_phase1.safetensors"
        shared = any(not phase1_mode(*_run_spec(spec))[1] for spec in a.run)
        if shared and not phase1.is_file():  # only when a run starts from it
            log(f"seed {seed}: phase 1 (a control run of one phase-2 epoch)")
            _finetune(ws, p1, {"seed": seed, "model_lr": 0.0, "epochs2": 1}, phase1=None, log=log)
        for spec in a.run:
            name, kw = _run_spec(spec)
            out = sd / f"{name}.npz"
            log(f"seed {seed}: {name}")
            opts, own = phase1_mode(name, kw)
            opts, start = model_mode(name, opts)
            start_path = None
            if start == "oracle":
                if not own:
                    raise SystemExit(f"bench_update_budget: run {name}: model=oracle needs phase1=own (the shared "
                                     "phase-1 encoder was trained on the initial model)")
                start_path = a.scratch / "oracle_model.npz"
                if not start_path.is_file():
                    write_oracle_model(ws, start_path)
            cpu = _finetune(ws, out, {"seed": seed} | opts, phase1=None if own else phase1, log=log, model=start_path)
            m, _ = load_models(out, lpath)
            key = str(out)
            row = {"run": name, "seed": seed, "options": kw, "cpu_s": cpu, "workspace": str(ws)}
            row.update(_measure_encoder(m, light, ss, sd / f"{name}_encoder.safetensors"))
            # the model alone: the control's model is the initial one; measured once per distinct model file
            frozen = float(opts.get("model-lr", opts.get("model_lr", 1))) == 0 and opts.get("solver", "sgd") == "sgd"
            key = start if frozen else key
            if key not in model_cache:
                start_model = oracle_as_model(model0, oracle) if start == "oracle" else model0
                model_cache[key] = _measure_model(start_model if frozen else m, light, ss, truth, oracle)
            row.update(model_cache[key])
            log(f"  encoder PSNR {np.mean(row['psnr']):.2f} SSIM {np.mean(row['ssim']):.3f}; refined "
                f"{np.mean(row['refined_psnr']):.2f} / {np.mean(row['refined_ssim']):.3f}; albedo residual "
                f"{row['albedo_residual']:.4f}")
            append_jsonl(a.jsonl, row)
    return 0


def _ci(d, digits=2) -> str:
    from reflectmm_cli.evaluation.face_metrics import mean_ci

    c = mean_ci(np.asarray(d, np.float64))
    return f"{c['mean']:+.{digits}f} ± {c['half_width']:.{digits}f}"


def summarise(paths: list[Path], pairs: list[str]) -> str:
    rows = [json.loads(line) for p in paths for line in open(p) if line.strip()]
    by: dict[str, list[dict]] = {}
    for r in rows:
        by.setdefault(r["run"], []).append(r)
    orc = by.pop("oracle", [None])[0]
    refined = "refined PSNR (gap to the oracle closed)" if orc is not None else "refined PSNR"
    out = [f"| run | options | seeds | CPU s (median) | encoder PSNR | encoder SSIM | {refined} | refined SSIM | "
           "albedo residual (gap closed) | lobe-weight residual (gap closed) |", "|" + "---|" * 10]
    # the initial model's measures: those of a run whose model stayed frozen (a control), averaged over its seeds
    ctl = next((rs for rs in by.values() if float(rs[0]["options"].get("model-lr", 1)) == 0
                and rs[0]["options"].get("solver", "sgd") == "sgd"
                and rs[0]["options"].get("model", "initial") == "initial"), None)
    ini = None if ctl is None else {k: float(np.mean([np.mean(r[k]) for r in ctl]))
                                    for k in ("refined_psnr", "albedo_residual", "weights_residual")}
    ini_psnr = ini["refined_psnr"] if ini else None
    for name, rs in by.items():
        cpu = float(np.median([r["cpu_s"] for r in rs]))
        enc_p = np.mean([np.mean(r["psnr"]) for r in rs])
        enc_s = np.mean([np.mean(r["ssim"]) for r in rs])
        ref_p = np.mean([np.mean(r["refined_psnr"]) for r in rs])
        ref_s = np.mean([np.mean(r["refined_ssim"]) for r in rs])
        cells = []
        for k in ("albedo", "weights"):  # the mean over seeds (an SGD run's model depends on its seed)
            v = float(np.mean([r[f"{k}_residual"] for r in rs]))
            o = rs[0][f"{k}_residual_oracle"]
            i0 = ini[f"{k}_residual"] if ini else None
            cells.append(f"{v:.3f}" + (f" ({100 * (i0 - v) / (i0 - o):+.0f} %)" if i0 is not None else ""))
        opts = ", ".join(f"{k} {v}" for k, v in rs[0]["options"].items())
        gp = ""  # the gap to the oracle's refined PSNR closed from the initial model
        if orc is not None and ini_psnr is not None:
            gp = f" ({100 * (ref_p - ini_psnr) / (np.mean(orc['refined_psnr']) - ini_psnr):+.0f} %)"
        out.append(f"| {name} | {opts} | {len(rs)} | {cpu:.0f} | {enc_p:.2f} | {enc_s:.3f} | {ref_p:.2f}{gp} | "
                   f"{ref_s:.3f} | {cells[0]} | {cells[1]} |")
    if orc is not None:
        out.append(f"| oracle | the training identities' truth | – | – | – | – | {np.mean(orc['refined_psnr']):.2f} | "
                   f"{np.mean(orc['refined_ssim']):.3f} | {orc['albedo_residual']:.3f} | "
                   f"{orc['weights_residual']:.3f} |")
    if pairs:
        out += ["", "| pair | Δ encoder PSNR | Δ encoder SSIM | Δ refined PSNR | Δ refined SSIM | Δ albedo residual "
                "| CPU ratio |", "|---|---|---|---|---|---|---|"]
        for spec in pairs:
            an, _, bn = spec.partition(":")
            A = {r["seed"]: r for r in by[an]}
            B = {r["seed"]: r for r in by[bn]}
            seeds = sorted(set(A) & set(B))
            cells = []
            for k in ("psnr", "ssim", "refined_psnr", "refined_ssim"):
                d = np.concatenate([np.subtract(A[s][k], B[s][k]) for s in seeds])
                cells.append(_ci(d, 2 if "psnr" in k else 4))
            d = np.concatenate([np.subtract(A[s]["albedo_residuals"], B[s]["albedo_residuals"]) for s in seeds])
            cells.append(_ci(d, 4))
            ratio = np.median([A[s]["cpu_s"] for s in seeds]) / np.median([B[s]["cpu_s"] for s in seeds])
            out.append(f"| {an} − {bn} | " + " | ".join(cells) + f" | {ratio:.2f} |")
    return "\n".join(out)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--workspace", type=Path, default=Path("work"))
    ap.add_argument("--scratch", type=Path, default=Path("/tmp/bench_update_budget"))
    ap.add_argument("--seeds", type=lambda s: [int(x) for x in s.split(",")], default=[0])
    ap.add_argument("--run", action="append", default=[],
                    help="NAME:option=value,... (finetune's options without the dashes; e.g. "
                         "sgd8:epochs2=8 or control8:model-lr=0,epochs2=8)")
    ap.add_argument("--oracle", action="store_true",
                    help="also measure the oracle (a model of the same size from the training identities' truth), "
                         "refined like the runs' models; --summarise then gives the gap to its refined PSNR closed")
    ap.add_argument("--jsonl", type=Path, default=None)
    ap.add_argument("--summarise", type=Path, nargs="+", default=None)
    ap.add_argument("--pair", action="append", default=[], help="A:B with --summarise")
    a = ap.parse_args()
    if a.summarise:
        print(summarise(a.summarise, a.pair))
        return 0
    os.environ.setdefault("OMP_NUM_THREADS", "1")
    return run(a)


if __name__ == "__main__":
    sys.exit(main())
