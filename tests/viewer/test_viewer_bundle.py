"""The viewer's bundle and page without a browser: encodings, constants, refusals, the command and its meta."""
from __future__ import annotations

import json
import re
import sys
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

sys.path.insert(0, str(Path(__file__).parent))
import _viewer_data as D  # noqa: E402

from reflectmm_cli.artifacts import read_artifact, read_meta, write_artifact  # noqa: E402
from reflectmm_cli.errors import ReflectmmError  # noqa: E402
from reflectmm_cli.shading.sh import (_legendre_consts, blinn_phong_norm, blinn_phong_sh_coeffs,  # noqa: E402
                                      lambert_sh_coeffs, sh_basis)
from reflectmm_cli.viewer import (EXTERNAL_URL, LightData, ViewerOptions, build_bundle, decode_blob,  # noqa: E402
                                  model_data, render_page)
from reflectmm_cli.viewer.bundle import _blob, _quantise  # noqa: E402


@pytest.fixture(scope="module")
def small(tmp_path_factory):
    t = tmp_path_factory.mktemp("vb")
    fm = D.face_model(t / "fm.npz", n_vertices=1200)
    m = D.reflectance_model(t / "m.npz", fm, 3)
    D.envmap(t / "env.exr", width=64)
    return {"dir": t, "fm": fm, "fm_path": t / "fm.npz", "model": m, "env": t / "env.exr"}


@settings(max_examples=40, deadline=None)
@given(st.integers(1, 4), st.integers(1, 50), st.integers(1, 5), st.floats(1e-3, 1e3), st.integers(0, 2 ** 31))
def test_encodings_round_trip_within_their_bound(m, n, c, scale, seed):
    b = np.random.default_rng(seed).normal(size=(m, n, c)) * scale
    f2 = decode_blob(json.loads(json.dumps(_blob(b, "f2").to_json())))
    assert np.all(np.abs(f2 - b) <= np.abs(b) * 2.0 ** -11 + 6e-8)
    u8 = decode_blob(json.loads(json.dumps(_quantise(b).to_json())))
    top = np.abs(b).max(axis=1, keepdims=True)
    # half a quantisation step, plus the float32 decode: the scale stored in float32 (|q| ≤ 127 times its
    # rounding, ≤ top · 2⁻²⁴) and the rounding of the product (≤ top · 2⁻²⁴)
    assert np.all(np.abs(u8 - b) <= 0.5 * top / 127 + 2 * top * 2.0 ** -24 + 1e-12)


