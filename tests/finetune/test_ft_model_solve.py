"""The least-squares model update (finetune/model_solve.py): the CG solution against a dense least-squares solve,
the preconditioner's diagonal against the dense Hessian, and an alternating run that never raises its objective."""
import numpy as np
import pytest
import torch

from _shards import make_dataset
from reflectmm_cli.finetune import model_solve as MS
from reflectmm_cli.finetune.render import ModelParams, batch_gbuffer, lighting, shade_gbuffer
from reflectmm_cli.finetune.shards import load_shards


def small_data(folder, n_images: int) -> dict:
    """A small data set (16² images of a 5×5 cap) and its first 4 images packed as one float64 batch, every pixel
    counted as skin, with their true coefficients."""
    d = make_dataset(folder, n_images=n_images, size=16, mesh_n=5, seed=2)
    ss = load_shards(d["shards"])
    gb = batch_gbuffer(ss.batch([0, 1, 2, 3]), dtype=torch.float64)
    gb.skin[:] = True
    p = ModelParams(d["truth"], dtype=torch.float64)
    beta, gamma, z = (torch.tensor(d[k][:4]) for k in ("betas", "gammas", "zs"))
    return dict(d=d, ss=ss, gb=gb, p=p, beta=beta, gamma=gamma, z=z)


@pytest.fixture(scope="module")
def small(tmp_path_factory):
    return small_data(tmp_path_factory.mktemp("msolve"), 4)


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


def _dense_system(prob, theta0, start, pull, cols_of, reg=None):
    """Dense (H, g) of F in the unknowns u (θ = start + cols_of(u)), built column by column from the renderer;
    ``reg`` the pull's per-element weights (default λ / the part's element count)."""
    shapes = [t.shape for t in theta0]
    sizes = [t.numel() for t in theta0]
    flat0 = torch.cat([t.reshape(-1) for t in theta0]).numpy()
    flat_s = torch.cat([t.reshape(-1) for t in start]).numpy()

    def unflat(x):
        out, k = [], 0
        for sh, m in zip(shapes, sizes):
            out.append(torch.as_tensor(x[k:k + m]).reshape(sh))
            k += m
        return out

    Jv = []  # per-vertex Jacobian of the rendered pixels (the renderer is linear in θ)
    zero = np.zeros(sum(sizes))
    r0 = MS._render(prob, *unflat(zero)).reshape(-1).numpy()
    for j in range(sum(sizes)):
        e = zero.copy()
        e[j] = 1.0
        Jv.append(MS._render(prob, *unflat(e)).reshape(-1).numpy() - r0)
    Jv = np.stack(Jv, 1)
    A = cols_of  # (n_vertex_values, n_unknowns)
    J = Jv @ A
    w = np.repeat(prob.weight.numpy(), 3)
    if reg is None:
        reg = np.concatenate([np.full(m, pull / m) for m in sizes])
    H = J.T @ (w[:, None] * J) + A.T @ (reg[:, None] * A)
    resid = Jv @ flat_s - prob.target.numpy().reshape(-1)
    g = J.T @ (w * resid) + A.T @ (reg * (flat_s - flat0))
    return H, g, unflat


def _harmonic_columns(phi, shapes):
    """The dense map u → Φu of all four parts (block-diagonal over parts, components and channels)."""
    import scipy.linalg

    blocks = []
    for sh in shapes:
        lead = int(np.prod(sh[:-2])) if len(sh) > 2 else 1
        C = sh[-1]
        # θ part laid out (lead, V, C) row-major; u part (lead, Q, C): Φ acts on V with C and lead fixed
        blocks.append(np.kron(np.eye(lead), np.kron(phi, np.eye(C))))
    return scipy.linalg.block_diag(*blocks)


def _noisy_problem(small, seed: int):
    """(rng, the merged problem of the small batch with its targets moved by N(0, 0.02) noise): a solve with a
    non-zero residual."""
    p, gb, d = small["p"], small["gb"], small["d"]
    rng = np.random.default_rng(seed)
    prob = MS.build_problem(p, d["light"], gb, small["beta"], small["gamma"], small["z"], max_pixels=0)
    prob.target = prob.target + torch.tensor(rng.normal(0, 0.02, tuple(prob.target.shape)))
    return rng, MS.merge_problems([prob], 4)


