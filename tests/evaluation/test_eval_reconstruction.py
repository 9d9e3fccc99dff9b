"""Table 2 pure functions: encodings, seen vertices, per-image scale, reflectance errors, rows, figures."""
import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from reflectmm_cli.errors import ReflectmmError
from reflectmm_cli.evaluation.face_metrics import PSNR_CAP
from reflectmm_cli.evaluation.figures import PANELS, error_colormap, grid, method_panels, write_figure
from reflectmm_cli.evaluation.reconstruction_eval import (decode_image, encode_like, image_metrics_table,
                                                          markdown_table, per_image_scale, seen_vertices,
                                                          spec_albedo_of, table_row, vertex_reflectance_errors)


@pytest.mark.parametrize("enc", ["gamma1.2", "srgb", "linear"])
def test_encode_inverts_decode(enc):
    codes = np.arange(256, dtype=np.uint8)
    assert np.allclose(encode_like(decode_image(codes, enc), enc), codes / 255.0, atol=1e-9)
    with pytest.raises(ReflectmmError, match="unknown image encoding"):
        encode_like(codes, "gamma2.2")


def test_seen_vertices_from_a_packed_gbuffer():
    off = np.array([0, 2, 3])
    vid = np.array([[0, 1, 2], [2, 3, 4], [5, 6, 0]], np.int32)
    s = seen_vertices(off, vid, 8)
    assert s.tolist() == [[1, 1, 1, 1, 1, 0, 0, 0], [1, 0, 0, 0, 0, 1, 1, 0]]
    s2 = seen_vertices(off, vid, 8, rows=np.array([False, True, True]))
    assert s2[0].tolist() == [0, 0, 1, 1, 1, 0, 0, 0]


@given(st.integers(0, 1000))
def test_per_image_scale_is_the_least_squares_scale(seed):
    rng = np.random.default_rng(seed)
    p = rng.uniform(0.1, 1, (3, 20, 3))
    t = p * rng.uniform(0.5, 2, (3, 1, 1)) + rng.normal(0, 0.05, p.shape)
    r = rng.uniform(size=(3, 20)) < 0.7
    r[:, 0] = True
    s = per_image_scale(p, t, r)
    for i in range(3):
        a, b = p[i][r[i]].reshape(-1, 1), t[i][r[i]].reshape(-1)
        assert s[i] == pytest.approx(np.linalg.lstsq(a, b, rcond=None)[0][0], rel=1e-10)


def test_reflectance_errors_raw_and_scaled():
    """The albedo/lighting ambiguity: a prediction 1.3× too bright everywhere has zero scaled error."""
    rng = np.random.default_rng(0)
    ta = rng.uniform(0.2, 0.7, (4, 50, 3))
    ts = rng.uniform(0.02, 0.08, (4, 50))
    reg = rng.uniform(size=(4, 50)) < 0.8
    res = vertex_reflectance_errors(1.3 * ta, 1.3 * ts, ta, spec_albedo_of(ts[..., None]), reg)
    assert np.allclose(res["scale"], 1 / 1.3)
    assert np.allclose(res["per_image"]["raw"]["albedo_rel"], 0.3)
    assert np.allclose(res["per_image"]["raw"]["spec_rel"], 0.3)
    assert np.allclose(res["per_image"]["scaled"]["albedo_rel"], 0, atol=1e-12)
    i = 2
    d = (1.3 * ta[i] - ta[i])[reg[i]]
    assert res["per_image"]["raw"]["albedo_psnr"][i] == pytest.approx(10 * np.log10(1 / np.mean(d ** 2)))
    assert res["summary"]["raw"]["albedo_rel"]["mean"] == pytest.approx(0.3)
    # a pattern error survives the scale
    bad = ta.copy()
    bad[:, :25] *= 0.5
    res2 = vertex_reflectance_errors(bad, None, ta, None, reg)
    assert np.all(res2["per_image"]["scaled"]["albedo_rel"] > 0.05) and "spec_rel" not in res2["per_image"]["raw"]
    reg[1] = False
    with pytest.raises(ReflectmmError, match="#1 has no evaluated vertex"):
        vertex_reflectance_errors(ta, None, ta, None, reg)


