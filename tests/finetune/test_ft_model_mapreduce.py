"""The map-reduce of the least-squares model update (finetune/model_mapreduce.py): the reduced normal equations
against a dense Jacobian built from the renderer, the sum of the shards' equations against the unsharded ones, the
Cholesky solve against a dense solve and against the CG, and the sharded rounds against one process, serially, on
the process pool and on Dask."""
import numpy as np
import pytest
import torch

from _shards import wrong_initial
from reflectmm_cli.finetune import model_mapreduce as MR
from reflectmm_cli.finetune import model_solve as MS
from reflectmm_cli.threads import torch_threads
from test_ft_model_solve import _dense_system, _harmonic_columns, _relative_reg, small_data


@pytest.fixture(scope="module")
def small(tmp_path_factory):
    from reflectmm_cli.geometry.harmonics import mesh_harmonics

    s = small_data(tmp_path_factory.mktemp("mapreduce"), 8)
    d, ss, gb, p, beta, gamma, z = (s[k] for k in ("d", "ss", "gb", "p", "beta", "gamma", "z"))
    rng = np.random.default_rng(7)
    prob = MS.build_problem(p, d["light"], gb, beta, gamma, z, max_pixels=0)
    prob.target = prob.target + torch.tensor(rng.normal(0, 0.02, tuple(prob.target.shape)))
    prob = MS.merge_problems([prob], 4)
    theta0 = [p.albedo_mean.clone(), p.albedo_basis.clone(), p.weights_mean.clone(), p.weights_basis.clone()]
    start = [t + 0.01 * torch.as_tensor(rng.normal(size=tuple(t.shape))) for t in theta0]
    phi = mesh_harmonics(d["V"], d["tri"], 6)[0]
    return dict(d=d, ss=ss, prob=prob, theta0=theta0, start=start, phi=phi)


def _u_order(theta0, Q):
    """Permutation from U's layout (M+1, Q, A) to the parts' flat layout [am (Q,3), ab (M,Q,3), wm (Q,K), wb]."""
    M, K = theta0[1].shape[0], theta0[2].shape[1]
    idx = np.arange((M + 1) * Q * (3 + K)).reshape(M + 1, Q, 3 + K)
    return np.concatenate([idx[0, :, :3].ravel(), idx[1:, :, :3].ravel(), idx[0, :, 3:].ravel(),
                           idx[1:, :, 3:].ravel()])


def test_reduced_normal_equations_equal_the_dense_jacobians(small):
    """H = JᵀWJ and g = JᵀWr of the data term in U, f = rᵀWr, against the Jacobian built column by column from the
    linear renderer (the pull set to zero in the dense system)."""
    prob, theta0, start, phi = small["prob"], small["theta0"], small["start"], small["phi"]
    A = _harmonic_columns(phi, [t.shape for t in theta0])
    H_d, g_d, _ = _dense_system(prob, theta0, start, 0.0, A, reg=np.zeros(A.shape[0]))
    H, g, f = MR.normal_equations(prob, start, torch.as_tensor(phi), image_chunk=3)
    o = _u_order(theta0, phi.shape[1])
    np.testing.assert_allclose(H[np.ix_(o, o)], H_d, rtol=1e-10, atol=1e-13 * np.abs(H_d).max())
    np.testing.assert_allclose(g[o], g_d, rtol=1e-10, atol=1e-13 * np.abs(g_d).max())
    r = MS._render(prob, *start) - prob.target
    assert f == pytest.approx(float((prob.weight[:, None] * r * r).sum()), rel=1e-12)


def test_the_reduce_of_shards_equals_the_unsharded_normal_equations(small):
    """The problem cut into image groups (1 + 3 images, then 2 + 2): the sum of the groups' (H, g, f) equals the
    whole problem's."""
    prob, start, phi = small["prob"], small["start"], torch.as_tensor(small["phi"])
    H, g, f = MR.normal_equations(prob, start, phi)
    for groups in ([[0], [1, 2, 3]], [[0, 1], [2, 3]]):
        Hs, gs, fs = 0, 0, 0.0
        for grp in groups:
            sel = torch.nonzero(torch.isin(prob.image, torch.tensor(grp))).reshape(-1)
            part = MS.SolveProblem(**{k: (v[:, sel] if k == "S" else v[sel]) for k, v in vars(prob).items()})
            h, gg, ff = MR.normal_equations(part, start, phi)
            Hs, gs, fs = Hs + h, gs + gg, fs + ff
        np.testing.assert_allclose(Hs, H, rtol=1e-12, atol=1e-15 * np.abs(H).max())
        np.testing.assert_allclose(gs, g, rtol=1e-12, atol=1e-15 * np.abs(g).max())
        assert fs == pytest.approx(f, rel=1e-12)


