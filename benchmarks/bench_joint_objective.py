"""Whether fit-geometry's joint rounds are held back by where they start or by what they minimise.

For each identity of a synthetic workspace, the fit of the detector chain is run three times, identical but for the
state the joint rounds (``joint_rounds``; docs/fit-geometry.md, step 5) start from:

- ``fit``: the chain's own state (the stage as the recipe runs it);
- ``cameras``: the views without landmarks put at their true poses, the face, the head and the views with
  landmarks where the chain left them;
- ``truth``: everything at the truth: the face's coefficients, every view's pose and the head (the rig → model
  transform that best carries the rig's centres onto the true ones).

Each run reports its vertex RMS, its camera centres' errors, and the joint objective (landmark term, flash term,
shape prior, rig prior) at its final state and at the truth, both with the flash samples' weights and scale of the
final state. ``J(end) − J(truth)`` below zero means the run found a state that the objective prefers to the truth:
then no better start or longer optimisation brings the fit to the truth, and the limit is the objective itself
(its flash model, its rig, its landmarks). The truth start shows whether there is a minimum near the truth at all.

    python benchmarks/bench_joint_objective.py --workspace WS [--ids 001,006] [--starts fit,cameras,truth]
        [--recipe recipes/synthetic.toml] [--stage fit-geometry] [--set key=value ...]
        [--capture-dir DIR --face-model FILE --rig FILE --truth-dir DIR]

The fit's parameters are the stage's ``params`` in the recipe (``--set`` overrides one); its inputs are the
workspace's (WS/preprocess-multipie, WS/face-model-embed, WS/calibrate-rig, WS/synth-multipie/truth), or, for a
world made outside a workspace, ``--capture-dir``, ``--face-model``, ``--rig`` and ``--truth-dir`` (then
``--workspace`` is not needed). One line per identity and start on stdout; a summary at the end.
"""
from __future__ import annotations

import argparse
import statistics
import sys
from contextlib import contextmanager
from pathlib import Path

import numpy as np
import torch

STARTS = ("fit", "cameras", "truth")
TERMS = ("landmarks", "flash", "shape prior", "rig prior")
TRUE = "the truth"  # the true state itself (the start "truth" names the end of the rounds run from it)


def put_truth(prob, truth: dict, what: str) -> None:
    """Set the unknowns of a fit problem to the truth: ``what`` = ``"cameras"`` (the views without landmarks) or
    ``"truth"`` (the face's coefficients, every view and the head).  ``truth``: the synthetic truth's arrays
    (``camera_names``, ``R``, ``t``, ``cam_centers``, ``shape_coeffs``, ``exp_coeffs``).  The views set are marked
    registered (the joint rounds take only registered views)."""
    from reflectmm_cli.geometry.align import rigid_align
    from reflectmm_cli.geometry.rotations import matrix_to_axis_angle
    from reflectmm_cli.geometry_fit.fit import write_poses

    names = [str(n) for n in np.asarray(truth["camera_names"]).reshape(-1)]
    idx = [names.index(n) for n in prob.views.names]
    which = ~prob.marked if what == "cameras" else np.ones(prob.V, dtype=bool)
    write_poses(prob, prob.tt(np.asarray(truth["R"])[idx]), prob.tt(np.asarray(truth["t"])[idx]), which)
    if what == "truth":
        m = prob.model
        with torch.no_grad():
            prob.zs.copy_(prob.tt(np.asarray(truth["shape_coeffs"], np.float64)[:m.n_shape] / m.shape_sigma))
            k = prob.ze.numel()
            if k:
                prob.ze.copy_(prob.tt(np.asarray(truth["exp_coeffs"], np.float64)[:k] / m.exp_sigma[:k]))
            if prob.use_rig:
                Rh, th, _ = rigid_align(prob.views.rig_centers, np.asarray(truth["cam_centers"], np.float64)[idx])
                prob.dwh.copy_(matrix_to_axis_angle(prob.tt(Rh) @ prob.Rh0_t.T) / prob.r_unit)
                prob.dth.copy_((prob.tt(th) - prob.th0_t) / prob.t_unit)
    prob.registered |= which & ~prob.marked


