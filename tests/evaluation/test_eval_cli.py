"""evaluate truth / representation / report end to end through the CLI on small synthetic artifacts."""
import json

import numpy as np
import pytest
import torch

from reflectmm_cli.artifacts import read_artifact, read_image, write_artifact
from reflectmm_cli.evaluation import LPIPS
from reflectmm_cli.evaluation.synthetic import simulate_ggx_observations


@pytest.fixture(scope="module")
def ggx_ws(tmp_path_factory):
    """Workspace with 2 identities' GGX-rendered uv-observations (S=32), truth and fitted maps."""
    from reflectmm_cli.reflectance.fit import fit_maps

    ws = tmp_path_factory.mktemp("ws")
    for i in range(2):
        obs, truth = simulate_ggx_observations(size=32, seed=i)
        ident = f"{i:03d}"
        write_artifact(ws / "unwrap-uv" / f"{ident}.npz", "uv-observations", obs, extra_meta={"identity": ident})
        write_artifact(ws / "truth" / f"{ident}.npz", "synth-truth",
                       {k: np.asarray(v, np.float32) for k, v in truth.items()})
        m = fit_maps(obs)
        write_artifact(ws / "fit-reflectance" / f"{ident}.npz", "reflectance-maps",
                       {"albedo": m.albedo, "weights": m.weights, "exponents": m.exponents, "mask": m.mask,
                        "flagged": m.flagged}, extra_meta={"identity": ident})
    return ws


def test_evaluate_representation_cli(ggx_ws, cli, tmp_path):
    sd = LPIPS("alex").random_state_dict(seed=0)
    wf = tmp_path / "lpips.pth"
    torch.save(sd, wf)
    r = cli("-q", "evaluate", "representation", "--ids", "000,001", "--workspace", ggx_ws,
            "--exponents-sets", "8;64;1,8,64", "--lpips-weights", wf)
    assert r.exit_code == 0, r.stderr
    assert "| 3-lobe (1,8,64) |" in r.stdout and "LPIPS: off" not in r.stdout
    out = ggx_ws / "evaluate-representation" / "evaluate-representation.npz"
    art = read_artifact(out, "evaluation")
    assert art["psnr"].shape == (2, 5) and art["lpips"].shape == (2, 5)
    assert np.all(np.isfinite(art["lpips"])) and np.all(art["lpips"] >= 0)
    assert art.meta["lpips"] == "on"
    assert read_image(out.with_suffix(".png")).shape[1] == 6 * (96 + 4)
    # GGX truth: the 3-lobe representation must beat both global exponents here (reported, not forced)
    names = list(art["representations"])
    mp = art["psnr"].mean(0)
    i3 = names.index("3-lobe (1,8,64)")
    assert mp[i3] > mp[names.index("global p=8")] and mp[i3] > mp[names.index("global p=64")]
    # without weights: no LPIPS array and a clear statement
    r = cli("-q", "evaluate", "representation", "--ids", "000,001", "--max-identities", "1", "--workspace", ggx_ws,
            "--exponents-sets", "16", "--no-baselines", "-o", tmp_path / "rep.npz")
    assert r.exit_code == 0, r.stderr
    assert "LPIPS: off (no weights given)" in r.stdout
    art = read_artifact(tmp_path / "rep.npz")
    assert "lpips" not in art.arrays and art["psnr"].shape == (1, 1) and list(art["ids"]) == ["000"]
    # bad holdout names the flash ids
    r = cli("evaluate", "representation", "--ids", "000", "--workspace", ggx_ws, "--holdout", "02",
            "-o", tmp_path / "x.npz")
    assert r.exit_code == 1 and "02" in r.stderr and "03" in r.stderr


def test_evaluate_representation_counts_an_identity_once(ggx_ws, cli, tmp_path):
    f = ggx_ws / "unwrap-uv" / "000.npz"
    r = cli("evaluate", "representation", "-i", f, "-i", f, "--workspace", ggx_ws, "-o", tmp_path / "x.npz")
    assert r.exit_code == 1 and "identity 000 is given twice" in r.stderr and not (tmp_path / "x.npz").exists()


