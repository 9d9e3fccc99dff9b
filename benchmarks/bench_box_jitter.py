"""The shape predictor averaged over boxes around the detector's (``detect-landmarks --box-jitter``): time and
landmark error on the room-light captures of a workspace made by recipes/synthetic.toml.

For every room-light image in which the HOG detector finds a face, the 68 points at each jitter (0 = the
detector's box alone) against the embedded landmark vertices of the true mesh, projected with the true camera
(the face model of ``face-model-embed``).  Per jitter: the CPU time per image (median; the detection and the
predictor calls), the inner points' error (17-67, RMS per coordinate, px), and that error with each camera's mean
over the identities taken off (what no per-camera offset can take), split into the shift of the whole view, each
point group's shift beyond it (brows, nose, eyes, mouth) and the rest within the groups.  The jitters run image by
image, interleaved, so all see the same machine load.

    python benchmarks/bench_box_jitter.py --workspace WS [--jitters 0,0.03,0.05]
"""
from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

GROUPS = (range(17, 27), range(27, 36), range(36, 48), range(48, 68))
INNER = np.arange(17, 68)


def decompose(errors: dict[str, list[np.ndarray]]) -> tuple[float, ...]:
    """(all, after the per-camera mean, view shift, group shift, within groups), RMS per coordinate in px, from
    per-camera lists of (68, 2) errors; cameras seen by one identity count in the first only."""
    raw, after, shift, gshift, within = [], [], [], [], []
    for es in errors.values():
        es = np.stack(es)
        raw += [e[INNER] for e in es]
        if len(es) < 2:
            continue
        for e in es - es.mean(0):
            s = e[INNER].mean(0)
            after.append(e[INNER])
            shift.append(s[None])
            for g in GROUPS:
                gi = list(g)
                gshift.append((e[gi].mean(0) - s)[None])
                within.append(e[gi] - e[gi].mean(0))

    def rms(parts):
        return float(np.sqrt(np.mean(np.square(np.concatenate(parts))))) if parts else float("nan")

    return rms(raw), rms(after), rms(shift), rms(gshift), rms(within)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--workspace", required=True, type=Path)
    ap.add_argument("--jitters", default="0,0.03,0.05")
    args = ap.parse_args(argv)
    from reflectmm_cli.artifacts import read_image_u8
    from reflectmm_cli.detection import detect_landmarks, pick_face
    from reflectmm_cli.geometry.camera import project

    ws = args.workspace
    jitters = [float(j) for j in args.jitters.split(",")]
    idx = np.load(ws / "face-model-embed" / "face-model-embed.npz")["landmarks"]
    errors = {j: {} for j in jitters}
    cpu = {j: [] for j in jitters}
    images = sorted((ws / "synth-multipie" / "data").glob("*/multiview/*/01/*/*_00.png"))
    truths: dict[str, dict] = {}
    for n, p in enumerate(images):
        ident, cam = p.parts[-4], p.parts[-2]
        img = read_image_u8(p)
        for j in jitters:
            t0 = time.process_time()
            face = pick_face(detect_landmarks(img, box_jitter=j))
            cpu[j].append(time.process_time() - t0)
            if face is None:
                continue
            if ident not in truths:
                truths[ident] = dict(np.load(ws / "synth-multipie" / "truth" / f"{ident}.npz"))
            t = truths[ident]
            k = [str(c) for c in t["camera_names"]].index(cam)
            x = project(np.asarray(t["vertices"], np.float64)[idx], t["K"][k], t["R"][k], t["t"][k])[0]
            errors[j].setdefault(cam, []).append(face.landmarks - x)
        print(f"\r{n + 1}/{len(images)} images", end="", file=sys.stderr)
    print(file=sys.stderr)
    print(f"{len(images)} room-light images of {ws}; faces found: "
          + ", ".join(f"{j:g}: {sum(len(v) for v in errors[j].values())}" for j in jitters))
    print("| box jitter | CPU s / image (median) | inner points vs truth, px | less each camera's mean | view shift "
          "| group shift | within groups |")
    print("|---|---|---|---|---|---|---|")
    for j in jitters:
        r = decompose(errors[j])
        print(f"| {j:g} | {np.median(cpu[j]):.3f} | " + " | ".join(f"{v:.2f}" for v in r) + " |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
