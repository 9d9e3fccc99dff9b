"""Fitted faces against the truth, split into size and shape: per identity the vertex RMS as fitted (model space),
after the best rigid motion, and after the best similarity (rotation, shift and one scale), with that scale.

The raw error of a fit on a rig whose distances are off by some per cent holds the face's size error (a face of
about 80 mm radius, 3 % too large, is 2.4 mm off at its rim); the similarity-aligned error is the shape alone.

    python benchmarks/bench_face_shape.py LABEL=FIT_DIR:TRUTH_DIR [...]

FIT_DIR holds geometry artifacts NNN.npz (fit-geometry's output folder), TRUTH_DIR the synth-truth files of the
same names.
"""
from __future__ import annotations

import sys
from pathlib import Path

import numpy as np

from reflectmm_cli.geometry.align import rigid_align


def align(a: np.ndarray, b: np.ndarray, scale: bool) -> tuple[float, float]:
    """(RMS of ‖s·R·a + t − b‖, s) for the best rotation R, shift t and, with ``scale``, the best scale s
    (:func:`reflectmm_cli.geometry.align.rigid_align`)."""
    a, b = np.asarray(a, np.float64), np.asarray(b, np.float64)
    R, t, s = rigid_align(a, b, scale=scale)
    return float(np.sqrt((((s * a @ R.T + t) - b) ** 2).sum(1).mean())), float(s)


def measure(fit_dir: Path, truth_dir: Path) -> list[tuple[str, float, float, float, float]]:
    """(identity, raw, rigid, similarity RMS in mm, the similarity's scale) per fit."""
    rows = []
    for path in sorted(fit_dir.glob("[0-9]*.npz")):
        a = np.load(path)["vertices"].astype(np.float64)
        b = np.load(truth_dir / path.name)["vertices"].astype(np.float64)
        raw = float(np.sqrt(((a - b) ** 2).sum(1).mean()))
        rigid, _ = align(a, b, False)
        sim, s = align(a, b, True)
        rows.append((path.stem, raw, rigid, sim, s))
    return rows


def main(argv: list[str] | None = None) -> int:
    args = sys.argv[1:] if argv is None else argv
    if not args or any("=" not in a or ":" not in a for a in args):
        print(__doc__, file=sys.stderr)
        return 2
    for arg in args:
        label, rest = arg.split("=", 1)
        fit_dir, truth_dir = (Path(p) for p in rest.split(":", 1))
        rows = measure(fit_dir, truth_dir)
        if not rows:
            print(f"{fit_dir}: no fits", file=sys.stderr)
            return 1

        def col(k):
            return " ".join(f"{r[k]:.2f}" for r in rows) + f" (mean {np.mean([r[k] for r in rows]):.2f})"
        print(f"{label}: raw {col(1)} | rigid {col(2)} | shape {col(3)} | scale "
              + " ".join(f"{r[4]:.3f}" for r in rows))
    return 0


if __name__ == "__main__":
    sys.exit(main())