def test_evaluate_representation_holdout_names_each_flash_once(ggx_ws, cli, tmp_path):
    # "05,05" was taken as "held-out flashes 05, 05"; "" said "holdout: empty list", not the option
    for value, msg in (("05,05", "--holdout: 05 named more than once"), ("", "--holdout: empty list")):
        r = cli("evaluate", "representation", "--ids", "000", "--workspace", ggx_ws, "--holdout", value,
                "-o", tmp_path / "x.npz")
        assert r.exit_code == 1 and r.stderr.strip() == f"reflectmm: error: {msg}", r.stderr
        assert not (tmp_path / "x.npz").exists()
    r = cli("evaluate", "representation", "--help")
    assert "0 or 'diffuse' = diffuse only" in " ".join(r.stdout.split())


def test_evaluate_truth_cli(ggx_ws, cli):
    r = cli("-q", "evaluate", "truth", "--id", "001", "--workspace", ggx_ws)
    assert r.exit_code == 0, r.stderr
    doc = json.loads(r.stdout)
    e = doc["errors"]["reflectance"]
    assert e["raw"]["observable"]["albedo_rel"] < 0.1
    assert {"observable", "flagged", "all"} <= set(e["raw"])
    art = read_artifact(doc["outputs"][0], "evaluation")
    names = list(art["names"])
    v = art["values"][names.index("reflectance.raw.observable.albedo_rmse")]
    assert v == pytest.approx(e["raw"]["observable"]["albedo_rmse"])
    r = cli("evaluate", "truth", "--id", "007", "--workspace", ggx_ws)
    assert r.exit_code == 1 and "007.npz" in r.stderr


def test_evaluate_truth_refuses_what_gave_wrong_or_nan_tables(ggx_ws, cli, tmp_path):
    """Another identity's maps or truth were scored (albedo error 0.23 instead of 0.05); a NaN truth gave NaN
    errors over a good output; maps with fewer weight channels than exponents passed; a truncated truth or maps
    without weights were internal errors."""
    maps1 = read_artifact(ggx_ws / "fit-reflectance" / "001.npz", "reflectance-maps")
    truth1 = read_artifact(ggx_ws / "truth" / "001.npz", "synth-truth")
    out = tmp_path / "t.npz"
    base = ("evaluate", "truth", "--id", "001", "--workspace", ggx_ws, "-o", out)
    cases = []
    write_artifact(tmp_path / "t002.npz", "synth-truth", dict(truth1.arrays), extra_meta={"identity": "000"})
    cases.append((("--truth", tmp_path / "t002.npz"),
                  "is identity 000's synth-truth, but this task is for identity 001"))
    cases.append((("--maps", ggx_ws / "fit-reflectance" / "000.npz"), "is identity 000's reflectance-maps"))
    nan = {k: np.array(v) for k, v in truth1.arrays.items()}
    nan["albedo"][0, 3, 3] = np.nan
    write_artifact(tmp_path / "tnan.npz", "synth-truth", nan)
    cases.append((("--truth", tmp_path / "tnan.npz"), "synth-truth array 'albedo' has 1 NaN or inf values"))
    two = {**maps1.arrays, "weights": maps1["weights"][:2]}
    write_artifact(tmp_path / "m2.npz", "reflectance-maps", two, extra_meta={"identity": "001"})
    cases.append((("--maps", tmp_path / "m2.npz"), "has 2 lobe-weight channels but 3 exponents"))
    now = {k: v for k, v in maps1.arrays.items() if k != "weights"}
    write_artifact(tmp_path / "mnow.npz", "reflectance-maps", now, extra_meta={"identity": "001"})
    cases.append((("--maps", tmp_path / "mnow.npz"), "reflectance-maps artifact has no array 'weights'"))
    (tmp_path / "trunc.npz").write_bytes((ggx_ws / "truth" / "001.npz").read_bytes()[:5000])
    cases.append((("--truth", tmp_path / "trunc.npz"), "truncated or corrupt NPZ"))
    half = {k: (np.asarray(v)[..., ::2, ::2] if np.ndim(v) >= 2 else v) for k, v in truth1.arrays.items()}
    write_artifact(tmp_path / "t16.npz", "synth-truth", half)  # another UV size: the message named no file
    cases.append((("--truth", tmp_path / "t16.npz"), f"{tmp_path / 't16.npz'}: evaluate truth: albedo has shape "
                  f"(3, 16, 16), the maps {ggx_ws / 'fit-reflectance' / '001.npz'} (3, 32, 32): the UV sizes "
                  "must agree"))
    for extra, msg in cases:
        r = cli(*base, *extra)
        assert r.exit_code == 1 and msg in r.stderr and "internal error" not in r.stderr, (extra, r.stderr)
        assert not out.exists()


