"""fit-geometry's optimisation budget in the flash rounds: the demo's two chains (dlib's landmarks, and the annotated
reference with landmarks on every view) refitted with more L-BFGS iterations per flash round or more rounds.

Each identity is fitted with the params of the demo's recipe (read from recipes/synthetic.toml: ``fit-geometry``
and ``fit-geometry-annotated``) on its inputs in a finished demo workspace, with the given FitConfig overrides, one
process per identity (two at a time, one torch thread each). Printed: per chain and budget the mean vertex RMS
against the truth, the per-identity values, the summed CPU time, and per budget the ratio of the two chains by the
median identity (issue 23's measure).

    python benchmarks/bench_flash_budget.py --workspace WS --budget demo: --budget iters160:flash_iters=160 \\
        --budget iters400:flash_iters=400 --budget rounds8:flash_rounds=8

``--chain NAME CAPTURE_DIR FACE_MODEL RIG LANDMARK_SIGMA JAW_WEIGHT`` fits other chains instead (paths relative to
the workspace, or absolute): e.g. captures with the synthetic landmarks on the views where dlib found a face.
The ratio table then sets the first chain against the second.
"""
from __future__ import annotations

import argparse
import os
import time
from multiprocessing import Pool
from pathlib import Path

import numpy as np

from reflectmm_cli.params import parse_ids

RECIPE = Path(__file__).resolve().parents[1] / "recipes" / "synthetic.toml"
CHAINS = {
    # chain: (capture folder, face model, rig in the workspace, the recipe stage whose params the fit takes)
    "detector": ("preprocess-multipie", "face-model-embed/face-model-embed.npz", "calibrate-rig/rig.toml",
                 "fit-geometry"),
    "annotated": ("preprocess-annotated", "synth-multipie/face_model.npz", "calibrate-annotated/rig.toml",
                  "fit-geometry-annotated"),
}


def recipe_params(stage: str) -> dict:
    """The params of one fit-geometry stage of the demo's recipe, as the recipe declares them."""
    from reflectmm_cli.recipes.recipe import load_recipe

    return dict(load_recipe(RECIPE).stages[stage].params)


def parse_budget(text: str) -> tuple[str, dict]:
    """``NAME:key=value,key=value`` → (NAME, overrides); the values are converted to FitConfig's field types."""
    from reflectmm_cli.geometry_fit import FitConfig

    name, _, rest = text.partition(":")
    defaults = FitConfig()
    out = {}
    for item in filter(None, rest.split(",")):
        key, _, value = item.partition("=")
        if not hasattr(defaults, key):
            raise SystemExit(f"--budget {text}: FitConfig has no field {key!r}")
        out[key] = type(getattr(defaults, key))(float(value))
    return name, out


def _fit(job) -> tuple[str, float, float]:
    workspace, spec, identity, overrides = job
    import torch

    torch.set_num_threads(1)
    from reflectmm_cli.geometry_fit.identity import fit_identity
    from reflectmm_cli.stages.fit_geometry import config_from_params

    cap, fm, rig, params = spec
    cfg = config_from_params({**params, **overrides})
    t0 = time.process_time()
    arrays, _, _ = fit_identity(workspace / cap / f"{identity}.npz", workspace / fm, identity,
                                rig_path=workspace / rig, config=cfg,
                                truth_path=workspace / "synth-multipie" / "truth" / f"{identity}.npz")
    return identity, float(arrays["err_vertex_rmse_mm"]), time.process_time() - t0


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--workspace", required=True, type=Path)
    ap.add_argument("--budget", action="append", required=True, help="NAME:key=value,... (FitConfig overrides)")
    ap.add_argument("--ids", default="001-008", help="e.g. 001-008 or 001,003")
    ap.add_argument("--processes", type=int, default=2)
    ap.add_argument("--chain", nargs=6, action="append",
                    metavar=("NAME", "CAPTURE_DIR", "FACE_MODEL", "RIG", "LANDMARK_SIGMA", "JAW_WEIGHT"))
    args = ap.parse_args(argv)
    os.environ.setdefault("REFLECTMM_QUIET", "1")
    ids = parse_ids(args.ids)
    budgets = [parse_budget(b) for b in args.budget]
    print("| budget | chain | vertex RMS mm, mean | per identity | CPU s (sum) |")
    print("|---|---|---|---|---|")
    chains = {name: (cap, fm, rig, recipe_params(stage)) for name, (cap, fm, rig, stage) in CHAINS.items()}
    if args.chain:  # the annotated reference's settings, with the chain's landmark noise and jaw weight
        base = recipe_params("fit-geometry-annotated")
        chains = {c[0]: (c[1], c[2], c[3], {**base, "landmark_sigma_px": float(c[4]),
                                           "landmark_weights": {"jaw": float(c[5])}}) for c in args.chain}
    errors = {}
    with Pool(args.processes) as pool:
        for name, overrides in budgets:
            for chain, spec in chains.items():
                res = pool.map(_fit, [(args.workspace, spec, i, overrides) for i in ids])
                err = np.array([r[1] for r in res])
                errors[name, chain] = err
                print(f"| {name} | {chain} | {err.mean():.3f} | {', '.join(f'{e:.2f}' for e in err)} | "
                      f"{sum(r[2] for r in res):.0f} |", flush=True)
    first, second = list(chains)[:2] if len(chains) > 1 else (None, None)
    if first is None:
        return 0
    print(f"\n| budget | {first} ÷ {second}, median identity | identities within 1.3× |")
    print("|---|---|---|")
    for name, _ in budgets:
        ratio = errors[name, first] / errors[name, second]
        print(f"| {name} | {np.median(ratio):.2f} | {int((ratio <= 1.3).sum())} of {len(ratio)} |")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
