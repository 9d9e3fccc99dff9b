"""The viewer page: its size per encoding, the time to build it and to draw its first frame, and its agreement with
``render`` (PSNR over the face, per-vertex reflectance, the same state), in headless Chromium with software WebGL.

Usage: python benchmarks/bench_viewer.py [--vertices N] [--components M] [--size WxH]

The test inputs of tests/viewer (_viewer_data.py: a procedural face, random smooth reflectance models of 1, 3 and
5 lobes, a synthetic sky) and its browser helper (_browser.py). Needs Chromium (``make browser``).
"""
from __future__ import annotations

import argparse
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "tests" / "viewer"))
import _browser as B  # noqa: E402
import _viewer_data as D  # noqa: E402

from reflectmm_cli.geometry import to_display  # noqa: E402
from reflectmm_cli.geometry.render_face import render_face  # noqa: E402


def _psnr(shot, ref, mask):
    d = shot.astype(np.float64)[mask] / 255.0 - ref[mask]
    return 10 * np.log10(1.0 / max(float(np.mean(d ** 2)), 1e-12))


def main() -> int:
    ap = argparse.ArgumentParser()
    ap.add_argument("--vertices", type=int, default=35000)
    ap.add_argument("--components", type=int, default=10)
    ap.add_argument("--size", default="480x360")
    ap.add_argument("--repeats", type=int, default=3)
    a = ap.parse_args()
    W, H = map(int, a.size.split("x"))
    from scipy.ndimage import binary_erosion

    with tempfile.TemporaryDirectory() as tmp:
        t = Path(tmp)
        fm = D.face_model(t / "fm.npz", a.vertices)
        D.envmap(t / "env.exr")
        print(f"face: {fm.n_vertices} vertices, {fm.triangles.shape[0]} triangles; canvas {W}x{H}\n")
        blank = t / "blank.html"
        blank.write_text("<!doctype html><html><body style='margin:0;background:#000'></body></html>")
        starts = []
        for _ in range(a.repeats):
            t0 = time.perf_counter()
            B.screenshot(blank, "", (W, H))
            starts.append(time.perf_counter() - t0)
        print(f"browser start + screenshot of an empty page: {statistics.median(starts):.2f} s (median)\n")
        print("| lobes | encoding | page MB | build s (median) | first frame s (median, incl. browser start) "
              "| ms per redraw (β changed), software WebGL |")
        print("|---|---|---|---|---|---|")
        pages = {}
        for k in (1, 3, 5):
            m = D.reflectance_model(t / f"m{k}.npz", fm, k, n_ids=a.components + 1, seed=k)
            for enc in ("f2", "u8"):
                out = t / f"m{k}_{enc}.html"
                builds, frames = [], []
                for _ in range(a.repeats):
                    t0 = time.perf_counter()
                    subprocess.run([sys.executable, "-m", "reflectmm_cli", "-q", "view", str(m), "--face-model",
                                    str(t / "fm.npz"), "--envmap", str(t / "env.exr"), "--encoding", enc,
                                    "--components", str(a.components), "-o", str(out)], check=True,
                                   capture_output=True)
                    builds.append(time.perf_counter() - t0)
                    t0 = time.perf_counter()
                    B.screenshot(out, f"size={W}x{H}&ui=0", (W, H))
                    frames.append(time.perf_counter() - t0)
                pages[k, enc] = out
                import re

                d = B.dom(out, f"size={W}x{H}&ui=0&beta=1,1,1", query="frames=10", size=(W, H))
                ms = re.search(r'data-ms-per-frame="([0-9.]+)"', d)
                print(f"| {k} | {enc} | {out.stat().st_size / 1e6:.2f} | {statistics.median(builds):.2f} | "
                      f"{statistics.median(frames):.2f} | {ms.group(1) if ms else 'n/a'} |")
        print("\n| lobes | encoding | light | layer | PSNR dB over the face |")
        print("|---|---|---|---|---|")
        beta = [1.2, -0.8, 0.6]
        cam = "yaw=20,pitch=8,distance=900,focal=1600"
        for (k, enc), page in pages.items():
            for light in ("env", "point"):
                kw = {"envmap": t / "env.exr"} if light == "env" else {"point_light": "300,250,700"}
                lh = "light=env:0" if light == "env" else "light=point&lp=300,250,700"
                full = None
                for layer in ("full", "specular", f"lobe{k - 1}", "albedo"):
                    if light == "point" and layer == "albedo":
                        continue
                    img = render_face(t / "fm.npz", reflectance_model=t / f"m{k}.npz", coeffs=",".join(map(str, beta)),
                                      camera=f"{cam},size={W}x{H}", reflectance_at="vertex", layer=layer, **kw)["image"]
                    if full is None:
                        full = img
                        face = full[full.max(-1) > 0]
                        e = 0.9 / float(np.percentile(face.max(-1), 99.5))
                        mask = binary_erosion(full.max(-1) > 0, iterations=1)
                    ee = 1.0 if layer == "albedo" else e
                    shot = B.screenshot(page, f"beta={','.join(map(str, beta))}&{lh}&cam=20,8,900&focal=1600&"
                                        f"size={W}x{H}&layer={layer}&exposure={ee!r}&ui=0&aa=0", (W, H))
                    print(f"| {k} | {enc} | {light} | {layer} | {_psnr(shot, to_display(img, exposure=ee), mask):.1f} |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