def joint_terms(prob, sm):
    """The joint rounds' objective as a function of the current unknowns, term by term: returns ``terms()`` →
    (landmarks, flash, shape prior, rig prior) floats, with the flash term of the rounds (its view weights, blur,
    sample weights and scale fixed at the state of this call; :func:`reflectmm_cli.geometry_fit.fit.joint_flash_term`).
    Every registered view without landmarks is held to the head, as in the rounds."""
    from reflectmm_cli.geometry_fit import fit as F

    cfg = prob.cfg
    um = ~prob.marked
    with F._held_to_head(prob, um):
        _, flash, images_t = F.joint_flash_term(prob, sm, prob.marked | (um & prob.registered))

    def terms() -> tuple[float, float, float, float]:
        with F._held_to_head(prob, um), torch.no_grad():
            (lf, _, _), R, t = flash(images_t, residual=False)
            shape = 0.5 * (cfg.w_shape * (prob.zs ** 2).sum() + cfg.w_exp * (prob.ze ** 2).sum()) / prob.wsum
            return (float(cfg.w_landmark * prob.landmark_term(R, t)), float(cfg.w_flash * lf), float(shape),
                    float(prob.prior(R, t) - shape))

    return terms


def _errors(prob, truth: dict) -> tuple[float, np.ndarray]:
    """Vertex RMS (mm) and the (V,) camera centres' errors (mm) of the current state against the truth."""
    from reflectmm_cli.geometry.camera import camera_centers

    names = [str(n) for n in np.asarray(truth["camera_names"]).reshape(-1)]
    idx = [names.index(n) for n in prob.views.names]
    with torch.no_grad():
        X = prob.verts().cpu().numpy()
        R, t = (x.cpu().numpy() for x in prob.poses())
    v = float(np.sqrt(((X - np.asarray(truth["vertices"], np.float64)) ** 2).sum(-1).mean()))
    return v, np.linalg.norm(camera_centers(R, t) - np.asarray(truth["cam_centers"], np.float64)[idx], axis=-1)


@contextmanager
def compared(starts, truth: dict, record: dict):
    """Patch fit-geometry's joint rounds: after the chain's own rounds (state ``fit``), run them again from each
    other start of ``starts`` (the gate off: a view at its true place joins wherever the rig puts it), record each
    end state's errors and the objective at every end state and at the truth under two fixed sets of sample weights
    (those of the chain's end state, ``"at fit"``, and the truth's, ``"at truth"``), then put the chain's state
    back, so that the fit written is the chain's."""
    import dataclasses

    from reflectmm_cli.geometry_fit import fit as F

    original = F._joint_rounds

    def rounds(prob, sm):
        ends = {}
        before = F._snapshot(prob)
        out = original(prob, sm)
        ends["fit"] = F._snapshot(prob)
        cfg = prob.cfg
        for s in starts:
            if s == "fit":
                continue
            F._restore(prob, before)
            put_truth(prob, truth, s)
            prob.cfg = dataclasses.replace(cfg, joint_gate_mm=float("inf"))
            try:
                original(prob, sm)
            finally:
                prob.cfg = cfg
            ends[s] = F._snapshot(prob)
        for s, state in ends.items():
            F._restore(prob, state)
            record.setdefault(s, {})["errors"] = _errors(prob, truth)
        truth_state = dict(ends)
        F._restore(prob, before)
        put_truth(prob, truth, "truth")
        truth_state[TRUE] = F._snapshot(prob)
        for where in ("fit", "truth"):
            F._restore(prob, truth_state[where if where == "fit" else TRUE])
            terms = joint_terms(prob, sm)
            for s, state in truth_state.items():
                F._restore(prob, state)
                record.setdefault(s, {})[f"at {where}"] = terms()
        F._restore(prob, ends["fit"])
        return out

    F._joint_rounds = rounds
    try:
        yield
    finally:
        F._joint_rounds = original


def stage_params(recipe: Path, stage: str, overrides: list[str]) -> dict:
    """The params of the recipe's ``stage`` as ``reflectmm run --set STAGE.KEY=VALUE`` would give them (the
    project's recipe loader: ``[defaults]`` merged, each override a TOML value)."""
    from reflectmm_cli.errors import ReflectmmError
    from reflectmm_cli.recipes.recipe import load_recipe

    try:
        spec = load_recipe(recipe, [f"{stage}.{item}" for item in overrides]).stages.get(stage)
    except ReflectmmError as exc:
        sys.exit(str(exc))
    if spec is None:
        sys.exit(f"{recipe}: no stage {stage}")
    params = dict(spec.params)
    if int(params.get("joint_rounds", 0)) <= 0:
        sys.exit(f"{recipe}: stage {stage} runs no joint round (joint_rounds = 0): nothing to measure")
    return params


