"""reflectmm fit-reflectance end to end on a simulated uv-observations artifact."""
import numpy as np

from reflectmm_cli.artifacts import read_artifact, read_exr, write_artifact
from reflectmm_cli.reflectance import simulate_observations


def _write_obs(ws, S=16, **kw):
    obs, truth = simulate_observations(S, return_truth=True, **kw)
    path = write_artifact(ws / "unwrap-uv" / "042.npz", "uv-observations", obs)
    return obs, truth, path


def test_cli_end_to_end(cli, tmp_path):
    ws = tmp_path / "ws"
    obs, truth, _ = _write_obs(ws)
    r = cli("fit-reflectance", "--id", "042", "--workspace", ws, "--prior", "1e-6")
    assert r.exit_code == 0, r.output
    outs = r.stdout.split()
    npz = ws / "fit-reflectance" / "042.npz"
    assert str(npz) in outs
    for name in ("042.exr", "042_albedo.png", "042_weights.png", "042_residual.png", "042_flagged.png"):
        assert (ws / "fit-reflectance" / name).is_file()
    art = read_artifact(npz, "reflectance-maps")
    for k, shape in {"albedo": (3, 16, 16), "weights": (3, 16, 16), "exponents": (3,), "mask": (16, 16),
                     "residual": (16, 16), "conditioning": (16, 16), "flagged": (16, 16),
                     "obs_count": (16, 16)}.items():
        assert art[k].shape == shape, k
    ok = art["mask"] & ~art["flagged"] & np.all(art["observability"] >= 0.1, axis=0)
    rel = np.abs(art["albedo"] - truth["albedo"]) / truth["albedo"]
    assert rel[:, ok].max() < 0.01
    assert art.params["solver"] == "fast" and art.params["exponents"] == [1.0, 8.0, 64.0]
    assert art.meta["inputs"][0]["role"] == "observations"
    assert art.meta["inputs"][0]["schema"] == "reflectmm.uv-observations/1"
    ch, meta = read_exr(ws / "fit-reflectance" / "042.exr")
    assert set(ch) == {"albedo.R", "albedo.G", "albedo.B", "weight.p1", "weight.p8", "weight.p64"}
    np.testing.assert_allclose(ch["weight.p64"], art["weights"][2], rtol=1e-6)
    assert meta["schema"] == "reflectmm.reflectance-maps/1"
    # rerun: byte-identical artifact
    before = npz.read_bytes()
    r2 = cli("fit-reflectance", "--id", "042", "--workspace", ws, "--prior", "1e-6")
    assert r2.exit_code == 0
    assert npz.read_bytes() == before


def test_cli_options_and_explicit_paths(cli, tmp_path):
    ws = tmp_path / "ws"
    _, _, src = _write_obs(ws, S=8)
    out = tmp_path / "o" / "m.npz"
    r = cli("fit-reflectance", "--input", src, "--output", out, "--exponents", "16", "--loss", "l2",
            "--symmetry", "0.5", "--flash-intensity", "4225000", "--json")
    assert r.exit_code == 0, r.output
    art = read_artifact(out, "reflectance-maps")
    assert art["weights"].shape == (1, 8, 8)
    assert art.params["flash_intensity"] == [4225000.0] and art.params["symmetry"] == 0.5
    ch, _ = read_exr(out.with_suffix(".exr"))
    assert "weight.p16" in ch
    r = cli("fit-reflectance", "--input", src, "--output", tmp_path / "a.npz", "--solver", "adam", "--steps", "20")
    assert r.exit_code == 0, r.output
    assert read_artifact(tmp_path / "a.npz").meta["stats"]["steps"] == 20


def test_cli_symmetry_mode(cli, tmp_path):
    """--symmetry-mode lands in params and stats; 'all' gives mirror-symmetric maps, the default does not have to."""
    ws = tmp_path / "ws"
    _, _, src = _write_obs(ws, S=8)
    r = cli("fit-reflectance", "--input", src, "--output", tmp_path / "d.npz")
    assert r.exit_code == 0, r.output
    d = read_artifact(tmp_path / "d.npz", "reflectance-maps")
    assert d.params["symmetry_mode"] == "adaptive" and d.meta["stats"]["symmetry_mode"] == "adaptive"
    assert d.meta["producer"]["stage_version"] == 4
    assert d.params["prior_tail"] == 100.0 and d.meta["stats"]["prior_tail"] == 100.0
    r = cli("fit-reflectance", "--input", src, "--output", tmp_path / "a.npz", "--symmetry-mode", "all")
    assert r.exit_code == 0, r.output
    a = read_artifact(tmp_path / "a.npz", "reflectance-maps")
    assert a.params["symmetry_mode"] == "all" and a.meta["stats"]["n_pooled"] == int(a["mask"].sum())
    np.testing.assert_allclose(a["albedo"], a["albedo"][:, :, ::-1], rtol=1e-5, atol=1e-7)
    r = cli("fit-reflectance", "--input", src, "--output", tmp_path / "x.npz", "--symmetry-mode", "some")
    assert r.exit_code != 0


