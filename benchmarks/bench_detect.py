"""How many capture views dlib annotates, and how well, with and without the exposure normalisation.

For every room-light image ``*_00.png`` under the given capture folders (``synth multipie`` output, which
writes the synthetic landmarks beside each as ``*_00_lm.pts``), run ``detect_landmarks`` once per setting
(``--exposure none`` and ``auto``, at ``--upsample``) and report per camera how many images get a face, the
median landmark error over all found images (mean point distance / inter-ocular distance of the synthetic
landmarks, the usual normalisation of the 300-W benchmark) and its 90th percentile, and the median time per image.
The settings run interleaved image by image, so both see the same machine load.

With ``--wild DIR`` (``synth wild`` output) the images are its renders, the truth its ``landmarks_true`` and the
rows are grouped by absolute yaw (0–15°, 15–30°, 30° and more) instead of by camera.

A second table says where the error of the faces found with ``auto`` lies: per point group (jaw, brows, inner
points) and as the scale of the best similarity between the detector's points and the synthetic ones, a bias
that a bundle adjustment reads as a different face size or distance.

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

    out = {s: {"found": Counter(), "err": [], "sec": [], "pairs": []} for s in SETTINGS}
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
            out[s]["pairs"].append((face.landmarks, truth))
    return out


def similarity_scale(points: np.ndarray, ref: np.ndarray) -> float:
    """The scale of the least-squares similarity taking ``ref`` (n, 2) to ``points`` (n, 2), rotation and shift free
    (:func:`~reflectmm_cli.geometry.align.rigid_align`'s Umeyama scale)."""
    from reflectmm_cli.geometry.align import rigid_align

    return rigid_align(ref, points, scale=True)[2]


#: Point sets of the bias table (iBUG-68, 0-based).
SUBSETS = {"all 68": np.r_[0:68], "without the jaw": np.r_[17:68], "inner (nose, eyes, mouth)": np.r_[27:68]}


def bias_table(pairs: list[tuple[np.ndarray, np.ndarray]]) -> str:
    """Markdown: where the detector's landmarks differ from the synthetic ones, per found face — the mean error
    of the jaw (0–16), brows (17–26) and inner points (27–67) over the inter-ocular distance, the brows' vertical
    offset (negative: the detector's are higher), and the similarity scale of the detector's points against the
    synthetic ones for three point sets (1 = the same size); median (10th–90th percentile)."""
    rows = {"jaw error / IOD": [], "brow error / IOD": [], "inner error / IOD": [], "brow vertical offset / IOD": []}
    rows |= {f"scale, {k}": [] for k in SUBSETS}
    for det, syn in pairs:
        iod = _iod(syn)
        err = np.linalg.norm(det - syn, axis=1) / iod
        rows["jaw error / IOD"].append(err[0:17].mean())
        rows["brow error / IOD"].append(err[17:27].mean())
        rows["inner error / IOD"].append(err[27:68].mean())
        rows["brow vertical offset / IOD"].append((det[17:27, 1] - syn[17:27, 1]).mean() / iod)
        for k, idx in SUBSETS.items():
            rows[f"scale, {k}"].append(similarity_scale(det[idx], syn[idx]))
    out = ["| measure | median (10th–90th percentile) |", "|---|---|"]
    for k, v in rows.items():
        v = np.asarray(v)
        out.append(f"| {k} | {np.median(v):.3f} ({np.percentile(v, 10):.3f}–{np.percentile(v, 90):.3f}) |")
    return "\n".join(out)


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
    if res["auto"]["pairs"]:
        print(f"\nWhere the error is (exposure auto, {len(res['auto']['pairs'])} faces):\n")
        print(bias_table(res["auto"]["pairs"]))


if __name__ == "__main__":
    main()
