"""Face models: the procedural model, linear evaluation, normals, artifact round trip and the BFM loaders."""
import numpy as np
import pytest
import scipy.io
import torch
from hypothesis import given
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays

from reflectmm_cli.errors import ReflectmmError
from reflectmm_cli.geometry import (
    FaceModel,
    load_bfm09,
    load_bfm_front,
    load_face_model,
    procedural_face_model,
    save_face_model,
    vertex_normals,
)
from reflectmm_cli.geometry.face_model import face_normals

# iBUG 68 left/right landmark pairs (0-based)
IBUG_PAIRS = ([(i, 16 - i) for i in range(8)] + [(17 + i, 26 - i) for i in range(5)]
              + [(31, 35), (32, 34), (36, 45), (37, 44), (38, 43), (39, 42), (40, 47), (41, 46),
                 (48, 54), (49, 53), (50, 52), (59, 55), (58, 56), (60, 64), (61, 63), (67, 65)])


@pytest.fixture(scope="module")
def small():
    return procedural_face_model(grid=(61, 51), n_shape=12, n_exp=8, seed=3)


def test_procedural_deterministic_and_seeded(small):
    again = procedural_face_model(grid=(61, 51), n_shape=12, n_exp=8, seed=3)
    other = procedural_face_model(grid=(61, 51), n_shape=12, n_exp=8, seed=4)
    for k in ("mean_shape", "shape_basis", "exp_basis", "triangles", "uv", "landmarks", "skin_mask"):
        np.testing.assert_array_equal(getattr(small, k), getattr(again, k))
    np.testing.assert_array_equal(small.mean_shape, other.mean_shape)  # the seed drives only the bases
    assert not np.allclose(small.shape_basis, other.shape_basis)


def test_procedural_default_size_and_extent():
    m = procedural_face_model(n_vertices=8000, n_shape=10, n_exp=5)
    assert 7000 < m.n_vertices < 9000
    ext = m.mean_shape.max(0) - m.mean_shape.min(0)
    assert 130 < ext[0] < 170 and 190 < ext[1] < 210  # ~ 150 mm × 200 mm face
    assert m.shape_basis.shape == (10, m.n_vertices, 3) and m.exp_basis.shape == (5, m.n_vertices, 3)


def test_procedural_orientation_outward(small):
    fn = face_normals(small.mean_shape, small.triangles)
    c = small.mean_shape[small.triangles].mean(1)
    radial = c * np.array([1.0, 0.0, 1.0])  # away from the vertical head axis
    frac = np.mean((fn * radial).sum(1) > 0)
    assert frac > 0.97, frac


def test_procedural_symmetry(small):
    mi = small.mirror_index()
    np.testing.assert_allclose(small.mean_shape[mi], small.mean_shape * [-1, 1, 1], atol=1e-3)
    np.testing.assert_allclose(small.uv[mi, 0], 1 - small.uv[:, 0], atol=1e-6)
    np.testing.assert_allclose(small.uv[mi, 1], small.uv[:, 1], atol=1e-6)
    assert np.all(small.uv >= 0) and np.all(small.uv <= 1)
    # the stored map agrees with the geometric nearest-neighbour map
    m2 = FaceModel(small.mean_shape, None, None, None, None, small.triangles, small.uv, small.landmarks,
                   small.skin_mask)
    np.testing.assert_array_equal(m2.mirror_index(), mi)
    np.testing.assert_array_equal(small.skin_mask[mi], small.skin_mask)


def test_procedural_landmarks_anatomy():
    m = procedural_face_model(n_vertices=20000, n_shape=4, n_exp=2)
    p = m.mean_shape[m.landmarks]
    assert len(set(m.landmarks.tolist())) == 68
    for a, b in IBUG_PAIRS:
        np.testing.assert_allclose(p[a] * [-1, 1, 1], p[b], atol=2.0)
    assert p[36, 0] < 0 < p[45, 0]  # iBUG 36 is the subject's right eye (image left) → −x
    assert np.argmax(p[:, 2]) == 30  # nose tip is the most forward landmark
    assert np.argmin(p[:, 1]) == 8  # chin is the lowest
    assert p[19, 1] > p[37, 1] > p[30, 1] > p[51, 1] > p[57, 1] > p[8, 1]  # brow > eye > nose > lips > chin
    eye_c = p[36:42].mean(0)
    eye_v = np.argmin(np.linalg.norm(m.mean_shape - eye_c, axis=1))
    assert not m.skin_mask[eye_v]  # eye interior is not skin
    assert m.skin_mask.mean() > 0.95


