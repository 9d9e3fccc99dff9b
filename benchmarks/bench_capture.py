"""Benchmark: preprocess-multipie and unwrap-uv per identity (issue 5), with the error of the unwrapped radiance.

Data: ``synth multipie --brdf model`` (exact 3-lobe BRDF) at 640×480, the paper's 9 views and 11 flashes; geometry
from ``fit-geometry --from-truth``; unwrap at UV 256.  Each verb runs through the CLI in-process (the same code
path as the shell, without the interpreter start-up).  Times are wall-clock and process CPU seconds (the
machine may be shared; CPU seconds are the steadier number).  Error of the unwrapped radiance against the
ground-truth shading evaluated exactly at each observed texel (albedo/weights of the truth UV maps at the texel
centre), in linear units; ``QUANT = 2·1.2·0.5/255`` is the worst-case 8-bit quantisation of flash − room.
With ``--fitted`` the first identity is also unwrapped with a real ``fit-geometry`` result; its error then
includes the geometry misfit (texel positions/normals of the fitted mesh against truth maps).

Usage::

    python benchmarks/bench_capture.py [--identities 2] [--size 640x480] [--uv 256] [--fitted] [--workdir DIR]
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

VIEWS = "09_0,08_0,13_0,14_0,05_1,05_0,04_1,19_0,20_0"
FLASHES = "03,04,05,06,07,08,09,10,11,14,18"
QUANT = 2 * 1.2 * 0.5 / 255


def _run(*args):
    from click.testing import CliRunner

    from reflectmm_cli.cli import main

    w0, c0 = time.perf_counter(), time.process_time()
    res = CliRunner().invoke(main, ["-q"] + [str(a) for a in args], catch_exceptions=False)
    if res.exit_code != 0:
        sys.exit(f"failed: reflectmm {' '.join(map(str, args))}\n{res.output}")
    return time.perf_counter() - w0, time.process_time() - c0


def texel_errors(obs, truth) -> np.ndarray:
    from reflectmm_cli.shading.brdf import shade_directional

    alb, wts = truth["albedo"].transpose(1, 2, 0), truth["weights"].transpose(1, 2, 0)
    errs = []
    for p in range(obs["pair_view"].shape[0]):
        ob = obs["observed"][p]
        if not ob.any():
            continue
        vi, fi = int(obs["pair_view"][p]), int(obs["pair_flash"][p])
        x = obs["position"][ob].astype(np.float64)
        dl = obs["flash_pos"][fi] - x
        E = obs["flash_intensity"][fi] / (dl * dl).sum(1)
        s = shade_directional(alb[ob], wts[ob], truth["exponents"], obs["normal"][ob].astype(np.float64), dl,
                              obs["cam_centers"][vi] - x, E[:, None] * np.ones(3))
        errs.append(np.abs(obs["radiance"][p][ob].astype(np.float64) - s).ravel())
    return np.concatenate(errs)


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--identities", type=int, default=2)
    ap.add_argument("--size", default="640x480")
    ap.add_argument("--uv", type=int, default=256)
    ap.add_argument("--face-vertices", type=int, default=35000)
    ap.add_argument("--workdir", type=Path, default=None)
    ap.add_argument("--fitted", action="store_true",
                    help="also unwrap the first identity with geometry from a real fit-geometry run")
    a = ap.parse_args(argv)
    from reflectmm_cli.artifacts import read_artifact

    work = a.workdir or Path(tempfile.mkdtemp(prefix="bench_capture_"))
    mp, ws = work / "mp", work / "ws"
    ids = [f"{i:03d}" for i in range(1, a.identities + 1)]
    if not (mp / "truth" / f"{ids[-1]}.npz").exists():
        _run("synth", "multipie", "-n", a.identities, "--brdf", "model", "--image-size", a.size, "--uv-size", a.uv,
             "--cameras", VIEWS, "--flashes", FLASHES, "--face-vertices", a.face_vertices, "--out", mp, "-w", ws)
    rows = []

    def unwrap_row(ident, label, pw, pc, geometry, out):
        uw, uc = _run("unwrap-uv", "--id", ident, "--uv-size", a.uv, "--geometry", geometry, "-o", out, "-w", ws)
        obs = read_artifact(out, "uv-observations")
        e = texel_errors(obs, read_artifact(mp / "truth" / f"{ident}.npz", "synth-truth"))
        rep = obs.meta.get("report", {})
        rows.append((ident, label, pw, pc, uw, uc, float(np.median(e)), float(np.percentile(e, 90)),
                     float(np.percentile(e, 99)), float(np.mean(e <= QUANT)), int(rep.get("observed_pairs", 0)),
                     int(obs["mask"].sum()), (ws / "preprocess-multipie" / f"{ident}.npz").stat().st_size / 1e6,
                     out.stat().st_size / 1e6))

    for k, ident in enumerate(ids):
        pw, pc = _run("preprocess-multipie", "--root", mp, "--id", ident, "-w", ws)
        _run("fit-geometry", "--id", ident, "--from-truth", mp / "truth" / f"{ident}.npz", "-w", ws)
        unwrap_row(ident, "truth", pw, pc, ws / "fit-geometry" / f"{ident}.npz", ws / "unwrap-uv" / f"{ident}.npz")
        if a.fitted and k == 0:
            fw, fc = _run("fit-geometry", "--id", ident, "-w", ws, "-o", ws / "fitted" / f"{ident}.npz")
            print(f"fit-geometry {ident}: {fw:.1f} s wall, {fc:.1f} s CPU", file=sys.stderr)
            unwrap_row(ident, "fitted", pw, pc, ws / "fitted" / f"{ident}.npz", ws / "fitted" / f"{ident}_obs.npz")
    print(f"`python benchmarks/bench_capture.py --identities {a.identities} --size {a.size} --uv {a.uv}"
          f"{' --fitted' if a.fitted else ''}` (9 views × 11 flashes, synth --brdf model)\n")
    print("| identity | geometry | preprocess wall s | preprocess CPU s | unwrap wall s | unwrap CPU s | |err| median "
          "| p90 | p99 | ≤ QUANT | observed texel-pairs | texels | capture MB | observations MB |")
    print("|---|---|---|---|---|---|---|---|---|---|---|---|---|---|")
    for r in rows:
        print(f"| {r[0]} | {r[1]} | {r[2]:.2f} | {r[3]:.2f} | {r[4]:.2f} | {r[5]:.2f} | {r[6]:.4f} | {r[7]:.4f} "
              f"| {r[8]:.4f} | {100 * r[9]:.1f} % | {r[10]} | {r[11]} | {r[12]:.1f} | {r[13]:.1f} |")
    med = np.median(np.array([r[2:6] for r in rows if r[1] == "truth"]), axis=0)
    print(f"\nmedian per identity (truth geometry): preprocess {med[0]:.2f} s wall ({med[1]:.2f} s CPU), unwrap "
          f"{med[2]:.2f} s wall ({med[3]:.2f} s CPU); QUANT = {QUANT:.4f}")


if __name__ == "__main__":
    main()