def test_image_metrics_table_on_shard_like_arrays():
    rng = np.random.default_rng(1)
    imgs = rng.integers(0, 256, (3, 32, 32, 3), dtype=np.uint8)
    masks = np.zeros((3, 32, 32), bool)
    masks[:, 6:26, 8:24] = True
    exact = decode_image(imgs, "gamma1.2")
    t = image_metrics_table(exact, imgs, masks, "gamma1.2")
    assert np.all(t["per_image"].per_image["psnr"] == PSNR_CAP)
    # a wrong light intensity (the user's lighting estimate is off by 20 %) lowers every image's PSNR
    t2 = image_metrics_table(exact * 1.2, imgs, masks, "gamma1.2")
    assert np.all(t2["per_image"].per_image["psnr"] < 40)
    assert t2["released"]["psnr"] > t2["per_image"].summary["psnr"]["mean"]  # zero background inflates it
    row = table_row("ours", t2, vertex_reflectance_errors(np.ones((3, 5, 3)), np.ones((3, 5)), np.ones((3, 5, 3)),
                                                           np.ones((3, 5)), np.ones((3, 5), bool)))
    assert row["LPIPS"] == "off" and "albedo rel (scaled)" in row and "±" in row["PSNR"]
    md = markdown_table([row, {"method": "w/o finetune"}])
    assert md.count("\n") == 3 and md.startswith("| method |")
    assert md.splitlines()[1] == "|" + "---|" * len(row)
    right = markdown_table([{"a": "x", "b": "1"}], align="lr")
    assert right == "| a | b |\n|---|---:|\n| x | 1 |"
    with pytest.raises(ValueError, match="align"):
        markdown_table([{"a": "x", "b": "1"}], align="l")


def test_figure_panels_and_error_ramp(tmp_path):
    assert np.allclose(error_colormap(np.array([0.0, 0.2, 1.0]), 0.2), [[0, 0, 0], [1, 1, 1], [1, 1, 1]])
    assert np.allclose(error_colormap(np.array([0.2 / 3]), 0.2), [[1, 0, 0]])
    rng = np.random.default_rng(2)
    inp = rng.uniform(size=(16, 20, 3))
    m = np.zeros((16, 20), bool)
    m[4:12, 5:15] = True
    panels = method_panels(inp, inp, inp * 0.8, None, m)
    assert len(panels) == len(PANELS)
    assert np.all(panels[4] == 0)  # perfect reconstruction → black error map
    assert np.all(panels[3][m] == 0)  # absent specular layer
    g = grid([panels, panels[:2]])
    assert g.shape == (2 * 18 + 2, 5 * 22 + 2, 3)
    p = write_figure(tmp_path / "fig.png", [panels])
    assert p.stat().st_size > 100
    with pytest.raises(ReflectmmError, match="panel"):
        method_panels(inp, inp[:8], None, None, m)


def test_paper_vs_ours_rows():
    from reflectmm_cli.evaluation.paper_numbers import PAPER_NUMBERS, paper_vs_ours_rows

    rows = paper_vs_ours_rows({"table3.diffuse_psnr": 24.5, "table2.psnr_gain_finetune": 0.4},
                              {"table3.diffuse_psnr": "reflectmm evaluate albedo"})
    assert len(rows) == len(PAPER_NUMBERS)
    byq = {r["quantity"]: r for r in rows}
    assert byq["diffuse albedo PSNR (ours)"]["paper"] == "20.13 dB"
    assert byq["diffuse albedo PSNR (ours)"]["reflectmm"] == "24.50 dB"
    assert byq["PSNR gain of ours over ours w/o finetuning"]["reflectmm"] == "+0.40 dB"
    assert byq["specular albedo PSNR (ours; Σw as specular albedo)"]["reflectmm"] == "not run"
    rows = paper_vs_ours_rows({"table2.psnr_gain_finetune": -0.14}, {}, {"table2.psnr_gain_finetune": 0.381})
    assert {r["quantity"]: r for r in rows}["PSNR gain of ours over ours w/o finetuning"]["reflectmm"] == \
        "-0.14 ± 0.38 dB"


