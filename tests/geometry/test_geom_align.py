"""geometry/align.rigid_align against known transforms and a dense least-squares solve (scipy.optimize)."""
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.optimize import least_squares
from scipy.spatial.transform import Rotation

from reflectmm_cli.geometry.align import rigid_align


def _residual_fn(src, dst, w, scale):
    sw = np.sqrt(w)[:, None]

    def f(x):
        R = Rotation.from_rotvec(x[:3]).as_matrix()
        s = np.exp(x[6]) if scale else 1.0
        return (sw * (s * src @ R.T + x[3:6] - dst)).ravel()
    return f


def _dense_solve(src, dst, w, scale, x0):
    """Generic nonlinear least squares over (rotation vector, t, log s), started near the answer."""
    sol = least_squares(_residual_fn(src, dst, w, scale), x0, xtol=1e-15, ftol=1e-15, gtol=1e-15, method="lm")
    return sol.x, 0.5 * (sol.fun ** 2).sum()


@settings(max_examples=40)
@given(st.integers(0, 2 ** 31 - 1), st.booleans(), st.integers(3, 60))
def test_recovers_a_known_rigid_or_similarity_transform(seed, scale, n):
    rng = np.random.default_rng(seed)
    src = rng.normal(size=(n, 3)) * rng.uniform(1, 500)
    R = Rotation.random(random_state=seed).as_matrix()
    t = rng.normal(size=3) * 100
    s = rng.uniform(0.2, 5.0) if scale else 1.0
    dst = s * src @ R.T + t
    Ra, ta, sa = rigid_align(src, dst, scale=scale)
    np.testing.assert_allclose(Ra, R, atol=1e-9)
    np.testing.assert_allclose(ta, t, atol=1e-8 * max(1.0, np.abs(dst).max()))
    assert sa == pytest.approx(s, rel=1e-10)
    assert np.linalg.det(Ra) == pytest.approx(1.0)


def test_two_dimensional_similarity():
    rng = np.random.default_rng(3)
    src = rng.normal(size=(7, 2))
    a = 0.7
    R = np.array([[np.cos(a), -np.sin(a)], [np.sin(a), np.cos(a)]])
    Ra, ta, sa = rigid_align(src, 2.5 * src @ R.T + [3.0, -1.0], scale=True)
    np.testing.assert_allclose(Ra, R, atol=1e-12)
    np.testing.assert_allclose(ta, [3.0, -1.0], atol=1e-12)
    assert sa == pytest.approx(2.5)


@pytest.mark.parametrize("scale", [False, True])
@pytest.mark.parametrize("weighted", [False, True])
@pytest.mark.parametrize("mirrored", [False, True])
def test_noisy_solution_is_the_least_squares_optimum(scale, weighted, mirrored):
    rng = np.random.default_rng(11 + 4 * mirrored + 2 * scale + weighted)
    n = 40
    src = rng.normal(size=(n, 3)) * [80, 60, 30]
    R = Rotation.from_rotvec([0.4, -0.9, 0.3]).as_matrix()
    dst = 1.3 * src @ R.T + [5.0, -20.0, 7.0] + rng.normal(size=(n, 3)) * 4.0
    if mirrored:  # no proper rotation fits: the reflection handling and the scale's tr(S D) are exercised
        dst[:, 0] *= -1
    w = rng.uniform(0.1, 3.0, n) if weighted else np.ones(n)
    Ra, ta, sa = rigid_align(src, dst, weights=w if weighted else None, scale=scale)
    x0 = np.concatenate([Rotation.from_matrix(Ra).as_rotvec(), ta, [np.log(sa)]])
    # start the dense solve away from the closed form; both must land on the same optimum
    x_ls, cost_ls = _dense_solve(src, dst, w, scale, x0 + rng.normal(size=7) * np.r_[0.05, 0.05, 0.05, 0, 0, 0, 0])
    cost = 0.5 * (_residual_fn(src, dst, w, scale)(x0) ** 2).sum()
    assert cost <= cost_ls * (1 + 1e-12)
    np.testing.assert_allclose(Rotation.from_rotvec(x_ls[:3]).as_matrix(), Ra, atol=1e-7)
    np.testing.assert_allclose(x_ls[3:6], ta, atol=1e-5)
    if scale:
        assert np.exp(x_ls[6]) == pytest.approx(sa, rel=1e-8)
    else:
        assert sa == 1.0


