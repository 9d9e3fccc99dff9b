"""How much of fit-geometry's camera error is the head's rotation: per identity, the rotation about the model
origin (the head) that best carries the fitted centres of the views *with landmarks* onto the true ones, and
every view's centre error before and after that rotation.

A camera centre in model space is off either because the view was placed badly relative to the others, or because
the whole head sits turned in the rig (then every camera of the identity is off together, by about the angle times
the 1.3 m distance). The rotation is fitted to the views with landmarks only, so the errors it leaves on the views
without landmarks measure their placement relative to the others, which the truth did not take part in.

    python benchmarks/bench_head_rotation.py --workspace WS [--stage fit-geometry] [--truth-dir DIR]

Prints one line per identity (the rotation as x / y / z components in degrees: x is the pitch, y the yaw, z the
roll; the model's +y is up) and a summary of the views with and without landmarks.
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np


def head_rotation(fitted: np.ndarray, true: np.ndarray) -> np.ndarray:
    """(3, 3) rotation R (about the origin) that minimises Σ‖R·fitted_i − true_i‖² over the (N, 3) centres.

    Kabsch without centring: the turn is about the head, which sits at the model's origin, not about the cameras'
    centroid, so :func:`reflectmm_cli.geometry.align.rigid_align` (which always fits a shift) does not apply."""
    H = np.asarray(fitted, np.float64).T @ np.asarray(true, np.float64)
    U, _, Vt = np.linalg.svd(H)
    D = np.diag([1.0, 1.0, np.sign(np.linalg.det(Vt.T @ U.T))])
    return Vt.T @ D @ U.T


def rotation_degrees(R: np.ndarray) -> np.ndarray:
    """(3,) rotation vector of R in degrees."""
    from scipy.spatial.transform import Rotation

    return Rotation.from_matrix(R).as_rotvec(degrees=True)


def split(fitted: np.ndarray, true: np.ndarray, marked: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(rotation (3, 3), error before (V,), error after (V,)) of one identity's (V, 3) centres; the rotation is
    fitted to the ``marked`` (V,) views (all views when fewer than 2 are marked)."""
    fitted, true = np.asarray(fitted, np.float64), np.asarray(true, np.float64)
    use = marked if marked.sum() >= 2 else np.ones(len(marked), bool)
    R = head_rotation(fitted[use], true[use])
    before = np.linalg.norm(fitted - true, axis=1)
    after = np.linalg.norm(fitted @ R.T - true, axis=1)
    return R, before, after


def _summary(label: str, e: np.ndarray, limit: float) -> str:
    if e.size == 0:
        return f"{label}: none"
    return (f"{label}: median {np.median(e):.1f} mm, max {e.max():.1f} mm, {int((e <= limit).sum())} of {e.size} "
            f"within {limit:g} mm")


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--workspace", required=True, type=Path)
    ap.add_argument("--stage", default="fit-geometry")
    ap.add_argument("--truth-dir", type=Path, help="default WS/synth-multipie/truth")
    ap.add_argument("--limit", type=float, default=20.0, help="the goal's distance [mm]")
    args = ap.parse_args(argv)
    truth_dir = args.truth_dir or args.workspace / "synth-multipie" / "truth"
    fits = sorted((args.workspace / args.stage).glob("[0-9]*.npz"))
    if not fits:
        print(f"{args.workspace / args.stage}: no fits", file=sys.stderr)
        return 1
    acc = {k: [] for k in ("unmarked_before", "unmarked_after", "marked_before", "marked_after")}
    for path in fits:
        fit = np.load(path)
        truth = np.load(truth_dir / path.name)
        names = [str(n) for n in truth["camera_names"]]
        idx = [names.index(str(v)) for v in fit["view_names"]]
        marked = np.array([str(e).startswith("landmarks") for e in fit["view_evidence"]])
        R, before, after = split(fit["cam_centers"], truth["cam_centers"][idx], marked)
        rv = rotation_degrees(R)
        print(f"{path.stem}: head rotation x {rv[0]:+.2f}° y {rv[1]:+.2f}° z {rv[2]:+.2f}° "
              f"({int(marked.sum())} views with landmarks); centres {before.mean():.1f} → {after.mean():.1f} mm "
              f"mean, {before.max():.1f} → {after.max():.1f} mm max")
        acc["unmarked_before"] += list(before[~marked])
        acc["unmarked_after"] += list(after[~marked])
        acc["marked_before"] += list(before[marked])
        acc["marked_after"] += list(after[marked])
    a = {k: np.asarray(v) for k, v in acc.items()}
    print(_summary("views without landmarks, as fitted", a["unmarked_before"], args.limit))
    print(_summary("views without landmarks, after the head's rotation", a["unmarked_after"], args.limit))
    print(_summary("views with landmarks, as fitted", a["marked_before"], args.limit))
    print(_summary("views with landmarks, after the head's rotation", a["marked_after"], args.limit))
    return 0


if __name__ == "__main__":
    sys.exit(main())