def test_bases_orthonormal_and_linear(small):
    B = small.shape_basis.reshape(small.n_shape, -1).astype(np.float64)
    np.testing.assert_allclose(B @ B.T, np.eye(small.n_shape), atol=1e-5)
    assert np.all(np.diff(small.shape_sigma) <= 0) and small.shape_sigma[-1] > 0
    # plausible per-vertex RMS motion at 1σ for the first component: millimetres, not noise or metres
    rms = small.shape_sigma[0] / np.sqrt(small.n_vertices)
    assert 0.5 < rms < 20
    a = np.random.default_rng(0).normal(size=small.n_shape) * small.shape_sigma
    e = np.random.default_rng(1).normal(size=small.n_exp) * small.exp_sigma
    ref = small.mean_shape.astype(np.float64) + np.einsum("k,knc->nc", a, small.shape_basis) \
        + np.einsum("k,knc->nc", e, small.exp_basis)
    np.testing.assert_allclose(small.vertices(a, e), ref, atol=1e-3)
    np.testing.assert_allclose(small.vertices(a[:3]), small.vertices(np.r_[a[:3], np.zeros(small.n_shape - 3)]))
    with pytest.raises(ReflectmmError, match="coefficients"):
        small.vertices(np.zeros(small.n_shape + 1))


def test_vertices_torch_matches_and_differentiates(small):
    a = torch.tensor(np.random.default_rng(2).normal(size=small.n_shape) * 5, dtype=torch.float64,
                     requires_grad=True)
    e = torch.zeros(small.n_exp, dtype=torch.float64)
    v = small.vertices_torch(a, e)
    np.testing.assert_allclose(v.detach().numpy(), small.vertices(a.detach().numpy()), atol=1e-3)
    v[10, 2].backward()
    np.testing.assert_allclose(a.grad.numpy(), small.shape_basis[:, 10, 2], atol=1e-6)
    vb = small.vertices_torch(torch.zeros(2, small.n_shape, dtype=torch.float64))
    assert vb.shape == (2, small.n_vertices, 3)


def _icosphere(r=1.0, sub=3):
    import trimesh

    s = trimesh.creation.icosphere(subdivisions=sub, radius=r)
    return np.asarray(s.vertices), np.asarray(s.faces)


def test_vertex_normals_sphere_numpy_and_torch():
    errs = []
    for sub in (3, 4, 5):
        v, f = _icosphere(50.0, sub)
        n = vertex_normals(v, f)
        errs.append(np.abs(n - v / 50.0).max())
    assert errs[2] < 4e-3 and errs[2] < errs[1] < errs[0]  # converges to the analytic normal
    v, f = _icosphere(50.0, 4)
    n = vertex_normals(v, f)
    nt = vertex_normals(torch.tensor(v), torch.tensor(f))
    np.testing.assert_allclose(nt.numpy(), n, atol=1e-6)


@given(arrays(np.float64, (6, 3), elements=st.floats(-10, 10)),
       st.lists(st.tuples(*[st.integers(0, 5)] * 3), min_size=1, max_size=8))
def test_vertex_normals_degenerate_finite(v, tris):
    t = np.array(tris)
    t = np.concatenate([t, [[0, 0, 1], [2, 2, 2]]])  # always include degenerate triangles
    n = vertex_normals(v, t)
    assert np.all(np.isfinite(n))
    ln = np.linalg.norm(n, axis=1)
    assert np.all((np.abs(ln - 1) < 1e-4) | (ln == 0))
    vt = torch.tensor(v, requires_grad=True)
    nt = vertex_normals(vt, t)
    nt.sum().backward()
    assert torch.isfinite(nt).all() and torch.isfinite(vt.grad).all()


def test_artifact_round_trip(small, tmp_path):
    p = save_face_model(small, tmp_path / "fm.npz")
    back = load_face_model(p)
    for k in ("mean_shape", "shape_basis", "shape_sigma", "exp_basis", "exp_sigma", "triangles", "uv",
              "landmarks", "skin_mask", "mirror"):
        np.testing.assert_array_equal(getattr(back, k), getattr(small, k))
    assert back.name == small.name
    p2 = save_face_model(small, tmp_path / "fm2.npz")
    assert p.read_bytes() == p2.read_bytes()  # deterministic