def test_cli_errors(cli, tmp_path):
    ws = tmp_path / "ws"
    r = cli("fit-reflectance", "--id", "042", "--workspace", ws)
    assert r.exit_code == 1 and "unwrap-uv/042.npz" in r.stderr and "not found" in r.stderr
    obs, _, src = _write_obs(ws, S=6)
    j, y, x = np.argwhere(obs["observed"])[0]
    obs["radiance"][j, y, x, 0] = np.nan
    bad = write_artifact(tmp_path / "bad.npz", "uv-observations", obs)
    r = cli("fit-reflectance", "--input", bad, "--output", tmp_path / "x.npz")
    assert r.exit_code == 1 and "bad.npz" in r.stderr and "NaN" in r.stderr
    assert not (tmp_path / "x.npz").exists()
    wrong = write_artifact(tmp_path / "wrong.npz", "geometry", {"a": np.zeros(2)})
    r = cli("fit-reflectance", "--input", wrong, "--output", tmp_path / "y.npz")
    assert r.exit_code == 1 and "uv-observations" in r.stderr
    r = cli("fit-reflectance", "--input", src, "--exponents", "1,x", "--output", tmp_path / "z.npz")
    assert r.exit_code == 1 and "--exponents" in r.stderr
    r = cli("fit-reflectance", "--input", src, "--flash-intensity", "1,2", "--output", tmp_path / "z.npz")
    assert r.exit_code == 1 and "--flash-intensity has 2 values" in r.stderr


def test_collinear_exponents_are_refused(cli, tmp_path):
    # duplicates and near-duplicates are one lobe twice: refused, one line, nothing written
    _, _, src = _write_obs(tmp_path / "ws", S=6)
    for exps in (["1", "1", "8"], ["1", "1.0000001", "8"], ["8", "64", "64.3"]):
        out = tmp_path / "d.npz"
        r = cli("fit-reflectance", "--input", src, "--exponents", ",".join(exps), "--output", out)
        assert r.exit_code == 1 and "collinear" in r.stderr and len(r.stderr.strip().splitlines()) == 1, r.stderr
        assert not out.exists()
    r = cli("fit-reflectance", "--input", src, "--exponents", "1,1.2,8", "--output", tmp_path / "ok.npz")
    assert r.exit_code == 0, r.stderr  # distinct enough


def test_collinear_exponents_refused_in_a_recipe(cli, tmp_path):
    ws = tmp_path / "ws"
    _write_obs(ws)
    (ws / "r.toml").write_text('schema = "reflectmm.recipe/1"\n[stages.fit-reflectance]\nforeach = ["042"]\n'
                               'inputs = { observations = "unwrap-uv/{id}.npz" }\n'
                               'params = { exponents = [1, 1.0000001, 8] }\n')
    r = cli("run", ws / "r.toml", "-w", ws)
    assert r.exit_code == 1 and "collinear" in r.stderr
    assert not (ws / "fit-reflectance" / "042.npz").exists()


def test_refine_normals_on_the_cli_and_in_a_recipe_with_one_cache_key(cli, tmp_path):
    """--refine-normals / --normal-sigma reach fit_maps, write the refined normals and their preview, enter the
    cache key, and a recipe spelling the same values plans a skip."""
    from reflectmm_cli.recipes import plan_recipe

    ws = tmp_path / "ws"
    _write_obs(ws, S=8)
    r = cli("fit-reflectance", "--id", "042", "-w", ws, "--refine-normals", "2", "--normal-sigma", "4")
    assert r.exit_code == 0, r.output
    out = ws / "fit-reflectance" / "042.npz"
    art = read_artifact(out, "reflectance-maps")
    assert art.params["refine_normals"] == 2 and art.params["normal_sigma"] == 4.0
    assert art["normal"].shape == (3, 8, 8) and art["normal_correction"].shape == (8, 8)
    assert art.meta["stats"]["normal_refinement"]["iterations"] == 2
    assert (ws / "fit-reflectance" / "042_normal_correction.png").is_file()
    key = art.meta["cache_key"]
    (ws / "r.toml").write_text('schema = "reflectmm.recipe/1"\n[stages.fit-reflectance]\nforeach = ["042"]\n'
                               'inputs = { observations = "unwrap-uv/{id}.npz" }\n'
                               'params = { refine_normals = 2.0, normal_sigma = 4 }\n')
    plan = plan_recipe(ws / "r.toml", ws)
    assert plan.tasks["fit-reflectance/042"].cache_key == key
    assert plan.tasks["fit-reflectance/042"].action == "skip"
    (ws / "r.toml").write_text((ws / "r.toml").read_text().replace("normal_sigma = 4", "normal_sigma = 3"))
    assert plan_recipe(ws / "r.toml", ws).tasks["fit-reflectance/042"].cache_key != key
    for bad in (["--refine-normals", "-1"], ["--normal-sigma", "0"], ["--refine-normals", "1.5"]):
        r = cli("fit-reflectance", "--id", "042", "-w", ws, "--output", tmp_path / "x.npz", *bad)
        assert r.exit_code != 0 and not (tmp_path / "x.npz").exists()
    r = cli("fit-reflectance", "--id", "042", "-w", ws, "--output", tmp_path / "a.npz", "--solver", "adam",
            "--steps", "5", "--refine-normals", "1")
    assert r.exit_code == 1 and "fast solver" in r.stderr


