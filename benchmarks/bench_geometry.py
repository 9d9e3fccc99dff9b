"""Geometry and ray-casting benchmark (issue 4): rasterisation time at 640×480, rays/s for shadow and visibility
rays, UV rasterisation, procedural model construction.  Prints a markdown table (medians over --repeat runs).

    python benchmarks/bench_geometry.py [--repeat 5]
"""
from __future__ import annotations

import argparse
import os
import platform
import statistics
import sys
import time

import numpy as np


def _median_time(fn, repeat):
    fn()  # warm-up
    ts = []
    for _ in range(repeat):
        t0 = time.perf_counter()
        fn()
        ts.append(time.perf_counter() - t0)
    return statistics.median(ts)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeat", type=int, default=5)
    ap.add_argument("--sizes", default="35000,70000", help="procedural model vertex counts")
    args = ap.parse_args(argv)

    from reflectmm_cli.geometry import (
        RayScene,
        orbit_camera,
        procedural_face_model,
        rasterize,
        rasterize_uv,
        shadow_mask,
        visibility,
    )

    rows = []
    print(f"# reflectmm geometry benchmark — {platform.processor() or platform.machine()}, "
          f"python {sys.version.split()[0]}, OMP_NUM_THREADS={os.environ.get('OMP_NUM_THREADS', 'unset')}",
          file=sys.stderr)
    # warm-up: first imports and the Embree device creation are not part of the timings
    w = procedural_face_model(n_vertices=2000, n_shape=4, n_exp=2)
    RayScene(w.mean_shape, w.triangles)
    for nv in [int(x) for x in args.sizes.split(",")]:
        t_build = _median_time(lambda: procedural_face_model(n_vertices=nv, n_shape=40, n_exp=20),
                               max(1, args.repeat // 2))
        m = procedural_face_model(n_vertices=nv, n_shape=40, n_exp=20)
        v = m.mean_shape
        t_scene = _median_time(lambda: RayScene(v, m.triangles), args.repeat)
        scene = RayScene(v, m.triangles)
        T = len(m.triangles)
        for yaw in (0, 45, 90):
            cam = orbit_camera(yaw, 0, 1000, focal_px=1500, width=640, height=480)
            holder = {}

            def ras():
                holder["r"] = rasterize(scene, cam)

            t = _median_time(ras, args.repeat)
            r = holder["r"]
            rows.append((f"rasterize 640×480, yaw {yaw}°", f"{m.n_vertices} / {T}", f"{t * 1e3:.0f} ms",
                         f"{640 * 480 / t / 1e6:.2f} M primary rays/s ({r.mask.mean() * 100:.0f} % face)"))
        cam = orbit_camera(0, 0, 1000, focal_px=1500, width=640, height=480)
        r = rasterize(scene, cam)
        pts, nrm = r.position[r.mask], r.normal[r.mask]
        flash = np.array([700.0, 0.0, 700.0])

        def sh():
            shadow_mask(scene, pts, nrm, flash)

        t = _median_time(sh, args.repeat)
        sh()
        st = scene.stats
        rows.append(("shadow rays (flash at 45°)", f"{m.n_vertices} / {T}", f"{t * 1e3:.0f} ms",
                     f"{st.cast / t / 1e6:.2f} M rays/s; {st.cast} cast, {st.skipped} skipped (n·l ≤ 0)"))
        eye = orbit_camera(60, 0, 1000).center

        def vis():
            visibility(scene, v, None, eye)

        t = _median_time(vis, args.repeat)
        rows.append(("visibility of all vertices (no normals)", f"{m.n_vertices} / {T}", f"{t * 1e3:.0f} ms",
                     f"{m.n_vertices / t / 1e6:.2f} M rays/s"))
        t = _median_time(lambda: rasterize_uv(m.uv, m.triangles, 256), args.repeat)
        rows.append(("rasterize_uv 256²", f"{m.n_vertices} / {T}", f"{t * 1e3:.0f} ms", ""))
        rows.append(("procedural_face_model (40 shape, 20 exp)", f"{m.n_vertices} / {T}", f"{t_build:.2f} s",
                     f"Embree scene build {t_scene * 1e3:.0f} ms"))
    print("| operation | vertices / triangles | median time | throughput |")
    print("|---|---|---|---|")
    for row in rows:
        print("| " + " | ".join(row) + " |")
    print(f"\n`python benchmarks/bench_geometry.py --repeat {args.repeat} --sizes {args.sizes}`")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
