"""Benchmark of the synthetic world (issue 4): seconds per synthetic identity and ray-casting throughput.

Per identity: the 9 default views + the 2 raised ones (11 cameras) x 19 shots (room light + 18 flashes) at
640x480, GGX ground truth, the procedural face model (35k vertices), everything written to disk (PNG, landmarks,
truth).  Prints a markdown table and the command that produced it.

    python benchmarks/bench_synth.py [--identities 3] [--size 640x480] [--face-vertices 35000]
"""

from __future__ import annotations

import argparse
import os
import statistics
import sys
import tempfile
import time
from pathlib import Path


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--identities", type=int, default=3)
    ap.add_argument("--size", default="640x480")
    ap.add_argument("--face-vertices", type=int, default=35000)
    ap.add_argument("--brdf", default="ggx", choices=["ggx", "model"])
    args = ap.parse_args()

    from reflectmm_cli.geometry import procedural_face_model
    from reflectmm_cli.rig import DEFAULT_VIEWS, RAISED_CAMERAS
    from reflectmm_cli.synth.envmaps import make_envmap
    from reflectmm_cli.synth.multipie import SynthConfig, synth_multipie

    w, h = (int(x) for x in args.size.split("x"))
    cams = tuple(DEFAULT_VIEWS) + tuple(RAISED_CAMERAS)
    t0 = time.perf_counter()
    model = procedural_face_model(n_vertices=args.face_vertices)
    t_model = time.perf_counter() - t0

    per_id, stats_all = [], []
    with tempfile.TemporaryDirectory() as tmp:
        for k in range(args.identities):
            cfg = SynthConfig(identities=1, seed=0, first_id=k + 1, brdf=args.brdf, image_size=(w, h),
                              cameras=cams, flashes=None)
            st: dict = {}
            t0 = time.perf_counter()
            synth_multipie(Path(tmp) / f"run{k}", cfg, face_model=model, progress_fn=lambda it, **kw: it, stats=st)
            per_id.append(time.perf_counter() - t0)
            stats_all.append(st)
        t0 = time.perf_counter()
        for i in range(4):
            make_envmap(0, i, 512)
        t_env = (time.perf_counter() - t0) / 4

    prim = statistics.median(s["primary_rays"] for s in stats_all)
    shad = statistics.median(s["shadow_rays"] for s in stats_all)
    rsec = statistics.median(s["ray_seconds"] for s in stats_all)
    med = statistics.median(per_id)
    shots = len(cams) * 19
    print(f"command: python benchmarks/bench_synth.py --identities {args.identities} --size {args.size} "
          f"--face-vertices {args.face_vertices} --brdf {args.brdf}")
    print(f"machine: {os.cpu_count()} CPUs visible, python {sys.version.split()[0]}")
    print()
    print("| quantity | value |")
    print("|---|---|")
    print(f"| face model ({model.n_vertices} vertices, {len(model.triangles)} triangles), built once | {t_model:.2f} s |")
    print(f"| seconds per identity ({len(cams)} views x 19 shots = {shots} PNGs at {w}x{h}, {args.brdf}), "
          f"median of {args.identities} | {med:.2f} s |")
    print(f"| per image (render + encode + write) | {1000 * med / shots:.1f} ms |")
    print(f"| primary rays per identity | {prim:,.0f} |")
    print(f"| shadow rays per identity (n·l > 0 face pixels only) | {shad:,.0f} |")
    esec = statistics.median(s["embree_seconds"] for s in stats_all)
    print(f"| ray casting per identity (rasterize + shadow_mask calls, incl. ray setup) | {rsec:.2f} s |")
    print(f"| ... of which in RayScene.intersect / shadow_mask (no camera-ray setup, no interpolation) | {esec:.2f} s |")
    print(f"| ray throughput, whole calls (primary + shadow) | {(prim + shad) / rsec / 1e6:.2f} Mrays/s |")
    print(f"| ray throughput, intersect / shadow_mask only | {(prim + shad) / esec / 1e6:.2f} Mrays/s |")
    print(f"| procedural HDR map 512x256, median kind | {1000 * t_env:.0f} ms |")


if __name__ == "__main__":
    main()