# ------------------------------------------------------------------------------------------- BFM loaders

def _flat(a):  # (N,3) → (3N,1), x y z interleaved per vertex (BFM layout)
    return a.reshape(-1, 1)


def _basis(b):  # (K,N,3) → (3N,K)
    return b.reshape(b.shape[0], -1).T


def _write_bfm09(path, m, rng, drop=None):
    um = 1000.0  # BFM09 stores micrometres
    tex_mu = rng.uniform(50, 200, size=(m.n_vertices, 3))
    tex_pc = np.linalg.qr(rng.normal(size=(3 * m.n_vertices, 4)))[0]
    d = {"shapeMU": _flat(m.mean_shape.astype(np.float64) * um), "shapePC": _basis(m.shape_basis.astype(np.float64)),
         "shapeEV": (m.shape_sigma.astype(np.float64) * um)[:, None], "texMU": _flat(tex_mu), "texPC": tex_pc,
         "texEV": np.array([[30.0], [20.0], [10.0], [5.0]]), "tl": (m.triangles + 1).astype(np.float64),
         "segbin": np.zeros((m.n_vertices, 4))}
    if drop:
        d.pop(drop)
    scipy.io.savemat(str(path), d)
    return tex_mu, tex_pc


def test_load_bfm09(small, tmp_path):
    rng = np.random.default_rng(0)
    tex_mu, tex_pc = _write_bfm09(tmp_path / "01_MorphableModel.mat", small, rng)
    m = load_bfm09(tmp_path / "01_MorphableModel.mat")
    np.testing.assert_allclose(m.mean_shape, small.mean_shape, atol=1e-3)
    np.testing.assert_allclose(m.shape_basis, small.shape_basis, atol=1e-6)
    np.testing.assert_allclose(m.shape_sigma, small.shape_sigma, rtol=1e-5)
    np.testing.assert_array_equal(m.triangles, small.triangles)
    np.testing.assert_allclose(m.mean_tex, tex_mu / 255, atol=1e-6)
    np.testing.assert_allclose(m.tex_basis[1], tex_pc[:, 1].reshape(-1, 3), atol=1e-6)
    np.testing.assert_allclose(m.tex_sigma, np.array([30, 20, 10, 5]) / 255, rtol=1e-6)
    assert m.info["units_detected"] == "micrometres" and m.n_exp == 0
    # computed UVs (BFM09 has none): symmetric layout in [0,1], distortion reported
    assert np.all((m.uv > 0) & (m.uv < 1))
    assert 0.5 < m.info["uv_distortion"]["area_ratio_median"] < 2
    # dispatch by content, not by name
    (tmp_path / "renamed.mat").write_bytes((tmp_path / "01_MorphableModel.mat").read_bytes())
    np.testing.assert_allclose(load_face_model(tmp_path / "renamed.mat").mean_shape, m.mean_shape)


def test_load_bfm09_with_expression_subset(small, tmp_path):
    rng = np.random.default_rng(1)
    _write_bfm09(tmp_path / "bfm.mat", small, rng)
    n = small.n_vertices
    subset = np.sort(rng.choice(n, size=n - 40, replace=False))
    K = 5
    mean = rng.normal(size=3 * len(subset)).astype(np.float32)
    basis = rng.normal(size=(K, 3 * len(subset))).astype(np.float32)  # stored as K rows of 3N
    with open(tmp_path / "Exp_Pca.bin", "wb") as f:
        f.write(np.int32(K).tobytes())
        f.write(mean.astype("<f4").tobytes())
        f.write(basis.astype("<f4").tobytes())
    scipy.io.savemat(str(tmp_path / "BFM_exp_idx.mat"), {"trimIndex": (subset + 1)[:, None].astype(np.float64)})
    np.savetxt(tmp_path / "std_exp.txt", np.arange(1, K + 1, dtype=float))
    with pytest.raises(ReflectmmError, match="trimIndex"):
        load_bfm09(tmp_path / "bfm.mat", tmp_path / "Exp_Pca.bin")
    m = load_bfm09(tmp_path / "bfm.mat", tmp_path / "Exp_Pca.bin", exp_std_path=tmp_path / "std_exp.txt",
                   exp_index_path=tmp_path / "BFM_exp_idx.mat")
    assert m.exp_basis.shape == (K, n, 3)
    np.testing.assert_allclose(m.exp_basis[2, subset], basis[2].reshape(-1, 3) / 1000.0, rtol=1e-5, atol=1e-9)
    missing = np.setdiff1d(np.arange(n), subset)
    assert np.all(m.exp_basis[:, missing] == 0)
    np.testing.assert_allclose(m.exp_sigma, np.arange(1, K + 1))
    (tmp_path / "bad.bin").write_bytes(np.int32(K).tobytes() + b"\0" * 10)
    with pytest.raises(ReflectmmError, match="does not match"):
        load_bfm09(tmp_path / "bfm.mat", tmp_path / "bad.bin")