def test_harmonic_solve_equals_the_dense_least_squares_solution(small):
    """The change restricted to Φu (Q mesh harmonics): the CG minimiser equals the dense normal-equation solution
    in u, from a start away from θ₀, and the preconditioner's diagonal is the dense diagonal in u."""
    from reflectmm_cli.geometry.harmonics import mesh_harmonics

    p, gb, d = small["p"], small["gb"], small["d"]
    rng, prob = _noisy_problem(small, 1)
    theta0 = _theta(p)
    phi = mesh_harmonics(d["V"], d["tri"], 6)[0]
    basis = torch.as_tensor(phi)
    start = [t + 0.01 * torch.as_tensor(rng.normal(size=tuple(t.shape))) for t in theta0]
    shapes = [t.shape for t in theta0]
    A = _harmonic_columns(phi, shapes)
    pull = 0.3
    H, g, unflat = _dense_system(prob, theta0, start, pull, A)
    u = np.linalg.solve(H, -g)
    want = torch.cat([t.reshape(-1) for t in start]).numpy() + A @ u
    theta, info = MS.solve_model(prob, theta0, start, pull=pull, cg_iterations=3000, cg_tol=1e-13, basis=basis)
    got = torch.cat([t.reshape(-1) for t in theta]).numpy()
    np.testing.assert_allclose(got, want, atol=1e-7 * max(1.0, np.abs(want).max()))
    assert info["f_end"] < info["f_start"]
    ushapes = [t.shape[:-2] + (6, t.shape[-1]) for t in theta0]
    diag = torch.cat([x.reshape(-1) for x in MS._diag(prob, ushapes, pull, [t.numel() for t in theta0], basis,
                                                      chunk=7)]).numpy()
    np.testing.assert_allclose(diag, np.diag(H), rtol=1e-9, atol=1e-15)


def _relative_reg(theta0, pull):
    """λ / ‖x₀‖² of each element's array (a mean, or one basis), computed directly, flattened like θ."""
    out = []
    for part, t in enumerate(theta0):
        x = t.numpy()
        arrays = [x] if part % 2 == 0 else list(x)
        out += [np.full(a.size, pull / float((a ** 2).sum())) for a in arrays]
    return np.concatenate(out)


@pytest.mark.parametrize("harmonics", [0, 6])
def test_relative_pull_solve_equals_the_dense_least_squares_solution(small, harmonics):
    """pull_scale relative, with one lobe-weight basis made 100× smaller than the others: the CG minimiser equals the
    dense normal-equation solution with the pull λ‖x − x₀‖²/‖x₀‖² per array (per vertex and with 6 harmonics, from a
    start away from θ₀), the preconditioner's diagonal is the dense diagonal, and the small basis moves less
    (relative to its size) than under the element pull."""
    from reflectmm_cli.geometry.harmonics import mesh_harmonics

    p, gb, d = small["p"], small["gb"], small["d"]
    rng = np.random.default_rng(4)
    prob = MS.build_problem(p, d["light"], gb, small["beta"], small["gamma"], small["z"], max_pixels=0)
    prob.target = prob.target + torch.tensor(rng.normal(0, 0.02, tuple(prob.target.shape)))
    prob = MS.merge_problems([prob], 4)
    theta0 = _theta(p)
    theta0[3][1] *= 0.01
    start = [t + 0.001 * torch.as_tensor(rng.normal(size=tuple(t.shape))) for t in theta0]
    shapes = [t.shape for t in theta0]
    n = sum(t.numel() for t in theta0)
    basis = torch.as_tensor(mesh_harmonics(d["V"], d["tri"], harmonics)[0]) if harmonics else None
    A = _harmonic_columns(basis.numpy(), shapes) if harmonics else np.eye(n)
    pull = 0.05
    reg = _relative_reg(theta0, pull)
    H, g, _ = _dense_system(prob, theta0, start, pull, A, reg=reg)
    want = torch.cat([t.reshape(-1) for t in start]).numpy() + A @ np.linalg.solve(H, -g)
    theta, info = MS.solve_model(prob, theta0, start, pull=pull, cg_iterations=4000, cg_tol=1e-13, basis=basis,
                                 pull_scale="relative")
    got = torch.cat([t.reshape(-1) for t in theta]).numpy()
    np.testing.assert_allclose(got, want, atol=1e-7 * max(1.0, np.abs(want).max()))
    assert info["f_end"] < info["f_start"]
    ushapes = shapes if not harmonics else [t.shape[:-2] + (harmonics, t.shape[-1]) for t in theta0]
    norms = MS.pull_norms(theta0, "relative")
    diag = torch.cat([x.reshape(-1) for x in MS._diag(prob, ushapes, pull, norms, basis, chunk=7)]).numpy()
    np.testing.assert_allclose(diag, np.diag(H), rtol=1e-9, atol=1e-15)
    # the element pull with the same λ lets the small basis grow far more relative to its size
    elem, _ = MS.solve_model(prob, theta0, start, pull=pull, cg_iterations=4000, cg_tol=1e-13, basis=basis)
    rel = lambda th: float(((th[3][1] - theta0[3][1]) ** 2).sum() / (theta0[3][1] ** 2).sum())  # noqa: E731
    assert rel(theta) < rel(elem)


