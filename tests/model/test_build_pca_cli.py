"""build-pca end to end through the CLI on small synthetic reflectance-maps artifacts."""
import numpy as np
import pytest

from reflectmm_cli.artifacts import read_artifact, read_image, write_artifact
from reflectmm_cli.model import model_from_arrays, sample_model


def _write_maps(ws, n=5, S=16, seed=0):
    rng = np.random.default_rng(seed)
    mask = np.zeros((S, S), bool)
    mask[2:-2, 3:-3] = True
    truth = []
    for i in range(n):
        a = rng.uniform(0.1, 0.8, (3, S, S)) * mask
        w = rng.uniform(0.0, 0.3, (3, S, S)) * mask
        truth.append((a, w))
        write_artifact(ws / "fit-reflectance" / f"{i:03d}.npz", "reflectance-maps",
                       {"albedo": a.astype(np.float32), "weights": w.astype(np.float32),
                        "exponents": np.array([1.0, 8.0, 64.0]), "mask": mask, "flagged": np.zeros((S, S), bool)},
                       extra_meta={"identity": f"{i:03d}"})
    return truth, mask


def _face_model(path):
    from reflectmm_cli.geometry.face_model import FaceModel, save_face_model

    g = 12
    u, v = np.meshgrid(np.linspace(0.05, 0.95, g), np.linspace(0.05, 0.95, g))
    x, y = (u - 0.5) * 160, (0.5 - v) * 200
    z = 80 * np.sqrt(np.clip(1 - ((u - 0.5) / 0.6) ** 2 - ((v - 0.5) / 0.6) ** 2, 0.05, 1))
    verts = np.stack([x, y, z], -1).reshape(-1, 3)
    tri = []
    for r in range(g - 1):
        for c in range(g - 1):
            i = r * g + c
            tri += [(i, i + g, i + 1), (i + 1, i + g, i + g + 1)]
    tri = np.array(tri)
    # orient outward (+z)
    n = np.cross(verts[tri[:, 1]] - verts[tri[:, 0]], verts[tri[:, 2]] - verts[tri[:, 0]])
    tri[n[:, 2] < 0] = tri[n[:, 2] < 0][:, ::-1]
    N = verts.shape[0]
    fm = FaceModel(mean_shape=verts, shape_basis=np.zeros((0, N, 3)), shape_sigma=np.zeros(0),
                   exp_basis=np.zeros((0, N, 3)), exp_sigma=np.zeros(0), triangles=tri,
                   uv=np.stack([u, v], -1).reshape(-1, 2), landmarks=np.arange(68) % N, skin_mask=np.ones(N, bool))
    save_face_model(fm, path)
    return fm


def test_build_pca_cli_end_to_end(tmp_path, cli):
    truth, mask = _write_maps(tmp_path)
    fm = _face_model(tmp_path / "face_model.npz")
    r = cli("-q", "build-pca", "--ids", "000-004", "--workspace", tmp_path, "--components", "10")
    assert r.exit_code == 0, r.output + (r.stderr or "")
    outs = r.stdout.split()
    assert outs[0].endswith("build-pca/build-pca.npz") and len(outs) == 3
    art = read_artifact(outs[0], "reflectance-model")
    m = model_from_arrays(art.arrays)
    assert m.n_components == 4 and art.meta["params"]["components"] == 10
    assert art["vertex_albedo_basis"].shape == (4, fm.uv.shape[0], 3)
    assert {i["role"] for i in art.meta["inputs"]} == {"maps", "face_model"}
    assert all(len(i["sha256"]) == 64 for i in art.meta["inputs"])
    for j, (a, w) in enumerate(truth):
        alb, wts = sample_model(m, m.train_coeffs[j])
        np.testing.assert_allclose(alb, a, atol=1e-5)
        np.testing.assert_allclose(wts, w, atol=1e-5)
    comp = read_image(outs[1])
    assert comp.shape == (3 * 20, 6 * 20, 3)
    samples = read_image(outs[2])
    assert samples.shape[0] == 5 * 130 and samples.shape[1] == 6 * 130
    # rerun is byte-identical (deterministic artifacts)
    before = (tmp_path / "build-pca" / "build-pca.npz").read_bytes()
    r = cli("-q", "build-pca", "--ids", "000-004", "--workspace", tmp_path, "--components", "10")
    assert (tmp_path / "build-pca" / "build-pca.npz").read_bytes() == before


