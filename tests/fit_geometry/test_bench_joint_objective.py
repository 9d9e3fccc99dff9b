"""benchmarks/bench_joint_objective.py (docs/benchmarks.md, "What holds the joint rounds back"): the truth put into
a fit problem, the joint objective evaluated term by term, and the comparison run inside a fit without changing it."""

import numpy as np
import pytest
import torch

from _benchmarks import load_benchmark
from test_flash import _flash_world
from test_unmarked import _displaced_world
from reflectmm_cli.geometry.camera import camera_centers
from reflectmm_cli.geometry_fit import FitConfig, fit_geometry
from reflectmm_cli.geometry_fit import fit as F

CFG = dict(photo_rounds=0, flash_rounds=2, w_flash=100.0, unmarked_sigma_mm=100.0)


@pytest.fixture(scope="module")
def world():
    """The flash toy on its exact rig (the -45° view without landmarks) and its truth as the synthetic world writes
    it (coefficients in model units)."""
    m, verts, R, t, views = _displaced_world(0.0, 0.0)
    _, zs, ze, *_ = _flash_world()
    truth = {"camera_names": np.array(views().names), "R": R, "t": t, "cam_centers": camera_centers(R, t),
             "vertices": verts, "shape_coeffs": zs * m.shape_sigma, "exp_coeffs": ze * m.exp_sigma}
    return m, views, truth


def _state(prob):
    with torch.no_grad():
        R, t = prob.poses()
        return prob.verts().numpy().copy(), R.numpy().copy(), t.numpy().copy()


def test_put_truth(world):
    """``truth``: the face and every pose are the truth's, and the head carries the rig's centres onto the true ones
    (exact rig: the rigid fit leaves nothing); ``cameras``: only the view without landmarks moves, to its true pose."""
    bench = load_benchmark("bench_joint_objective")
    m, views, truth = world
    prob = F._FitProblem(m, views(), FitConfig(**CFG), "cpu")
    X0, R0, t0 = _state(prob)
    bench.put_truth(prob, truth, "cameras")
    X1, R1, t1 = _state(prob)
    np.testing.assert_array_equal(X1, X0)
    np.testing.assert_allclose(R1[0], truth["R"][0], atol=1e-10)
    np.testing.assert_allclose(t1[0], truth["t"][0], atol=1e-6)
    np.testing.assert_array_equal(R1[1:], R0[1:])
    assert prob.registered[0] and not prob.registered[1:].any()
    bench.put_truth(prob, truth, "truth")
    X2, R2, t2 = _state(prob)
    np.testing.assert_allclose(X2, truth["vertices"], atol=1e-9)
    np.testing.assert_allclose(R2, truth["R"], atol=1e-10)
    np.testing.assert_allclose(camera_centers(R2, t2), truth["cam_centers"], atol=1e-6)
    with torch.no_grad():
        Rh, th = (x.numpy() for x in prob.head())
    np.testing.assert_allclose(views().rig_centers @ Rh.T + th, truth["cam_centers"], atol=1e-6)


def test_joint_terms_at_the_truth_and_away(world):
    """On the toy's noise-free Lambertian flash images the flash term is least at the truth: a face shifted by 3 mm
    raises it; the shape prior is ½‖z‖² / (the landmark weights' sum), from the truth's coefficients."""
    bench = load_benchmark("bench_joint_objective")
    m, views, truth = world
    prob = F._FitProblem(m, views(), FitConfig(**CFG), "cpu")
    bench.put_truth(prob, truth, "truth")
    terms = bench.joint_terms(prob, F._sub_mesh(prob))
    at_truth = terms()
    z = np.concatenate([truth["shape_coeffs"] / m.shape_sigma, truth["exp_coeffs"] / m.exp_sigma])
    assert at_truth[2] == pytest.approx(0.5 * (z ** 2).sum() / prob.wsum, rel=1e-9)
    assert at_truth[3] == pytest.approx(0.0, abs=1e-9)  # exact rig, the head carried onto it
    with torch.no_grad():
        prob.dth += torch.tensor([3.0, 0.0, 0.0], dtype=prob.dtype) / prob.t_unit  # the head (and the held view)
        for v in np.nonzero(prob.marked)[0]:  # and the views with landmarks move by 3 mm together: the face slides
            prob.dtr[v] += (torch.as_tensor(truth["R"][v], dtype=prob.dtype) @ torch.tensor(
                [-3.0, 0.0, 0.0], dtype=prob.dtype)) / prob.tv_unit
    away = terms()
    assert away[1] > 1.5 * at_truth[1], (away, at_truth)


def test_the_comparison_leaves_the_fit_as_it_was(world):
    """Run inside a fit with joint rounds, the comparison records every start and the truth, the start from the
    truth ends closer than the chain, and the fit returned is the one without the comparison, bit for bit."""
    bench = load_benchmark("bench_joint_objective")
    m, views, truth = world
    cfg = FitConfig(**CFG, joint_rounds=1, joint_blur_px=0.0)
    plain = fit_geometry(m, views(), cfg)
    record = {}
    with bench.compared(["fit", "cameras", "truth"], truth, record):
        compared = fit_geometry(m, views(), cfg)
    assert F._joint_rounds.__name__ == "_joint_rounds"  # put back
    np.testing.assert_array_equal(compared.vertices, plain.vertices)
    np.testing.assert_array_equal(compared.t, plain.t)
    assert set(record) == {"fit", "cameras", "truth", bench.TRUE}
    assert record[bench.TRUE]["at truth"] is not None and len(record["fit"]["at fit"]) == 4
    v_fit = record["fit"]["errors"][0]
    assert v_fit == pytest.approx(float(np.sqrt(((plain.vertices - truth["vertices"]) ** 2).sum(-1).mean())),
                                  rel=1e-9)
    assert record["truth"]["errors"][0] < v_fit


def test_inputs_are_checked(tmp_path):
    """Without a workspace every input must be given, and each must exist: one line naming what is missing."""
    bench = load_benchmark("bench_joint_objective")
    with pytest.raises(SystemExit, match="--face-model or --workspace is needed"):
        bench.main(["--capture-dir", str(tmp_path)])
    with pytest.raises(SystemExit, match="preprocess-multipie: not found"):
        bench.main(["--workspace", str(tmp_path)])
    with pytest.raises(SystemExit, match="unknown start"):
        bench.main(["--workspace", str(tmp_path), "--starts", "fit,elsewhere"])