def test_pull_norms_against_direct_norms():
    """element: the parts' element counts; relative: each mean's and each basis's squared norm, a zero basis held
    at 1e-12 × its part's largest."""
    rng = np.random.default_rng(5)
    theta0 = [torch.as_tensor(rng.normal(size=s)) for s in ((5, 3), (4, 5, 3), (5, 2), (4, 5, 2))]
    theta0[3][2] = 0.0
    assert MS.pull_norms(theta0) == [15, 60, 10, 40]
    got = MS.pull_norms(theta0, "relative")
    for part in (0, 2):
        assert got[part] == pytest.approx(float((theta0[part] ** 2).sum()), rel=1e-12)
    for part in (1, 3):
        want = (theta0[part] ** 2).sum((1, 2)).numpy()
        if part == 3:
            want[2] = 1e-12 * want.max()
        np.testing.assert_allclose(got[part].reshape(-1).numpy(), want, rtol=1e-12)
        assert got[part].shape == (4, 1, 1)
    from reflectmm_cli.errors import ReflectmmError

    with pytest.raises(ReflectmmError, match="pull_scale"):
        MS.SolveConfig(pull_scale="global")


def test_update_bases_freezes_the_later_bases(small):
    """update_bases = 1: the means and basis 0 change; the other bases keep their start; the free part equals the
    dense solution restricted to those unknowns."""
    p, gb, d = small["p"], small["gb"], small["d"]
    rng, prob = _noisy_problem(small, 2)
    theta0 = _theta(p)
    n = sum(t.numel() for t in theta0)
    free = torch.cat([m.reshape(-1) for m in MS._free_mask([t.shape for t in theta0], 1, torch.float64)]).numpy()
    A = np.eye(n)[:, free > 0]
    H, g, _ = _dense_system(prob, theta0, theta0, 0.3, A)
    want = torch.cat([t.reshape(-1) for t in theta0]).numpy() + A @ np.linalg.solve(H, -g)
    theta, _ = MS.solve_model(prob, theta0, pull=0.3, cg_iterations=3000, cg_tol=1e-13, update_bases=1)
    got = torch.cat([t.reshape(-1) for t in theta]).numpy()
    np.testing.assert_allclose(got, want, atol=1e-7 * max(1.0, np.abs(want).max()))
    for part in (1, 3):
        assert torch.equal(theta[part][1:], theta0[part][1:])
        assert not torch.equal(theta[part][0], theta0[part][0])


