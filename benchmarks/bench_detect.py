"""How many capture views dlib annotates, and how well, with and without the exposure normalisation.

For every room-light image ``*_00.png`` under the given capture folders (``synth multipie`` output, which
writes the synthetic landmarks beside each as ``*_00_lm.pts``), run ``detect_landmarks`` once per setting
(``--exposure none`` and ``auto``, at ``--upsample``) and report per camera how many images get a face, the
median landmark error over all found images (mean point distance / inter-ocular distance of the synthetic
landmarks, the usual normalisation of the 300-W benchmark) and its 90th percentile, and the median time per image.
The settings run interleaved image by image, so both see the same machine load.

With ``--wild DIR`` (``synth wild`` output) the images are its renders, the truth its ``landmarks_true`` and the
rows are grouped by absolute yaw (0–15°, 15–30°, 30° and more) instead of by camera.

    python benchmarks/bench_detect.py CAPTURE_DIR [CAPTURE_DIR ...] [--upsample 1]
    python benchmarks/bench_detect.py --wild SYNTH_WILD_DIR
"""

from __future__ import annotations

import argparse
import sys
import time
from collections import Counter
from pathlib import Path

import numpy as np

SETTINGS = ("none", "auto")


def _iod(lm: np.ndarray) -> float:
    return float(np.linalg.norm(lm[36:42].mean(0) - lm[42:48].mean(0)))


def capture_items(dirs: list[Path]) -> list[tuple[Path, str, np.ndarray]]:
    """(image, camera, synthetic landmarks) of every room-light image with ``*_00_lm.pts`` beside it."""
    from reflectmm_cli.landmarks import read_landmarks

    images = sorted(p for d in dirs for p in d.rglob("*_00.png") if p.with_name(p.stem + "_lm.pts").is_file())
    return [(p, p.parent.name, read_landmarks(p.with_name(p.stem + "_lm.pts"))) for p in images]


def wild_items(root: Path) -> list[tuple[Path, str, np.ndarray]]:
    """(image, yaw group, true landmarks) of every ``synth wild`` render."""
    from reflectmm_cli.artifacts import read_artifact

    man = read_artifact(root / "manifest.npz", "wild-manifest")
    items = []
    for n, pose in zip(man["names"].tolist(), man["pose_deg"]):
        yaw = abs(float(pose[0]))
        group = "yaw 0-15" if yaw < 15 else "yaw 15-30" if yaw < 30 else "yaw 30+"
        truth = read_artifact(root / "truth" / f"{n}.npz", "wild-truth")["landmarks_true"]
        items.append((root / "images" / f"{n}.png", group, np.asarray(truth, np.float64)))
    return items


def measure(items: list[tuple[Path, str, np.ndarray]], upsample: int) -> dict:
    from reflectmm_cli.artifacts import read_image_u8
    from reflectmm_cli.detection import detect_landmarks, pick_face

    out = {s: {"found": Counter(), "err": [], "sec": []} for s in SETTINGS}
    for p, group, truth in items:
        img = read_image_u8(p)
        for s in SETTINGS:
            t0 = time.perf_counter()
            face = pick_face(detect_landmarks(img, upsample=upsample, exposure=s))
            out[s]["sec"].append(time.perf_counter() - t0)
            if face is None:
                continue
            out[s]["found"][group] += 1
            out[s]["err"].append(np.linalg.norm(face.landmarks - truth, axis=1).mean() / _iod(truth))
    return out


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("captures", nargs="*", type=Path)
    ap.add_argument("--wild", type=Path, default=None)
    ap.add_argument("--upsample", type=int, default=1)
    args = ap.parse_args(argv)
    items = wild_items(args.wild) if args.wild else capture_items(args.captures)
    if not items:
        sys.exit("no *_00.png with *_00_lm.pts beside it under the given folders")
    cams = sorted({g for _, g, _ in items})
    per_cam = Counter(g for _, g, _ in items)
    res = measure(items, args.upsample)
    print(f"{len(items)} images, {len(cams)} groups, upsample {args.upsample}\n")
    print("| exposure | images with a face | " + " | ".join(cams) + " | error / IOD, median (p90) | s per image |")
    print("|---|---|" + "---|" * len(cams) + "---|---|")
    for s in SETTINGS:
        r = res[s]
        e = np.array(r["err"])
        err = f"{np.median(e):.3f} ({np.percentile(e, 90):.3f})" if e.size else "–"
        found = " | ".join(f"{r['found'][c]}/{per_cam[c]}" for c in cams)
        print(f"| {s} | {sum(r['found'].values())} / {len(items)} | {found} | {err} | "
              f"{np.median(r['sec']):.3f} |")


if __name__ == "__main__":
    main()