def test_build_pca_cli_errors(tmp_path, cli):
    _write_maps(tmp_path, n=3)
    r = cli("build-pca", "--ids", "000-003", "--workspace", tmp_path)
    assert r.exit_code == 1 and "003.npz" in r.stderr and "not found" in r.stderr
    r = cli("build-pca", "--ids", "000", "--workspace", tmp_path)
    assert r.exit_code == 1 and "at least 2" in r.stderr
    # mismatching exponents are refused with the file named
    p = tmp_path / "fit-reflectance" / "002.npz"
    art = read_artifact(p)
    arr = dict(art.arrays)
    arr["exponents"] = np.array([1.0, 16.0, 64.0])
    write_artifact(p, "reflectance-maps", arr)
    r = cli("build-pca", "--ids", "000-002", "--workspace", tmp_path)
    assert r.exit_code == 1 and "002.npz" in r.stderr and "exponents" in r.stderr
    # a wrong kind is refused
    r = cli("build-pca", "-i", tmp_path / "fit-reflectance" / "000.npz", "-i", tmp_path / "face_model.npz",
            "--workspace", tmp_path)
    assert r.exit_code == 1


def test_cap_message_is_logged(tmp_path, cli):
    import logging

    _write_maps(tmp_path, n=3)
    seen = []
    h = logging.Handler()
    h.emit = lambda rec: seen.append(rec.getMessage())
    logging.getLogger("reflectmm").addHandler(h)
    try:
        r = cli("build-pca", "--ids", "000-002", "--workspace", tmp_path, "--no-preview")
    finally:
        logging.getLogger("reflectmm").removeHandler(h)
    assert r.exit_code == 0
    assert any("N - 1 = 2" in s for s in seen)


def test_build_pca_refuses_maps_twice_unfitted_or_negative(tmp_path, cli):
    # the same maps twice counted twice; maps whose every texel was flagged (nothing fitted, all zero) or with
    # negative albedo made a model, with exit 0
    _write_maps(tmp_path, n=3)
    d = tmp_path / "fit-reflectance"
    out = tmp_path / "build-pca" / "build-pca.npz"

    def refused(files, msg):
        r = cli("build-pca", *[a for f in files for a in ("-i", f)], "--workspace", tmp_path)
        assert r.exit_code == 1 and msg in r.stderr and str(files[-1]) in r.stderr and not out.exists(), r.stderr

    refused([d / "000.npz", d / "001.npz", d / "000.npz"], "given twice")
    art = read_artifact(d / "002.npz")
    arr = dict(art.arrays)
    write_artifact(tmp_path / "unfitted.npz", "reflectance-maps",
                   {**arr, "albedo": np.zeros_like(arr["albedo"]), "flagged": np.ones_like(arr["flagged"])})
    refused([d / "000.npz", d / "001.npz", tmp_path / "unfitted.npz"], "face texels is flagged: nothing was fitted")
    write_artifact(tmp_path / "negative.npz", "reflectance-maps", {**arr, "albedo": -arr["albedo"]})
    refused([d / "000.npz", d / "001.npz", tmp_path / "negative.npz"], "albedo below 0")
    write_artifact(tmp_path / "reordered.npz", "reflectance-maps", {**arr, "exponents": np.array([64.0, 8.0, 1.0]),
                                                                    "weights": arr["weights"][::-1]})
    refused([d / "000.npz", d / "001.npz", tmp_path / "reordered.npz"], "in another order")
    r = cli("build-pca", "-i", d / "000.npz", "-i", d / "001.npz", "-i", d / "002.npz", "--workspace", tmp_path)
    assert r.exit_code == 0, r.stderr