@pytest.mark.parametrize("pull_scale,update_bases", [("element", -1), ("relative", -1), ("element", 1)])
def test_cholesky_solve_equals_the_dense_solution_and_the_cg(small, pull_scale, update_bases):
    """The reduced normal equations plus the pull, solved by Cholesky, equal the dense least-squares solution in u
    (from a start away from θ₀; the relative pull per array; the later bases frozen) and the CG solve to its
    tolerance (1e-13 relative residual: the two differ by ~1e-10 of the largest value)."""
    prob, theta0, start, phi = small["prob"], small["theta0"], small["start"], small["phi"]
    shapes = [t.shape for t in theta0]
    A = _harmonic_columns(phi, shapes)
    pull = 0.3
    reg = _relative_reg(theta0, pull) if pull_scale == "relative" else None
    if update_bases >= 0:  # the unknowns of the frozen bases are dropped from the dense system
        ushapes = [t.shape[:-2] + (phi.shape[1], t.shape[-1]) for t in theta0]
        free = torch.cat([m.reshape(-1) for m in MS._free_mask(ushapes, update_bases, torch.float64)]).numpy() > 0
        A = A[:, free]
    H_d, g_d, _ = _dense_system(prob, theta0, start, pull, A, reg=reg)
    want = torch.cat([t.reshape(-1) for t in start]).numpy() + A @ np.linalg.solve(H_d, -g_d)
    basis = torch.as_tensor(phi)
    H, g, f = MR.normal_equations(prob, start, basis)
    theta, info = MR.solve_normal_equations(H, g, f, start, theta0, basis, pull=pull, update_bases=update_bases,
                                            pull_scale=pull_scale)
    got = torch.cat([t.reshape(-1) for t in theta]).numpy()
    np.testing.assert_allclose(got, want, atol=1e-9 * max(1.0, np.abs(want).max()))
    cg, cinfo = MS.solve_model(prob, theta0, start, pull=pull, cg_iterations=4000, cg_tol=1e-13, basis=basis,
                               update_bases=update_bases, pull_scale=pull_scale)
    np.testing.assert_allclose(got, torch.cat([t.reshape(-1) for t in cg]).numpy(),
                               atol=1e-9 * max(1.0, np.abs(want).max()))
    assert info["f_start"] == pytest.approx(cinfo["f_start"], rel=1e-10)
    assert info["f_end"] == pytest.approx(cinfo["f_end"], rel=1e-8) and info["f_end"] < info["f_start"]


def test_no_pull_and_unseen_harmonics_is_a_one_line_error(small):
    from reflectmm_cli.errors import ReflectmmError

    prob, theta0, start = small["prob"], small["theta0"], small["start"]
    phi = np.zeros((small["phi"].shape[0], 2))
    phi[:, 0] = small["phi"][:, 0]  # the second function is zero: no pixel sees it
    H, g, f = MR.normal_equations(prob, start, torch.as_tensor(phi))
    with pytest.raises(ReflectmmError, match="not positive definite"):
        MR.solve_normal_equations(H, g, f, start, theta0, torch.as_tensor(phi), pull=0.0)


def test_shard_groups_are_whole_refinement_batches():
    idx = np.arange(11)
    groups = MR.shard_groups(idx, 3, 2)
    assert [len(x) for x in groups] == [4, 4, 3]
    np.testing.assert_array_equal(np.concatenate(groups), idx)


@pytest.mark.parametrize("harmonics", [0, 6])
def test_sharded_rounds_equal_one_process(small, harmonics):
    """Two rounds from a wrong model, shards of 2 images in batches of 2 (3 map tasks for the 6 training images):
    per vertex the arrays equal :func:`alternate`'s bit for bit (the same pixels, the same CG); with 6 harmonics they
    equal alternate's with its CG run to a 1e-13 residual to 1e-6 of the largest value (float32 output)."""
    d, ss = small["d"], small["ss"]
    wrong = wrong_initial(d["truth"], d["V"])
    cfg = MS.SolveConfig(rounds=2, pull=1e-2, cg_iterations=3000, cg_tol=1e-13, max_pixels=0, harmonics=harmonics,
                         robust=4.0)
    mesh = (d["V"], d["tri"])
    with torch_threads(1):  # the map tasks' thread count
        want, wrep = MS.alternate(wrong, d["light"], ss, cfg, mesh=mesh, batch_size=2)
    cfg2 = MS.SolveConfig(**{**cfg.__dict__, "shard_images": 2})
    got, grep = MR.alternate_sharded(wrong, d["light"], ss, cfg2, mesh=mesh, batch_size=2)
    for k in want:
        if harmonics:
            np.testing.assert_allclose(got[k], want[k], rtol=0, atol=1e-6 * np.abs(want[k]).max())
        else:
            np.testing.assert_array_equal(got[k], want[k])
    assert grep.best_round == wrep.best_round
    for a, b in zip(grep.rounds[1:], wrep.rounds[1:]):
        assert a["solve_end"] < a["solve_start"]
        assert a["train_refined_objective"] == pytest.approx(b["train_refined_objective"], rel=1e-6)
        assert a["pixels_left_out"] == pytest.approx(b["pixels_left_out"], rel=1e-12)


def test_the_process_pool_and_dask_give_the_serial_result(small):
    """jobs = 2 on the process pool, and a 2-worker Dask LocalCluster: the same arrays as the serial map, bit for
    bit (the reduce sums the shards in their order whichever finishes first)."""
    d, ss = small["d"], small["ss"]
    wrong = wrong_initial(d["truth"], d["V"])
    cfg = MS.SolveConfig(rounds=1, pull=1e-2, max_pixels=0, harmonics=6, shard_images=2)
    mesh = (d["V"], d["tri"])
    serial, _ = MR.alternate_sharded(wrong, d["light"], ss, cfg, mesh=mesh, batch_size=2)
    pool, _ = MR.alternate_sharded(wrong, d["light"], ss, cfg, mesh=mesh, batch_size=2, executor="pool", jobs=2)
    for k in serial:
        np.testing.assert_array_equal(pool[k], serial[k])
    pytest.importorskip("distributed")
    dask, _ = MR.alternate_sharded(wrong, d["light"], ss, cfg, mesh=mesh, batch_size=2, executor="dask", jobs=2)
    for k in serial:
        np.testing.assert_array_equal(dask[k], serial[k])