def test_evaluate_reconstruction_on_a_tiny_shard():
    from reflectmm_cli.evaluation.reconstruction_eval import evaluate_reconstruction

    rng = np.random.default_rng(4)
    N, Sz, V = 3, 24, 10
    img = rng.integers(0, 256, (N, Sz, Sz, 3), dtype=np.uint8)
    face = np.zeros((N, Sz, Sz), bool)
    face[:, 4:20, 5:19] = True
    off = np.array([0, 2, 4, 5])
    vid = np.array([[0, 1, 2], [2, 3, 4], [5, 6, 7], [7, 8, 9], [0, 9, 5]])
    ta = rng.uniform(0.2, 0.6, (N, V, 3)).astype(np.float16)
    tw = rng.uniform(0.0, 0.03, (N, V, 3)).astype(np.float16)
    shard = {"image": img, "face_mask": face, "skin_mask": face, "pix_offset": off, "vert_ids": vid,
             "names": np.array(["a", "b", "c"]), "truth_vertex_albedo": ta, "truth_vertex_weights": tw}
    sel = np.array([2, 0])
    pred = {"render": decode_image(img[sel], "srgb"), "vertex_albedo": 2.0 * ta[sel].astype(np.float64),
            "vertex_weights": 2.0 * tw[sel].astype(np.float64)}
    out = evaluate_reconstruction(pred, shard, encoding="srgb", select=sel)
    assert out["n_images"] == 2
    assert np.all(out["image"]["per_image"].per_image["psnr"] == PSNR_CAP)
    r = out["reflectance"]
    assert np.allclose(r["scale"], 0.5) and np.allclose(r["per_image"]["scaled"]["spec_rel"], 0, atol=1e-12)
    # image 2 sees only vertices {0, 5, 9}: its raw error is computed there only
    d = (2.0 * ta[2] - ta[2]).astype(np.float64)[[0, 5, 9]]
    assert r["per_image"]["raw"]["albedo_rmse"][0] == pytest.approx(np.sqrt(np.mean(d ** 2)))
    with pytest.raises(ReflectmmError, match="2 predicted renders for 3 images"):
        evaluate_reconstruction(pred, shard, encoding="srgb")


def test_results_document_and_flat_arrays():
    import json

    from reflectmm_cli.evaluation.face_metrics import face_region_metrics
    from reflectmm_cli.evaluation.results import evaluation_arrays, flatten_numbers, to_document

    rng = np.random.default_rng(7)
    t = rng.uniform(0.2, 0.8, (2, 16, 16, 3))
    p = np.clip(t + 0.05, 0, 1)
    m = np.ones((2, 16, 16), bool)
    fm = face_region_metrics(p, t, m)
    doc = {"ours": {"image": fm, "scale": np.array([1.0, 2.0]), "ok": True, "bad": float("nan")}}
    js = json.loads(json.dumps(to_document(doc)))
    assert js["ours"]["image"]["lpips"].startswith("off") and js["ours"]["bad"] is None
    assert js["ours"]["image"]["per_image"]["psnr"] == pytest.approx(list(fm.per_image["psnr"]))
    flat = flatten_numbers(doc)
    assert flat["ours.scale[1]"] == 2.0 and "ours.ok" not in flat
    assert flat["ours.image.summary.psnr.mean"] == pytest.approx(fm.summary["psnr"]["mean"])
    arr = evaluation_arrays(doc)
    assert list(arr["names"]) == sorted(arr["names"]) and arr["values"].dtype == np.float64
