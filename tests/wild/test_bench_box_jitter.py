"""The decomposition behind docs/benchmarks.md's table of the averaged landmarks (benchmarks/bench_box_jitter.py),
and the rig comparison behind "The carry in the demo" (benchmarks/bench_rig_vs_table.py)."""
import sys
from pathlib import Path

import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from _benchmarks import load_benchmark  # noqa: E402


def test_the_error_splits_into_the_cameras_bias_the_view_shift_the_group_shifts_and_the_rest():
    """Errors built from known parts: a camera's bias common to its identities, a shift of each view, a shift of
    each point group, and scatter within the groups; each part of the split is the RMS of the part put in."""
    bench = load_benchmark("bench_box_jitter")
    rng = np.random.default_rng(0)
    groups = [list(g) for g in bench.GROUPS]
    errors, shifts, gshifts, within = {}, [], [], []
    for cam in ("a", "b", "c"):
        bias = rng.normal(0, 2.0, (68, 2))
        for _ in range(4):
            s = rng.normal(0, 0.5, 2)
            e = bias + s
            for g in groups:
                gs = rng.normal(0, 0.3, 2)
                w = rng.normal(0, 0.2, (len(g), 2))
                e[g] += gs + w
            errors.setdefault(cam, []).append(e)
    raw, after, view, group, rest = bench.decompose(errors)
    inner = bench.INNER
    # direct: the same split computed here, camera by camera
    want = {"raw": [], "after": [], "view": [], "group": [], "rest": []}
    for es in errors.values():
        es = np.stack(es)
        want["raw"] += [e[inner] for e in es]
        for e in es - es.mean(0):
            want["after"].append(e[inner])
            v = e[inner].mean(0)
            want["view"].append(v[None])
            for g in groups:
                want["group"].append((e[g].mean(0) - v)[None])
                want["rest"].append(e[g] - e[g].mean(0))
    rms = {k: np.sqrt(np.mean(np.square(np.concatenate(v)))) for k, v in want.items()}
    assert (raw, after, view, group, rest) == pytest.approx((rms["raw"], rms["after"], rms["view"], rms["group"],
                                                             rms["rest"]))
    assert raw > 1.5 > after                                   # the cameras' bias is most of it and comes off
    assert 0.1 < rest < 0.3                                    # the within-group scatter put in (0.2 less its mean)
    one = bench.decompose({"a": [errors["a"][0]]})             # one identity: no per-camera split
    assert np.isfinite(one[0]) and np.isnan(one[1:]).all()


def test_rig_against_table_distances_and_angles(tmp_path, capsys):
    bench = load_benchmark("bench_rig_vs_table")

    def rig(path, cams, header=""):
        fmt = lambda v: "[" + ", ".join(f"{float(x):.9f}" for x in v) + "]"  # noqa: E731
        body = "".join(f'[[camera]]\nname = "{n}"\nposition = {fmt(p)}\nlook_at = {fmt(q)}\n'
                       f'up = [0.0, 1.0, 0.0]\nfocal_px = 1000.0\nwidth = 640\nheight = 480\n\n' for n, p, q in cams)
        path.write_text(header + "\n" + body)
        return path

    table = rig(tmp_path / "table.toml", [("a", (0.0, 0.0, 1000.0), (0.0, 0.0, 0.0)),
                                          ("b", (1000.0, 0.0, 0.0), (0.0, 0.0, 0.0))])
    t = np.radians(2.0)
    cal = rig(tmp_path / "rig.toml", [("a", (3.0, 4.0, 1000.0), (3.0, 4.0, 0.0)),
                                      ("b", (1000.0, 0.0, 0.0), (0.0, 1000.0 * np.tan(t), 0.0))],
              header="# carried by the similarity of the calibrated cameras' centres (x1.0, residual 1.0 mm / "
                     "0.50 deg RMS): nominal prior only\n")
    assert bench.main(["--table", str(table), str(cal)]) == 0
    out = capsys.readouterr().out
    assert "a 5 mm / 0.0°" in out and "b 0 mm / 2.0°" in out
    assert "carry: centres (x1.0, residual 1.0 mm / 0.50 deg RMS)" in out
