"""benchmarks/bench_head_rotation.py (docs/benchmarks.md, "The cameras' error is the head's rotation"): the
rotation fitted to the views with landmarks, and the errors it leaves; benchmarks/bench_face_shape.py ("The joint
rounds"): a fit's error split into size and shape."""

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from _benchmarks import load_benchmark


def _ring(n: int = 11, radius: float = 1300.0) -> np.ndarray:
    """Camera centres on a partly raised arc around the origin, as a Multi-PIE table."""
    yaw = np.radians(np.linspace(-60, 60, n))
    pitch = np.radians(np.where(np.arange(n) % 4 == 0, 12.0, 0.0))
    return radius * np.stack([np.sin(yaw) * np.cos(pitch), np.sin(pitch), np.cos(yaw) * np.cos(pitch)], -1)


def test_head_rotation_is_the_least_squares_rotation():
    """Against scipy's solution of the same problem (Wahba's), on noisy points."""
    bench = load_benchmark("bench_head_rotation")
    rng = np.random.default_rng(1)
    true = _ring()
    fitted = true @ Rotation.from_rotvec([0.03, -0.01, 0.02]).as_matrix() + rng.normal(0, 5.0, true.shape)
    R = bench.head_rotation(fitted, true)
    want, _ = Rotation.align_vectors(true, fitted)
    np.testing.assert_allclose(R, want.as_matrix(), atol=1e-9)
    assert np.isclose(np.linalg.det(R), 1.0)


def test_a_turned_head_leaves_only_the_misplaced_view():
    """Every camera of an identity turned 2° in pitch with the head, one view without landmarks 30 mm off besides:
    the rotation from the views with landmarks is the 2° (the x component, its sign undone), and it leaves 30 mm on
    that view and nothing on the others."""
    bench = load_benchmark("bench_head_rotation")
    true = _ring()
    turn = Rotation.from_rotvec(np.radians([2.0, 0.0, 0.0])).as_matrix()
    fitted = true @ turn.T
    marked = np.zeros(len(true), bool)
    marked[3:8] = True
    fitted[0] += [0.0, 30.0, 0.0]
    R, before, after = bench.split(fitted, true, marked)
    np.testing.assert_allclose(bench.rotation_degrees(R), [-2.0, 0.0, 0.0], atol=1e-9)
    np.testing.assert_allclose(after[0], 30.0, atol=1e-6)
    np.testing.assert_allclose(after[1:], 0.0, atol=1e-6)
    # before: the chord of a 2° turn at each camera's distance from the x axis (and the 30 mm on top for view 0)
    chord = 2 * np.linalg.norm(true[1:, 1:], axis=1) * np.sin(np.radians(1.0))
    np.testing.assert_allclose(before[1:], chord, rtol=1e-9)


def test_the_workspace_summary(tmp_path, capsys):
    """End to end on a two-identity workspace: the lines per identity and the counts within the limit."""
    bench = load_benchmark("bench_head_rotation")
    true = _ring()
    names = np.array([f"{i:02d}_0" for i in range(len(true))])
    evidence = np.array(["landmarks+flash" if 3 <= i < 8 else "rig+flash" for i in range(len(true))])
    (tmp_path / "fit-geometry").mkdir()
    (tmp_path / "synth-multipie" / "truth").mkdir(parents=True)
    for ident, deg in (("001", 2.0), ("002", 0.5)):
        turn = Rotation.from_rotvec(np.radians([deg, 0.0, 0.0])).as_matrix()
        np.savez(tmp_path / "fit-geometry" / f"{ident}.npz", cam_centers=true @ turn.T, view_names=names,
                 view_evidence=evidence)
        np.savez(tmp_path / "synth-multipie" / "truth" / f"{ident}.npz", cam_centers=true, camera_names=names)
    assert bench.main(["--workspace", str(tmp_path)]) == 0
    out = capsys.readouterr().out
    assert "001: head rotation x -2.00°" in out and "002: head rotation x -0.50°" in out
    # a 2° turn moves a camera 1.3 m away about 45 mm; 0.5° about 11 mm: 6 of the 12 views without landmarks
    # (all of 002's) are within 20 mm as fitted, all 12 after the rotation
    assert "views without landmarks, as fitted: median" in out
    assert "6 of 12 within 20 mm" in out.split("views without landmarks, as fitted")[1].split("\n")[0]
    assert "12 of 12 within 20 mm" in out.split("views without landmarks, after")[1].split("\n")[0]
    assert bench.main(["--workspace", str(tmp_path / "none")]) == 1


def test_face_shape_split_reads_a_known_similarity(tmp_path, capsys):
    """benchmarks/bench_face_shape.py: a face turned, moved and scaled 3 % is off as fitted, not after the
    similarity, whose scale is the inverse; a bent face keeps its bend in every column."""
    bench = load_benchmark("bench_face_shape")
    rng = np.random.default_rng(3)
    truth = rng.normal(0.0, 40.0, (500, 3))
    turn = Rotation.from_rotvec([0.02, -0.01, 0.03]).as_matrix()
    fitted = 1.03 * truth @ turn.T + [1.0, -2.0, 0.5]
    rms, s = bench.align(fitted, truth, True)
    assert rms < 1e-9 and s == pytest.approx(1 / 1.03)
    rigid, s1 = bench.align(fitted, truth, False)
    assert s1 == 1.0 and rigid > 0.5
    bent = truth.copy()
    bent[:, 2] += 0.002 * bent[:, 0] ** 2
    want = np.sqrt(((bent - bent.mean(0) - (truth - truth.mean(0))) ** 2).sum(1).mean())
    assert bench.align(bent, truth, True)[0] <= want + 1e-9  # the similarity can only lower the bend's RMS
    assert bench.align(bent, truth, True)[0] > 0.5 * want
    (tmp_path / "fit").mkdir()
    (tmp_path / "truth").mkdir()
    np.savez(tmp_path / "fit" / "001.npz", vertices=fitted)
    np.savez(tmp_path / "truth" / "001.npz", vertices=truth)
    assert bench.main([f"x={tmp_path / 'fit'}:{tmp_path / 'truth'}"]) == 0
    out = capsys.readouterr().out
    assert out.startswith("x: raw ") and "| shape 0.00 (mean 0.00) | scale 0.971" in out
    assert bench.main(["nonsense"]) == 2