def test_weights_select_the_points():
    rng = np.random.default_rng(5)
    src = rng.normal(size=(20, 3)) * 50
    R = Rotation.from_rotvec([0.2, 0.1, -0.3]).as_matrix()
    dst = src @ R.T + [1.0, 2.0, 3.0]
    dst[10:] = rng.normal(size=(10, 3)) * 50  # garbage half, weight zero
    w = np.r_[np.ones(10), np.zeros(10)]
    Ra, ta, _ = rigid_align(src, dst, weights=w)
    np.testing.assert_allclose(Ra, R, atol=1e-10)
    np.testing.assert_allclose(ta, [1.0, 2.0, 3.0], atol=1e-9)
    Rb, tb, _ = rigid_align(src[:10], dst[:10])
    np.testing.assert_allclose(Ra, Rb, atol=1e-12)
    # uniform weights of any size give the unweighted answer
    Ru, tu, su = rigid_align(src, dst, weights=np.full(20, 7.0), scale=True)
    Rn, tn, sn = rigid_align(src, dst, scale=True)
    np.testing.assert_allclose(Ru, Rn, atol=1e-12)
    np.testing.assert_allclose(tu, tn, atol=1e-9)
    assert su == pytest.approx(sn, rel=1e-12)


def test_reflected_target_still_gives_a_proper_rotation():
    rng = np.random.default_rng(7)
    src = rng.normal(size=(30, 3)) * [100, 50, 10]
    dst = src * [1.0, 1.0, -1.0]  # a mirror image: the best proper rotation, never the reflection
    R, t, _ = rigid_align(src, dst)
    assert np.linalg.det(R) == pytest.approx(1.0)
    assert np.allclose(R @ R.T, np.eye(3), atol=1e-12)
    # it is the best proper rotation: no small turn of it does better
    cost = ((src @ R.T + t - dst) ** 2).sum()
    for _ in range(20):
        Q = Rotation.from_rotvec(rng.normal(size=3) * 0.02).as_matrix() @ R
        tq = dst.mean(0) - Q @ src.mean(0)
        assert cost <= ((src @ Q.T + tq - dst) ** 2).sum()


def test_the_three_former_sites_agree_with_it():
    from reflectmm_cli.evaluation.truth import kabsch
    from reflectmm_cli.geometry_fit.calibrate import align_to
    from reflectmm_cli.geometry_fit.init import rigid_align as init_rigid_align

    rng = np.random.default_rng(9)
    src = rng.normal(size=(12, 3)) * 300
    dst = src @ Rotation.from_rotvec([0.3, 0.2, 0.1]).as_matrix().T + 40 + rng.normal(size=(12, 3))
    R, t, _ = rigid_align(src, dst)
    for Rk, tk in (kabsch(src, dst), init_rigid_align(src, dst)[:2], align_to(src, dst)[:2]):
        np.testing.assert_array_equal(Rk, R)
        np.testing.assert_array_equal(tk, t)
    np.testing.assert_allclose(init_rigid_align(src, dst)[2], np.linalg.norm(src @ R.T + t - dst, axis=1))


def test_bad_shapes_are_refused():
    with pytest.raises(ValueError, match="rigid_align"):
        rigid_align(np.zeros((5, 3)), np.zeros((4, 3)))
    with pytest.raises(ValueError, match="rigid_align"):
        rigid_align(np.zeros((5, 4)), np.zeros((5, 4)))
    with pytest.raises(ValueError, match="weights"):
        rigid_align(np.ones((5, 3)), np.ones((5, 3)), weights=np.zeros(5))