def test_bundle_carries_the_renderers_constants(small):
    art = read_artifact(small["model"], "reflectance-model")
    md = model_data(art.arrays, 10, "m", small["model"])
    fm = small["fm"]
    doc = build_bundle(fm.mean_shape, fm.triangles, np.tile([0.0, 0.0, 1.0], (fm.n_vertices, 1)), [md], LightData(),
                       ViewerOptions(sh_order=4))
    sh = doc["shading"]
    L = sh["order"]
    assert L == 0  # the uniform sky alone: order 0
    doc = build_bundle(fm.mean_shape, fm.triangles, np.tile([0.0, 0.0, 1.0], (fm.n_vertices, 1)), [md],
                       LightData(envmaps=[("x", np.ones((3, 25)))]), ViewerOptions())
    sh = doc["shading"]
    L = sh["order"]
    assert L == 4
    np.testing.assert_allclose(sh["lambert_over_pi"], lambert_sh_coeffs(4) / np.pi)
    np.testing.assert_allclose(sh["lobes"][0]["B"], blinn_phong_sh_coeffs(md.exponents, 4))
    np.testing.assert_allclose(sh["lobes"][0]["norm"], blinn_phong_norm(md.exponents))
    # the recurrence the page unrolls reproduces sh_basis (evaluated here as the page does)
    rec = sh["recurrence"]
    d = np.random.default_rng(0).normal(size=(20, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    Y = np.zeros((20, 25))
    x, y, z = d.T
    cm, sm = np.ones(20), np.zeros(20)
    for m in range(L + 1):
        if m == 1:
            cm, sm = x, y
        elif m > 1:
            cm, sm = x * cm - y * sm, x * sm + y * cm
        q1 = q2 = None
        for l in range(m, L + 1):  # noqa: E741
            if l == m:
                q = np.full(20, rec["pmm"][m])
                q1 = q
            elif l == m + 1:
                q = np.sqrt(2 * m + 3) * rec["pmm"][m] * z
                q2, q1 = q1, q
            else:
                q = rec["a"][m][l] * (z * q1 - rec["b"][m][l] * q2)
                q2, q1 = q1, q
            if m == 0:
                Y[:, l * l + l] = q
            else:
                Y[:, l * l + l + m] = np.sqrt(2) * q * cm
                Y[:, l * l + l - m] = np.sqrt(2) * q * sm
    np.testing.assert_allclose(Y, sh_basis(d, 4), atol=1e-12)
    pmm, _, _ = _legendre_consts(4)
    assert rec["pmm"] == list(pmm)


def test_view_command_writes_one_offline_page_with_meta(small, cli):
    out = small["dir"] / "page.html"
    r = cli("-q", "view", small["model"], "--face-model", small["fm_path"], "--envmap", small["env"],
            "--components", "3", "-o", out)
    assert r.exit_code == 0, r.output + (r.stderr or "")
    text = out.read_text()
    assert not EXTERNAL_URL.search(text)
    meta = read_meta(out)
    assert meta["schema"].startswith("reflectmm.viewer/") and meta["n_vertices"] == small["fm"].n_vertices
    assert {i["role"] for i in meta["inputs"]} == {"model", "face_model", "envmap"}
    doc = json.loads(re.search(r'<script type="application/json" id="reflectmm-data">(.*?)</script>', text,
                               re.S).group(1))
    assert doc["format"] == "reflectmm.viewer/1" and len(doc["models"][0]["sigma"]) == 3
    alb = decode_blob(doc["models"][0]["albedo_basis"])
    art = read_artifact(small["model"], "reflectance-model")
    np.testing.assert_allclose(alb, art["vertex_albedo_basis"][:3], rtol=2 ** -10, atol=1e-7)
    r = cli("inspect", out)
    assert r.exit_code == 0 and "kind:      viewer" in r.output and "models[0].albedo_basis" in r.output
    # a rerun gives the same bytes
    before = out.read_bytes()
    cli("-q", "view", small["model"], "--face-model", small["fm_path"], "--envmap", small["env"],
        "--components", "3", "-o", out)
    assert out.read_bytes() == before


def test_face_model_defaults_to_the_one_the_model_records(small, cli, tmp_path):
    import shutil

    shutil.copy(small["fm_path"], tmp_path / "face_model.npz")
    art = read_artifact(small["model"], "reflectance-model")
    write_artifact(tmp_path / "m.npz", "reflectance-model", art.arrays,
                   inputs=[{"role": "face_model", "path": "face_model.npz", "sha256": "0" * 64}])
    r = cli("-q", "view", tmp_path / "m.npz", "-o", tmp_path / "v.html")
    assert r.exit_code == 0, r.stderr
    assert any(i["role"] == "face_model" for i in read_meta(tmp_path / "v.html")["inputs"])
    (tmp_path / "face_model.npz").unlink()
    empty = tmp_path / "empty_ws"
    empty.mkdir()
    r = cli("view", tmp_path / "m.npz", "-w", empty, "-o", tmp_path / "w.html")
    assert r.exit_code != 0 and "give --face-model" in r.stderr and not (tmp_path / "w.html").exists()
    # the workspace's face model is the next default (workspace.find_face_model)
    import shutil as sh

    sh.copy(small["fm_path"], empty / "face_model.npz")
    r = cli("-q", "view", tmp_path / "m.npz", "-w", empty, "-o", tmp_path / "w.html")
    assert r.exit_code == 0, r.stderr


def test_model_without_per_vertex_part_is_refused(small, cli, tmp_path):
    art = read_artifact(small["model"], "reflectance-model")
    arrays = {k: v for k, v in art.arrays.items() if not k.startswith("vertex_")}
    write_artifact(tmp_path / "uv_only.npz", "reflectance-model", arrays)
    r = cli("view", tmp_path / "uv_only.npz", "--face-model", small["fm_path"], "-o", tmp_path / "v.html")
    assert r.exit_code == 1
    lines = [ln for ln in r.stderr.splitlines() if ln.strip()]
    assert len(lines) == 1 and "uv_only.npz" in lines[0] and "no per-vertex part" in lines[0]
    assert not (tmp_path / "v.html").exists()


def test_bad_inputs_are_one_line_errors(small, cli, tmp_path):
    art = read_artifact(small["model"], "reflectance-model")
    a = dict(art.arrays)
    a["exponents"] = np.arange(1.0, 10.0)
    a["vertex_weights_mean"] = np.zeros((a["vertex_albedo_mean"].shape[0], 9), np.float32)
    a["vertex_weights_basis"] = np.zeros((a["sigma"].size, a["vertex_albedo_mean"].shape[0], 9), np.float32)
    write_artifact(tmp_path / "nine.npz", "reflectance-model", a)
    r = cli("view", tmp_path / "nine.npz", "--face-model", small["fm_path"], "-o", tmp_path / "v.html")
    assert r.exit_code == 1 and "at most 8" in r.stderr
    r = cli("view", small["model"], "--face-model", small["fm_path"], "-o", tmp_path / "v.png")
    assert r.exit_code != 0 and ".html" in r.stderr
    r = cli("view", tmp_path / "missing.npz", "--face-model", small["fm_path"], "-o", tmp_path / "v.html")
    assert r.exit_code != 0 and "missing.npz" in r.stderr
    other = D.face_model(tmp_path / "other.npz", n_vertices=600)
    r = cli("view", small["model"], "--face-model", tmp_path / "other.npz", "-o", tmp_path / "v.html")
    assert r.exit_code == 1 and f"the face model {other.n_vertices}" in r.stderr
    assert not (tmp_path / "v.html").exists()
    a = dict(art.arrays)
    a["sigma"] = np.zeros_like(a["sigma"])  # coefficients in units of σ: at 0 the sliders would move nothing
    write_artifact(tmp_path / "zero_sigma.npz", "reflectance-model", a)
    r = cli("view", tmp_path / "zero_sigma.npz", "--face-model", small["fm_path"], "-o", tmp_path / "v.html")
    assert r.exit_code == 1 and "zero_sigma.npz" in r.stderr and "sigma must be > 0" in r.stderr
    assert not (tmp_path / "v.html").exists()
    with pytest.raises(ReflectmmError):
        ViewerOptions(encoding="f8")


def test_title_cannot_close_the_script(small):
    art = read_artifact(small["model"], "reflectance-model")
    md = model_data(art.arrays, 2, "</script><script>alert(1)</script>", small["model"])
    fm = small["fm"]
    doc = build_bundle(fm.mean_shape, fm.triangles, np.tile([0.0, 0.0, 1.0], (fm.n_vertices, 1)), [md],
                       LightData(), title="</script>")
    html = render_page(doc, {"schema": "reflectmm.viewer/1"})
    assert html.count("</script>") == 3  # meta, data, code: nothing from the bundle closes an element