def run_one(inputs: dict, ident: str, starts, params: dict) -> dict:
    from reflectmm_cli.geometry_fit.identity import fit_identity
    from reflectmm_cli.stages.fit_geometry import config_from_params

    truth_path = inputs["truth_dir"] / f"{ident}.npz"
    with np.load(truth_path) as z:
        truth = {k: z[k] for k in z.files}
    record: dict = {}
    with compared(starts, truth, record):
        fit_identity(inputs["capture_dir"] / f"{ident}.npz", inputs["face_model"], ident, rig_path=inputs["rig"],
                     config=config_from_params(params), truth_path=truth_path)
    if not record:
        sys.exit(f"identity {ident}: the joint rounds did not run")
    return record


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--workspace", type=Path)
    ap.add_argument("--capture-dir", type=Path, help="default WS/preprocess-multipie")
    ap.add_argument("--face-model", type=Path, help="default WS/face-model-embed/face-model-embed.npz")
    ap.add_argument("--rig", type=Path, help="default WS/calibrate-rig/rig.toml")
    ap.add_argument("--truth-dir", type=Path, help="default WS/synth-multipie/truth")
    ap.add_argument("--ids", default="", help="comma-separated identities (default: every capture)")
    ap.add_argument("--starts", default=",".join(STARTS))
    ap.add_argument("--recipe", type=Path, default=Path(__file__).resolve().parents[1] / "recipes" / "synthetic.toml")
    ap.add_argument("--stage", default="fit-geometry", help="the recipe's stage whose params the fit takes")
    ap.add_argument("--set", action="append", default=[], metavar="KEY=VALUE")
    a = ap.parse_args(argv)
    starts = ["fit"] + [s for s in a.starts.split(",") if s and s != "fit"]
    bad = [s for s in starts if s not in STARTS]
    if bad:
        sys.exit(f"--starts: unknown start(s) {', '.join(bad)} (choose from {', '.join(STARTS)})")
    defaults = {"capture_dir": "preprocess-multipie", "face_model": "face-model-embed/face-model-embed.npz",
                "rig": "calibrate-rig/rig.toml", "truth_dir": "synth-multipie/truth"}
    inputs = {}
    for key, rel in defaults.items():
        given = getattr(a, key)
        if given is None and a.workspace is None:
            sys.exit(f"--{key.replace('_', '-')} or --workspace is needed")
        inputs[key] = given if given is not None else a.workspace / rel
        if not inputs[key].exists():
            sys.exit(f"{inputs[key]}: not found")
    ids = [i for i in a.ids.split(",") if i] or sorted(p.stem for p in inputs["capture_dir"].glob("*.npz"))
    if not ids:
        sys.exit(f"{inputs['capture_dir']}: no captures found")
    params = stage_params(a.recipe, a.stage, a.set)
    verts: dict[str, list[float]] = {s: [] for s in starts}
    deeper: dict[str, int] = {s: 0 for s in starts}
    for ident in ids:
        rec = run_one(inputs, ident, starts, params)
        for s in starts:
            v, cams = rec[s]["errors"]
            verts[s].append(v)
            J = {w: sum(rec[s][f"at {w}"]) for w in ("fit", "truth")}
            Jt = {w: sum(rec[TRUE][f"at {w}"]) for w in ("fit", "truth")}
            Jf = {w: sum(rec["fit"][f"at {w}"]) for w in ("fit", "truth")}
            if s != "fit" and all(J[w] < Jf[w] for w in J):
                deeper[s] += 1
            print(f"{ident} start {s:8s} vertex {v:.2f} mm  cameras within 20 mm {int((cams <= 20).sum())}/{len(cams)}"
                  f" (max {np.nanmax(cams):.1f})  J - J(truth), weights at fit {J['fit'] - Jt['fit']:+.4f}, at truth"
                  f" {J['truth'] - Jt['truth']:+.4f}  [" + " ".join(
                      f"{n} {d:+.4f}" for n, d in zip(TERMS, np.subtract(rec[s]['at truth'], rec[TRUE]['at truth'])))
                  + "]", flush=True)
    for s in starts:
        tail = "" if s == "fit" else (f"; its end is lower than the chain's under both weightings for {deeper[s]} "
                                      f"of {len(ids)} identities")
        print(f"start {s}: vertex RMS mean {statistics.mean(verts[s]):.2f} mm{tail}")


if __name__ == "__main__":
    main()
