"""The landmark embedding (face-model embed-landmarks) on the independent toy model: a detector whose points sit
on other vertices than the model's is measured back exactly, from projections alone."""

import numpy as np
import pytest

import toy
from reflectmm_cli.errors import ReflectmmError
from reflectmm_cli.geometry.camera import project
from reflectmm_cli.geometry_fit.embedding import embed_landmarks, landmark_hits
from reflectmm_cli.geometry_fit.landmarks import GROUPS

AZ = [-20, 0, 20]


def _detector_vertices(m, shift_mm=8.0):
    """A 'detector convention': each landmark vertex replaced by the vertex nearest to a point shift_mm away on
    the front of the face (up for brows and eyes, sideways for the mouth), an independent choice of vertices."""
    mean = m.mean
    target = mean[m.landmarks].copy()
    target[17:48, 1] += shift_mm
    target[48:68, 0] *= 1.3
    target[48:68, 1] -= 5.0
    det = np.array([np.argmin(((mean - p) ** 2).sum(1) + 1e6 * (mean[:, 2] < p[2] - 15)) for p in target])
    return det


def _views(m, det, n_id=3, noise=0.0, seed=0):
    rng = np.random.default_rng(seed)
    K, R, t = toy.arc_cameras(AZ)
    out = []
    for _ in range(n_id):
        verts = m.vertices(rng.normal(size=m.n_shape) * m.shape_sigma * 0.8,
                           rng.normal(size=m.n_exp) * m.exp_sigma * 0.5)
        for v in range(len(AZ)):
            pts = project(verts[det], K[v], R[v], t[v])[0] + rng.normal(size=(68, 2)) * noise
            out.append((verts, K[v], R[v], t[v], pts))
    return out


def test_exact_projections_give_the_detector_vertices():
    m = toy.toy_model()
    det = _detector_vertices(m)
    assert (det[17:] != m.landmarks[17:]).mean() > 0.8  # most points really move
    emb = embed_landmarks(m.mean, m.triangles, m.landmarks, _views(m, det), groups=tuple(GROUPS))
    inner = np.arange(17, 68)
    np.testing.assert_array_equal(emb.indices[inner], det[inner])
    moved = np.linalg.norm(m.mean[det] - m.mean[m.landmarks], axis=1)
    np.testing.assert_allclose(emb.moved_mm[inner], moved[inner], atol=1e-9)
    # (a point hidden behind the nose in a side view, or a ray through an edge of the open grid, may not vote)
    assert (emb.views[inner] >= 8).all() and np.nanmax(emb.spread_mm[inner]) < 1e-3


def test_noisy_points_land_near_and_the_jaw_keeps_its_vertices_by_default():
    m = toy.toy_model()
    det = _detector_vertices(m)
    emb = embed_landmarks(m.mean, m.triangles, m.landmarks, _views(m, det, n_id=6, noise=1.0, seed=2))
    jaw = slice(*GROUPS["jaw"])
    np.testing.assert_array_equal(emb.indices[jaw], m.landmarks[jaw])
    assert not emb.embedded[jaw].any() and (emb.moved_mm[jaw] == 0).all()
    # 1 px at 1000 px focal and 1.3 m is 1.3 mm on the face; the median of 18 views is well within a few mm
    err = np.linalg.norm(m.mean[emb.indices[17:]] - m.mean[det[17:]], axis=1)
    assert np.median(err) < 1.5 and err.max() < 5.0, (np.median(err), err.max())
    assert np.nanmedian(emb.spread_mm[17:]) > 0.3  # the noise shows in the spread


def test_missing_and_off_mesh_points_do_not_vote():
    m = toy.toy_model()
    det = _detector_vertices(m)
    views = _views(m, det)
    verts, K, R, t, pts0 = views[1]
    tri, bary = landmark_hits(verts, m.triangles, K, R, t, pts0)
    assert (tri[17:] >= 0).all() and np.allclose(np.nansum(bary, 1)[tri >= 0], 1)
    pts = views[1][4].copy()
    pts[40] = np.nan
    pts[41] = [-5000.0, -5000.0]  # outside the image: the ray misses the head
    tri2, _ = landmark_hits(verts, m.triangles, K, R, t, pts)
    assert tri2[40] == -1 and tri2[41] == -1
    # only two views have landmark 36: with min_views 3 it keeps its vertex, the others move
    sparse = [(v, K, R, t, np.where(np.arange(68)[:, None] == 36, np.nan, p) if k > 1 else p)
              for k, (v, K, R, t, p) in enumerate(views)]
    emb = embed_landmarks(m.mean, m.triangles, m.landmarks, sparse, min_views=3)
    assert emb.views[36] == 2 and not emb.embedded[36] and emb.indices[36] == m.landmarks[36]
    assert emb.indices[37] == det[37]