def test_load_bfm09_errors(small, tmp_path):
    rng = np.random.default_rng(0)
    _write_bfm09(tmp_path / "a.mat", small, rng, drop="shapePC")
    with pytest.raises(ReflectmmError, match="missing key 'shapePC'.*a.mat|a.mat.*missing key 'shapePC'"):
        load_bfm09(tmp_path / "a.mat")
    d = scipy.io.loadmat(str(tmp_path / "a.mat"))
    d["shapePC"] = np.zeros((3 * small.n_vertices + 3, 2))
    d["shapeEV"] = np.ones((2, 1))
    scipy.io.savemat(str(tmp_path / "b.mat"), {k: v for k, v in d.items() if not k.startswith("__")})
    with pytest.raises(ReflectmmError, match=r"'shapePC' has shape .*expected \(3·"):
        load_bfm09(tmp_path / "b.mat")
    scipy.io.savemat(str(tmp_path / "c.mat"), {"foo": np.zeros(3)})
    with pytest.raises(ReflectmmError, match="not a face model.*foo"):
        load_face_model(tmp_path / "c.mat")
    (tmp_path / "junk.mat").write_bytes(b"not a mat file at all" * 10)
    with pytest.raises(ReflectmmError, match="junk.mat"):
        load_face_model(tmp_path / "junk.mat")
    # a blank mean shape (every vertex at the origin) imported with exit 0 and failed later without the file
    _write_bfm09(tmp_path / "z.mat", small, rng)
    z = scipy.io.loadmat(str(tmp_path / "z.mat"))
    z["shapeMU"] = np.zeros_like(z["shapeMU"])
    scipy.io.savemat(str(tmp_path / "z.mat"), {k: v for k, v in z.items() if not k.startswith("__")})
    with pytest.raises(ReflectmmError, match=r"z.mat: face model: the mean shape spans 0 x 0 x 0"):
        load_face_model(tmp_path / "z.mat")


def test_nan_mean_shape_is_refused_before_the_units_are_guessed(small, tmp_path):
    """An all-NaN mean shape has a NaN extent, which read as metres ('scaling by 1000') before the NaN error."""
    import logging

    msgs = []

    class _Catch(logging.Handler):
        def emit(self, record):
            msgs.append(record.getMessage())

    logger = logging.getLogger("reflectmm")
    handler, level = _Catch(level=logging.DEBUG), logger.level
    logger.addHandler(handler)
    logger.setLevel(logging.DEBUG)
    try:
        for key in ("shapeMU", "meanshape"):
            if key == "shapeMU":
                _write_bfm09(tmp_path / "n.mat", small, np.random.default_rng(0))
            else:
                n = small.n_vertices
                scipy.io.savemat(str(tmp_path / "n.mat"), {"meanshape": np.zeros((1, 3 * n)),
                                                           "idBase": np.zeros((3 * n, 2)),
                                                           "exBase": np.zeros((3 * n, 2))})
            d = scipy.io.loadmat(str(tmp_path / "n.mat"))
            d[key] = np.full_like(d[key], np.nan, dtype=np.float64)
            scipy.io.savemat(str(tmp_path / "n.mat"), {k: v for k, v in d.items() if not k.startswith("__")})
            with pytest.raises(ReflectmmError, match=r"n.mat: face model: mean_shape has \d+ NaN or infinite"):
                load_face_model(tmp_path / "n.mat")
            assert not [m for m in msgs if "look like" in m], msgs
    finally:
        logger.removeHandler(handler)
        logger.setLevel(level)


def test_a_directory_is_not_a_face_model(tmp_path):
    (tmp_path / "fm").mkdir()
    with pytest.raises(ReflectmmError, match=r"fm: is a directory, expected a face model \(a face-model artifact"):
        load_face_model(tmp_path / "fm")


