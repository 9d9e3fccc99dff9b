"""benchmarks/bench_unmarked.py --landmark-error (docs/benchmarks.md, "What limits the detector's set"): the table
reads a known per-group offset of a detector's points, and the cheek points' distance across the outline is
zero for points put on the outline."""

import re

import numpy as np

import toy
from _benchmarks import load_benchmark
from reflectmm_cli.geometry.camera import project
from reflectmm_cli.geometry_fit.contour import SLIDING, jaw_contour, outline
from reflectmm_cli.landmarks import write_pts


def test_landmark_error_reads_known_offsets(tmp_path, capsys):
    m = toy.toy_model()
    verts = m.vertices()
    K, R, t = toy.arc_cameras([0.0, 15.0])
    names = ["05_1", "14_0"]
    (tmp_path / "syn" / "truth").mkdir(parents=True)
    np.savez(tmp_path / "syn" / "face_model.npz", mean_shape=m.mean, triangles=m.triangles, landmarks=m.landmarks)
    np.savez(tmp_path / "syn" / "truth" / "001.npz", vertices=verts, K=K, R=R, t=t, camera_names=np.array(names))
    (tmp_path / "lm_detect").mkdir()
    contour = jaw_contour(m.mean, m.triangles, m.landmarks)
    for v, code in enumerate(["051", "140"]):
        pts = project(verts[m.landmarks], K[v], R[v], t[v])[0]
        pts[36:48] += [2.0, 0.0]  # the eyes 2 px to the right in both views
        pts[48:60] += [0.0, 1.0] if v == 0 else [0.0, -1.0]  # the outer mouth up in one view, down in the other
        for side, ids in enumerate(outline(contour, verts, K[v], R[v], t[v])):  # cheek points on the outline
            uv = project(verts[ids], K[v], R[v], t[v])[0]
            for k, s in zip(SLIDING, contour.sides):
                if s == side:
                    pts[k] = uv[np.argmin(((uv - pts[k]) ** 2).sum(-1))]
        write_pts(tmp_path / "lm_detect" / f"001_01_01_{code}_00.pts", pts)
    load_benchmark("bench_unmarked").main(["--workspace", str(tmp_path), "--landmark-error"])
    out = capsys.readouterr().out
    rows = {r[0]: [float(x) for x in r[1:]] for r in re.findall(r"\| (\w+) \| ([\d.]+) \| ([\d.]+) \| ([\d.]+) \|", out)}
    np.testing.assert_allclose(rows["eyes"], [2.0, 2.0, 0.0], atol=2e-3)  # (the .pts files keep 4 decimals)
    np.testing.assert_allclose(rows["mouth_outer"], [1.0, 1.0, 0.0], atol=2e-3)
    for g in ("brows", "nose_bridge", "nose_base", "mouth_inner"):
        np.testing.assert_allclose(rows[g], 0.0, atol=2e-3)
    inner = np.sqrt((12 * 4.0 + 12 * 1.0) / 51)  # RMS over the 51 inner points
    assert f"inner points (17-67) RMS {inner:.2f} px" in out
    across = [float(x) for x in re.search(r"median ([\d.]+), 90th percentile ([\d.]+), max ([\d.]+)", out).groups()]
    np.testing.assert_allclose(across, 0.0, atol=2e-3)