def test_observations_with_nothing_to_fit_are_refused(cli, tmp_path):
    # no pair, no observed texel, negative radiance, or lobes that no texel can separate: each used to write
    # all-zero maps with exit 0 (or, with no pair, fail with an internal error); now one line and nothing written
    ws = tmp_path / "ws"
    obs, _, path = _write_obs(ws)
    out = ws / "fit-reflectance" / "042.npz"

    def refused(arrays, msg, *extra):
        write_artifact(path, "uv-observations", arrays)
        r = cli("fit-reflectance", "--id", "042", "--workspace", ws, *extra)
        assert r.exit_code == 1 and msg in r.stderr and str(path) in r.stderr and not out.exists(), r.stderr

    none = {k: (v[:0] if k in ("radiance", "observed", "saturated", "pair_view", "pair_flash") else v)
            for k, v in obs.items()}
    refused(none, "has no observed texel (no view-flash pair)")
    refused({**obs, "observed": np.zeros_like(obs["observed"])}, "none observed")
    refused({**obs, "radiance": -np.abs(obs["radiance"]) - 0.1}, "negative values in observed texels")
    small = {**obs, "radiance": np.where(obs["observed"][..., None], obs["radiance"], 0.0)}
    small["radiance"] = small["radiance"] - 1e-4 * np.abs(small["radiance"]).max()  # noise a little below 0: kept
    write_artifact(path, "uv-observations", small)
    assert cli("fit-reflectance", "--id", "042", "--workspace", ws, "-o", tmp_path / "ok.npz").exit_code == 0
    refused(obs, "no texel could be fitted", "--exponents", ",".join(str(e) for e in range(1, 21)))


def test_flash_intensity_errors_name_their_source(cli, tmp_path):
    ws = tmp_path / "ws"
    obs, _, path = _write_obs(ws)
    F = obs["flash_pos"].shape[0]
    r = cli("fit-reflectance", "--id", "042", "--workspace", ws, "--flash-intensity", "1,2")
    assert r.exit_code == 1 and f"--flash-intensity has 2 values, expected 1 or {F}" in r.stderr
    write_artifact(path, "uv-observations", {**obs, "flash_intensity": np.zeros(F)})
    r = cli("fit-reflectance", "--id", "042", "--workspace", ws)
    assert r.exit_code == 1 and str(path) in r.stderr and "'flash_intensity' must be > 0" in r.stderr


def test_absurd_flash_intensities_are_refused_up_front(cli, tmp_path):
    # 1e300 and 1e-300 ran the fit, leaked a numpy RuntimeWarning (1e300) and ended in "no texel could be fitted:
    # ... ill-conditioned for the lobes of exponents ...", blaming the exponents
    ws = tmp_path / "ws"
    _write_obs(ws)
    for value, problem in (("1e300", "1e+300 is above the maximum 1e+12"),
                           ("1e-300", "1e-300 is below the minimum 1e-12")):
        r = cli("fit-reflectance", "--id", "042", "--workspace", ws, "--flash-intensity", value, "-o",
                tmp_path / "x.npz")
        assert r.exit_code == 1 and r.stderr.strip() == f"reflectmm: error: --flash-intensity: {problem}", r.stderr
        assert not (tmp_path / "x.npz").exists()


def test_fast_solver_settings_are_refused_with_adam(cli, tmp_path):
    # --solver adam --loss l2 wrote maps equal to the bit to the L1 run, with loss = "l2" in their params
    ws = tmp_path / "ws"
    _write_obs(ws)
    for opt, val in (("--loss", "l2"), ("--symmetry-mode", "all"), ("--prior", "0.1")):
        r = cli("fit-reflectance", "--id", "042", "--workspace", ws, "--solver", "adam", "--steps", "2", opt, val)
        assert r.exit_code == 1 and f"{opt} {val}: setting(s) of the fast solver" in r.stderr, r.stderr
    r = cli("fit-reflectance", "--id", "042", "--workspace", ws, "--solver", "adam", "--steps", "2")
    assert r.exit_code == 0, r.stderr