def test_bad_arguments_are_refused():
    m = toy.toy_model()
    views = _views(m, _detector_vertices(m), n_id=1)
    with pytest.raises(ReflectmmError, match="unknown landmark group"):
        embed_landmarks(m.mean, m.triangles, m.landmarks, views, groups=("chin",))
    with pytest.raises(ReflectmmError, match="min_views"):
        embed_landmarks(m.mean, m.triangles, m.landmarks, views, min_views=0)
    with pytest.raises(ReflectmmError, match="no view"):
        embed_landmarks(m.mean, m.triangles, m.landmarks, [])
    with pytest.raises(ReflectmmError, match="vertices"):
        embed_landmarks(m.mean, m.triangles, m.landmarks, [(m.mean[:10],) + views[0][1:]])


def test_mutated_points_never_break_the_embedding():
    """Hypothesis: detector points with NaNs, far-off or huge values give a valid embedding: indices in range,
    no landmark moved with fewer votes than min_views, votes never more than the views."""
    from hypothesis import HealthCheck, given, settings
    from hypothesis import strategies as st

    m = toy.toy_model()
    base = _views(m, _detector_vertices(m), n_id=1)

    @settings(max_examples=25, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
    @given(st.lists(st.tuples(st.integers(0, 2), st.integers(0, 67),
                              st.sampled_from([np.nan, np.inf, -1e9, 1e9, 0.0, 320.0])), max_size=40),
           st.integers(1, 3))
    def check(edits, min_views):
        views = [list(v) for v in base]
        for v in views:
            v[4] = v[4].copy()
        for vi, j, val in edits:
            views[vi][4][j] = val
        emb = embed_landmarks(m.mean, m.triangles, m.landmarks, [tuple(v) for v in views], min_views=min_views)
        assert emb.indices.shape == (68,) and (emb.indices >= 0).all() and (emb.indices < len(m.mean)).all()
        assert (emb.views <= len(views)).all()
        assert not (emb.embedded & (emb.views < min_views)).any()
        assert (emb.indices[~emb.embedded] == m.landmarks[~emb.embedded]).all()
        assert np.isfinite(emb.moved_mm).all()

    check()


def _biased_views(m, det, offsets_iod, n_id=4, noise=0.0, seed=0, scale=1.0):
    """Views of n_id identities on the arc whose detector points are the projected vertices plus a per-camera offset
    of offsets_iod[v] (68, 2) inter-ocular distances (the eye centres of the unbiased points), each face scaled."""
    from reflectmm_cli.landmarks import inter_ocular

    rng = np.random.default_rng(seed)
    K, R, t = toy.arc_cameras(AZ)
    out = []
    for _ in range(n_id):
        verts = scale * m.vertices(rng.normal(size=m.n_shape) * m.shape_sigma * 0.8,
                                   rng.normal(size=m.n_exp) * m.exp_sigma * 0.5)
        for v in range(len(AZ)):
            clean = project(verts[det], K[v], R[v], t[v])[0]
            iod = inter_ocular(clean)
            # the offset is fixed relative to the biased points' own eyes: solve p = clean + iod(p) · o by iteration
            p = clean + iod * offsets_iod[v]
            for _ in range(50):
                p = clean + inter_ocular(p) * offsets_iod[v]
            out.append((f"cam{v}", verts, K[v], R[v], t[v], p + rng.normal(size=(68, 2)) * noise))
    return out


def _offsets(seed=4):
    rng = np.random.default_rng(seed)
    o = rng.normal(size=(len(AZ), 68, 2)) * 0.02
    o[:, :17] = 0.0                                              # the jaw gets none (default groups)
    return o


def test_view_bias_recovers_each_cameras_offsets_and_taking_them_off_gives_the_projections():
    from reflectmm_cli.geometry_fit.embedding import apply_view_bias, view_bias

    m = toy.toy_model()
    det = _detector_vertices(m)
    off = _offsets()
    views = _biased_views(m, det, off)
    bias = view_bias(det, views)
    assert sorted(bias) == [f"cam{v}" for v in range(len(AZ))]
    for v in range(len(AZ)):
        assert bias[f"cam{v}"]["identities"] == 4
        np.testing.assert_allclose(bias[f"cam{v}"]["offset_iod"], off[v], atol=1e-9)
    # taken off the points of a face of another size (0.8×), the offsets leave the exact projections
    other = _biased_views(m, det, off, n_id=1, seed=9, scale=0.8)
    lm = np.stack([v[5] for v in other])                         # (C, 68, 2)
    fixed, done = apply_view_bias(lm, [v[0] for v in other], bias)
    assert done == [v[0] for v in other]
    for (name, verts, K, R, t, _), p in zip(other, fixed):
        np.testing.assert_allclose(p, project(verts[det], K, R, t)[0], atol=1e-6)
    # the jaw (outside the default groups) keeps its points; a camera without an entry is left as it is
    np.testing.assert_array_equal(fixed[:, :17], lm[:, :17])
    same, done = apply_view_bias(lm, ["a", "b", "c"], bias)
    assert done == [] and np.array_equal(same, lm)


def test_view_bias_averages_noise_and_keeps_missing_points_and_views_without_eyes_out():
    from reflectmm_cli.geometry_fit.embedding import apply_view_bias, view_bias

    m = toy.toy_model()
    det = _detector_vertices(m)
    off = _offsets(seed=5)
    views = _biased_views(m, det, off, n_id=40, noise=0.5, seed=3)
    bias = view_bias(det, views)
    err = np.abs(np.stack([bias[f"cam{v}"]["offset_iod"] for v in range(len(AZ))]) - off)[:, 17:]
    iod = 60.0  # the toy's inter-ocular distance in pixels is about this: 0.5 px of noise over 40 views ≈ 0.0013
    assert err.mean() < 0.5 / iod / np.sqrt(40) * 2, err.mean()
    # a view without one eye is left out of the mean and out of the correction
    views2 = [list(v) for v in _biased_views(m, det, off, n_id=2)]
    views2[0][5] = views2[0][5].copy()
    views2[0][5][36:42] = np.nan
    bias2 = view_bias(det, [tuple(v) for v in views2])
    assert bias2["cam0"]["identities"] == 1
    lm = np.stack([views2[0][5]])[None]                              # (1, 1, 68, 2)
    out, done = apply_view_bias(lm, ["cam0"], bias2)
    assert done == [] and np.array_equal(out, lm, equal_nan=True)


def test_a_face_models_offsets_are_applied_only_where_it_has_them():
    from reflectmm_cli.geometry_fit.embedding import correct_by_face_model

    lm = np.random.default_rng(0).normal(size=(2, 3, 68, 2)) * 5 + 100
    lm[..., 36:42, 0] -= 30                                      # eyes apart: a positive inter-ocular distance
    same, note = correct_by_face_model(lm, ["a", "b", "c"], {})
    assert note is None and np.array_equal(same, lm)
    info = {"landmark_view_bias": {"cameras": {"b": {"offset_iod": np.full((68, 2), 0.01).tolist(),
                                                     "identities": 2}}}}
    fixed, note = correct_by_face_model(lm, ["a", "b", "c"], info)
    assert "camera(s) b" in note and "no offsets for camera(s) a, c" in note
    np.testing.assert_array_equal(fixed[:, [0, 2]], lm[:, [0, 2]])
    assert (fixed[:, 1] < lm[:, 1]).all()
    with pytest.raises(ReflectmmError, match="offsets"):
        correct_by_face_model(lm, ["a", "b", "c"],
                              {"landmark_view_bias": {"cameras": {"a": {"offset_iod": [[0.0, 0.0]]}}}})
    with pytest.raises(ReflectmmError, match=r"^fm\.npz: view bias of camera a"):
        correct_by_face_model(lm, ["a", "b", "c"],
                              {"landmark_view_bias": {"cameras": {"a": {"offset_iod": [[0.0, 0.0]]}}}}, "fm.npz")


def test_mutated_points_never_give_non_finite_offsets_or_corrections():
    """Hypothesis: detector points with NaN, inf or huge values: the offsets stay finite (a view whose eyes are not
    finite is left out, a point that is not finite does not vote), and taking them off leaves finite points finite
    and missing ones missing."""
    from hypothesis import HealthCheck, given, settings
    from hypothesis import strategies as st

    from reflectmm_cli.geometry_fit.embedding import apply_view_bias, view_bias

    m = toy.toy_model()
    det = _detector_vertices(m)
    base = _biased_views(m, det, _offsets(), n_id=2)

    @settings(max_examples=30, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
    @given(st.lists(st.tuples(st.integers(0, len(base) - 1), st.integers(0, 67), st.integers(0, 1),
                              st.sampled_from([np.nan, np.inf, -np.inf, -1e9, 1e9, 0.0])), max_size=30))
    def check(edits):
        views = [list(v) for v in base]
        for v in views:
            v[5] = v[5].copy()
        for vi, j, c, val in edits:
            views[vi][5][j, c] = val
        bias = view_bias(det, [tuple(v) for v in views])
        for entry in bias.values():
            assert np.isfinite(entry["offset_iod"]).all() and 1 <= entry["identities"] <= 2
        lm = np.stack([v[5] for v in views[:len(AZ)]])
        out, _ = apply_view_bias(lm, [v[0] for v in views[:len(AZ)]], bias)
        fin = np.isfinite(lm)
        assert np.isnan(out[np.isnan(lm)]).all()
        # a finite point stays finite unless its view's eyes are huge (then the offset times the inter-ocular
        # distance may overflow to ±inf, never to NaN)
        assert not np.isnan(out[fin]).any()

    check()


def test_a_capture_given_twice_is_refused_in_the_embeddings_words(tmp_path):
    """The check is calibrate-rig's; its message named the calibration."""
    from reflectmm_cli.artifacts import write_artifact
    from reflectmm_cli.stages.face_model_embed import _views

    cap = write_artifact(tmp_path / "c.npz", "capture", {
        "view_names": np.array(["05_1"]), "landmarks": np.full((1, 68, 2), 20.0), "image_size": np.array([64, 48])},
        extra_meta={"report": {"identity": "001"}})
    with pytest.raises(ReflectmmError, match=r"identity 001 is given twice \(also .*c.npz\): each identity counts "
                                             r"once in the embedding$"):
        _views([cap, cap], [], 100)