def test_robust_weights_against_a_direct_computation(small):
    """Shadow-like outliers (a block of pixels made darker): the weights leave out exactly the pixels a direct
    per-image median / MAD computation flags, the inliers carry each image's weight, and the rest is unchanged."""
    p, gb, d = small["p"], small["gb"], small["d"]
    rng = np.random.default_rng(3)
    prob = MS.build_problem(p, d["light"], gb, small["beta"], small["gamma"], small["z"], max_pixels=0)
    prob = MS.merge_problems([prob], 4)
    theta = _theta(p)
    tgt = prob.target.numpy() + rng.normal(0, 0.01, tuple(prob.target.shape))
    img = prob.image.numpy()
    for b in range(4):  # a cast shadow: 10 % of the image's pixels at 30 % brightness
        idx = np.nonzero(img == b)[0]
        tgt[idx[: len(idx) // 10]] *= 0.3
    prob.target = torch.as_tensor(tgt)
    k = 3.0
    w, frac = MS.robust_weights(prob, theta, k)
    r = MS._render(prob, *theta).numpy() - tgt
    w0 = prob.weight.numpy()
    want = np.zeros_like(w0)
    left = 0
    for b in range(4):
        idx = np.nonzero(img == b)[0]
        rb = r[idx]
        dev = np.abs(rb - np.median(rb, 0))
        s = 1.4826 * np.median(dev)
        bad = (dev > k * s).any(1)
        left += bad.sum()
        want[idx] = np.where(bad, 0.0, w0[idx] * len(idx) / (~bad).sum())
        assert bad[: len(idx) // 10].mean() > 0.9  # the shadow is found
        np.testing.assert_allclose(want[idx].sum(), w0[idx].sum())  # each image keeps its share
    np.testing.assert_allclose(w.numpy(), want, rtol=1e-12)
    assert frac == pytest.approx(left / len(w0))


def test_constrained_alternating_update_lowers_its_objective(small):
    """Harmonics, robust pixels and a low-rank change together, 3 rounds on images of the truth model from a wrong
    initial mean: every solve lowers its objective, the refined training objective never rises from one round to
    the next, and the model moves towards the truth."""
    from _shards import wrong_initial

    d, ss = small["d"], small["ss"]
    wrong = wrong_initial(d["truth"], d["V"])
    cfg = MS.SolveConfig(rounds=3, pull=1e-4, cg_iterations=300, max_pixels=0, harmonics=20, robust=4.0,
                         update_bases=1)
    arrays, rep = MS.alternate(wrong, d["light"], ss, cfg, mesh=(d["V"], d["tri"]))
    train = [r["train_refined_objective"] for r in rep.rounds[1:]]
    for r in rep.rounds[1:]:
        assert r["solve_end"] < r["solve_start"]
        assert 0.0 <= r["pixels_left_out"] < 0.5
    assert all(b <= a * (1 + 1e-9) for a, b in zip(train, train[1:]))
    before = np.abs(np.asarray(wrong.vertex_albedo_mean) - np.asarray(d["truth"].vertex_albedo_mean)).mean()
    after = np.abs(arrays["vertex_albedo_mean"] - np.asarray(d["truth"].vertex_albedo_mean)).mean()
    assert after < before
    np.testing.assert_array_equal(arrays["vertex_albedo_basis"][1:], np.asarray(wrong.vertex_albedo_basis)[1:])


def test_harmonics_need_the_mesh(small):
    from reflectmm_cli.errors import ReflectmmError

    d = small["d"]
    with pytest.raises(ReflectmmError, match="face mesh"):
        MS.alternate(d["truth"], d["light"], small["ss"], MS.SolveConfig(rounds=1, harmonics=4))
    with pytest.raises(ReflectmmError, match="harmonics"):
        MS.SolveConfig(harmonics=-1)


def test_a_round_that_does_not_lower_the_objective_is_said(reflectmm_log):
    # --ls-pull 0 gave a model equal to the initial one without a word
    from reflectmm_cli.finetune.model_solve import warn_no_progress

    warn_no_progress(1, {"f_start": 0.5, "f_end": 0.4})
    assert not reflectmm_log
    warn_no_progress(2, {"f_start": 0.013107, "f_end": 0.013107})
    assert len(reflectmm_log) == 1 and "round 2 did not lower the training objective" in reflectmm_log[0]
