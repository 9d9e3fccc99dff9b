"""The least-squares model update (finetune/model_solve.py): the CG solution against a dense least-squares solve,
the preconditioner's diagonal against the dense Hessian, and an alternating run that never raises its objective."""
import numpy as np
import pytest
import torch

from _shards import make_dataset
from reflectmm_cli.finetune import model_solve as MS
from reflectmm_cli.finetune.render import ModelParams, batch_gbuffer, lighting, shade_gbuffer
from reflectmm_cli.finetune.shards import load_shards


@pytest.fixture(scope="module")
def small(tmp_path_factory):
    d = make_dataset(tmp_path_factory.mktemp("msolve"), n_images=4, size=16, mesh_n=5, seed=2)
    ss = load_shards(d["shards"])
    gb = batch_gbuffer(ss.batch([0, 1, 2, 3]), dtype=torch.float64)
    gb.skin[:] = True
    p = ModelParams(d["truth"], dtype=torch.float64)
    beta, gamma, z = (torch.tensor(d[k]) for k in ("betas", "gammas", "zs"))
    return dict(d=d, ss=ss, gb=gb, p=p, beta=beta, gamma=gamma, z=z)


def _theta(p):
    return [p.albedo_mean.clone(), p.albedo_basis.clone(), p.weights_mean.clone(), p.weights_basis.clone()]


def test_render_of_the_problem_is_the_gbuffer_shader(small):
    p, gb = small["p"], small["gb"]
    prob = MS.build_problem(p, small["d"]["light"], gb, small["beta"], small["gamma"], small["z"], max_pixels=0)
    got = MS._render(prob, *_theta(p))
    dd, s, _, _ = shade_gbuffer(p, small["beta"], lighting(small["d"]["light"], small["gamma"], small["z"]), gb)
    np.testing.assert_allclose(got.numpy(), (dd + s).detach().numpy(), atol=1e-10)


def test_cg_solution_equals_the_dense_least_squares_solution(small):
    """A noisy target and a perturbed start: the preconditioned CG minimiser equals the dense normal-equation
    solution of the same quadratic (Jacobian built column by column from the linear renderer)."""
    p, gb = small["p"], small["gb"]
    rng = np.random.default_rng(0)
    prob = MS.build_problem(p, small["d"]["light"], gb, small["beta"], small["gamma"], small["z"], max_pixels=0)
    prob.target = prob.target + torch.tensor(rng.normal(0, 0.02, tuple(prob.target.shape)))
    prob = MS.merge_problems([prob], 4)
    theta0 = _theta(p)
    shapes = [t.shape for t in theta0]
    sizes = [t.numel() for t in theta0]
    n = sum(sizes)
    pull = 0.3

    def unflat(x):
        out, k = [], 0
        for sh, m in zip(shapes, sizes):
            out.append(x[k:k + m].reshape(sh))
            k += m
        return out

    flat0 = torch.cat([t.reshape(-1) for t in theta0])
    r0 = (MS._render(prob, *unflat(torch.zeros(n, dtype=torch.float64))) - prob.target).reshape(-1)
    cols = []
    for j in range(n):
        e = torch.zeros(n, dtype=torch.float64)
        e[j] = 1.0
        cols.append((MS._render(prob, *unflat(e)) - prob.target).reshape(-1) - r0)
    J = torch.stack(cols, 1).numpy()
    w = np.repeat(prob.weight.numpy(), 3)
    reg = np.concatenate([np.full(m, pull / m) for m in sizes])
    H = J.T @ (w[:, None] * J) + np.diag(reg)
    g = J.T @ (w * prob.target.numpy().reshape(-1)) + reg * flat0.numpy()
    dense = np.linalg.solve(H, g)
    theta, info = MS.solve_model(prob, theta0, pull=pull, cg_iterations=2000, cg_tol=1e-12)
    got = torch.cat([t.reshape(-1) for t in theta]).numpy()
    np.testing.assert_allclose(got, dense, atol=1e-7 * max(1.0, np.abs(dense).max()))
    assert info["f_end"] < info["f_start"]
    # the preconditioner's diagonal is the dense H's diagonal
    diag = torch.cat([d.reshape(-1) for d in MS._diag(prob, shapes, pull, sizes)]).numpy()
    np.testing.assert_allclose(diag, np.diag(H), rtol=1e-9, atol=1e-15)


def test_alternating_update_recovers_a_model_and_keeps_the_best_round(small):
    """Images rendered by the truth model; the update starts from a wrong mean: every solve lowers its objective,
    the validation objective of the kept round is the lowest, and the model moves towards the truth."""
    from _shards import wrong_initial

    d, ss = small["d"], small["ss"]
    wrong = wrong_initial(d["truth"], d["V"])
    arrays, rep = MS.alternate(wrong, d["light"], ss, MS.SolveConfig(rounds=2, pull=1e-4, cg_iterations=200,
                                                                      max_pixels=0))
    for r in rep.rounds[1:]:
        assert r["solve_end"] <= r["solve_start"]
    vals = [r["val_objective"] for r in rep.rounds]
    if np.isfinite(vals).all():
        assert vals[rep.best_round] == min(vals)
    before = np.abs(np.asarray(wrong.vertex_albedo_mean) - np.asarray(d["truth"].vertex_albedo_mean)).mean()
    after = np.abs(arrays["vertex_albedo_mean"] - np.asarray(d["truth"].vertex_albedo_mean)).mean()
    assert after < before