def test_evaluate_report_cli(ggx_ws, cli):
    r = cli("-q", "build-pca", "--ids", "000,001", "--workspace", ggx_ws, "--no-preview")
    assert r.exit_code == 0, r.stderr
    cli("-q", "evaluate", "representation", "--ids", "000,001", "--workspace", ggx_ws, "--exponents-sets", "1,8,64")
    out = ggx_ws / "report.md"
    r = cli("-q", "evaluate", "report", "--workspace", ggx_ws, "--out", out)
    assert r.exit_code == 0, r.stderr
    text = out.read_text()
    assert "## Reflectance maps" in text and "| 000 |" in text and "| **mean** |" in text
    # the views and flashes each reflectance fit took, as its observations hold them
    for obs in sorted((ggx_ws / "unwrap-uv").glob("*.npz")):
        o = read_artifact(obs, "uv-observations")
        views, flashes = [str(v) for v in o["view_names"]], [str(f) for f in o["flash_ids"]]
        assert (f"- {obs.stem}: {len(views)} views ({', '.join(views)}); {len(flashes)} flashes "
                f"({', '.join(flashes)})") in text
    assert "The views and flashes each fit took" in text
    assert "## PCA reflectance model" in text and "Reconstruction of the held-in maps" in text
    assert "## Representation comparison" in text
    art = read_artifact(out.with_suffix(".npz"), "evaluation")
    names = list(art["names"])
    # 2 identities, 1 component: reconstruction with all components is exact for the held-in maps
    k = names.index("pca.build-pca.reconstruction.all.albedo_rmse")
    assert art["values"][k] < 1e-5
    r = cli("evaluate", "report", "--workspace", ggx_ws / "nothing")
    assert r.exit_code == 1 and "nothing to report" in r.stderr


def test_representation_skips_identities_without_the_held_out_flashes(monkeypatch, tmp_path):
    """Observations that kept only the flashes landmarks placed may lack a held-out flash: such an identity is
    skipped (with a warning), the next one taken up to max_identities, and none left is a one-line error."""
    from types import SimpleNamespace

    import reflectmm_cli.stages.evaluate_representation as er
    from reflectmm_cli.errors import ReflectmmError

    flashes = {"001": ["06", "07", "08"], "002": ["05", "06", "09"], "003": ["05", "09"], "004": ["05", "07", "09"]}
    monkeypatch.setattr(er, "read_artifact", lambda f, kind: SimpleNamespace(
        meta={"identity": f.stem}, arrays={"flash_ids": np.array(flashes[f.stem])}))
    files = [tmp_path / f"{i}.npz" for i in flashes]
    obs, ids, skipped = er._identities_with_holdout(files, ["05", "09"], 1)
    assert ids == ["002"] and skipped == ["001"]
    obs, ids, skipped = er._identities_with_holdout(files, ["05", "09"], 0)
    assert ids == ["002", "004"] and skipped == ["001", "003"]   # 003 has nothing left to fit
    with pytest.raises(ReflectmmError, match="held-out flashes 05, 09.*skipped: 001, 003"):
        er._identities_with_holdout([files[0], files[2]], ["05", "09"], 2)