def test_load_bfm_front(small, tmp_path):
    rng = np.random.default_rng(5)
    n = small.n_vertices
    dm = 0.01  # Deep3DFaceRecon stores decimetres
    offset = np.array([0.05, -0.1, 0.3])  # not centred in the file
    kp = rng.choice(n, size=68, replace=False)
    skin = rng.random(n) > 0.2
    d = {"meanshape": (small.mean_shape * dm + offset).reshape(1, -1),
         "idBase": _basis(small.shape_basis * small.shape_sigma[:, None, None]) * dm,
         "exBase": _basis(small.exp_basis * small.exp_sigma[:, None, None]) * dm,
         "meantex": rng.uniform(0, 255, size=(1, 3 * n)), "texBase": rng.normal(size=(3 * n, 3)),
         "tri": (small.triangles + 1).astype(np.float64), "point_buf": np.ones((n, 8)),
         "keypoints": (kp + 1)[None].astype(np.float64), "skinmask": skin[None].astype(np.float64)}
    scipy.io.savemat(str(tmp_path / "BFM_model_front.mat"), d)
    m = load_face_model(tmp_path / "BFM_model_front.mat")
    ref = small.mean_shape.astype(np.float64) - small.mean_shape.mean(0)
    np.testing.assert_allclose(m.mean_shape, ref, atol=2e-3)
    np.testing.assert_array_equal(m.landmarks, kp)
    np.testing.assert_array_equal(m.skin_mask, skin)
    np.testing.assert_allclose(m.shape_sigma, 1.0)
    a = rng.normal(size=small.n_shape)
    # Deep3D coefficients multiply the pre-scaled bases directly
    np.testing.assert_allclose(m.vertices(a) - m.mean_shape, small.vertices(a * small.shape_sigma) -
                               small.mean_shape, atol=2e-3)
    d.pop("keypoints")
    scipy.io.savemat(str(tmp_path / "nokp.mat"), d)
    with pytest.raises(ReflectmmError, match="missing key 'keypoints'"):
        load_bfm_front(tmp_path / "nokp.mat")


def test_shape_variation_keeps_landmarks_on_their_features():
    """Identity components move vertices with the features (in-place heights + in-plane warps), so the landmark
    vertices of a random identity stay at the anatomical extremes they mark."""
    m = procedural_face_model(n_vertices=12000, n_shape=40, n_exp=4, seed=1)
    rng = np.random.default_rng(0)
    for _ in range(5):
        v = m.vertices(rng.normal(size=m.n_shape) * m.shape_sigma)
        p = v[m.landmarks]
        front = np.abs(v[:, 0]) < 8
        near_mid = front & (np.abs(v[:, 1] - p[30, 1]) < 25)
        # the nose-tip landmark stays within 2 mm of the most protruding mid-face point
        assert v[near_mid, 2].max() - p[30, 2] < 2.0
        assert p[36, 0] < p[39, 0] < p[30, 0] < p[42, 0] < p[45, 0]
        assert p[19, 1] > p[37, 1] > p[30, 1] > p[51, 1] > p[57, 1] > p[8, 1]


def test_samples_do_not_fold():
    """Random identities and expressions at 1σ stay a proper surface: no ray from outside hits a triangle from
    behind (a fold/self-intersection would show up as back-facing first hits)."""
    from reflectmm_cli.geometry import RayScene, orbit_camera, rasterize

    m = procedural_face_model(n_vertices=8000)
    cams = [orbit_camera(y, p, 1200, focal_px=1500, width=120, height=90) for y in (-60, 0, 60) for p in (-15, 15)]
    rng = np.random.default_rng(7)
    for _ in range(4):
        v = m.vertices(rng.normal(size=m.n_shape) * m.shape_sigma, rng.normal(size=m.n_exp) * m.exp_sigma)
        scene = RayScene(v, m.triangles)
        fn = face_normals(v, m.triangles)
        for cam in cams:
            r = rasterize(scene, cam)
            pos = r.position[r.mask]
            inner = (pos[:, 1] < 95) & (pos[:, 1] > -80) & (np.abs(pos[:, 0]) < 65)  # not over the shell's rim
            back = ((cam.center - pos) * fn[r.tri_id[r.mask]]).sum(1) < 0
            assert not np.any(back & inner), cam.name
