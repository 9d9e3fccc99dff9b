"""render / face-model readers on bad inputs: sharp lobes, NaN pixels, odd channel counts, NaN geometry."""
import numpy as np
import pytest

from reflectmm_cli.artifacts import read_exr, write_artifact, write_exr


@pytest.fixture(scope="module")
def ws(tmp_path_factory):
    return tmp_path_factory.mktemp("geomrel")


@pytest.fixture(scope="module")
def model_file(ws):
    from click.testing import CliRunner

    from reflectmm_cli.cli import main

    res = CliRunner().invoke(main, ["face-model", "create", "--out", str(ws / "fm.npz"), "--vertices", "1500",
                                    "--shape-components", "4", "--exp-components", "2", "--seed", "2"],
                             catch_exceptions=False)
    assert res.exit_code == 0, res.output
    return ws / "fm.npz"


def _maps(path, exps, S=32):
    alb = np.full((3, S, S), 0.4, np.float32)
    w = np.full((len(exps), S, S), 0.05, np.float32)
    write_artifact(path, "reflectance-maps", {"albedo": alb, "weights": w, "exponents": np.asarray(exps, float),
                                              "mask": np.ones((S, S), bool)})
    return path


def _env(path, channels=3, value=1.5, nan=False):
    env = np.full((16, 32), value, np.float32)
    if nan:
        env = env.copy()
        env[3, 4] = np.nan
    names = ["R", "G", "B", "A"][:channels] if channels != 2 else ["Y", "A"]
    write_exr(path, {n: env for n in names})
    return path


def test_render_envmap_huge_exponent_is_cheap(cli, model_file, ws, monkeypatch):
    real = np.polynomial.legendre.leggauss
    monkeypatch.setattr(np.polynomial.legendre, "leggauss",
                        lambda n: real(n) if n <= 4096 else pytest.fail(f"leggauss({n})"))
    maps = _maps(ws / "sharp.npz", [1.0, 8.0, 1e5])
    out = ws / "sharp.exr"
    r = cli("render", "--face-model", model_file, "--maps", maps, "--envmap", _env(ws / "env.exr"),
            "--camera", "size=80x60,focal=200", "-o", out)
    assert r.exit_code == 0, r.stderr
    assert np.isfinite(read_exr(out)[0]["R"]).all()


def _nan_model(model_file, dst, field, index):
    from reflectmm_cli.artifacts import read_artifact

    art = read_artifact(model_file, "face-model")
    arrays = dict(art.arrays)
    a = np.array(arrays[field], dtype=np.float32)
    a[index] = np.nan
    arrays[field] = a
    write_artifact(dst, "face-model", arrays, extra_meta={k: v for k, v in art.meta.items()
                                                         if k in ("name", "info")})
    return dst


@pytest.mark.parametrize("field,index,word", [("mean_shape", (7, 1), "vertex 7"), ("uv", (3, 0), "vertex 3")])
def test_face_model_with_nan_is_refused_naming_the_file(cli, model_file, ws, field, index, word):
    import warnings

    bad = _nan_model(model_file, ws / f"nan_{field}.npz", field, index)
    maps = _maps(ws / "m.npz", [1.0, 8.0])
    with warnings.catch_warnings():
        warnings.simplefilter("error", RuntimeWarning)  # no raw numpy warning on the way
        for args in (["face-model", "info", bad],
                     ["render", "--face-model", bad, "--maps", maps, "--point-light", "0,0,900",
                      "--camera", "size=40x30,focal=100", "-o", ws / "x.exr"]):
            r = cli(*args)
            assert r.exit_code == 1, r.stderr
            line = r.stderr.strip()
            assert line.startswith(f"reflectmm: error: {bad}:") and field in line and word in line, line
            assert len(line.splitlines()) == 1
    # the same through a recipe stage
    (ws / "r.toml").write_text('schema = "reflectmm.recipe/1"\n[stages.render]\n'
                               f'inputs = {{ face_model = "{bad.name}", maps = "m.npz" }}\n'
                               'params = { point_light = "0,0,900", camera = "size=40x30,focal=100" }\n')
    r = cli("run", ws / "r.toml", "-w", ws)
    assert r.exit_code == 1 and str(bad) in r.stderr and "NaN" in r.stderr


@pytest.mark.parametrize("kind", ["nan", "two-channel"])
def test_render_refuses_bad_envmap_naming_it(cli, model_file, ws, kind):
    env = _env(ws / f"env_{kind}.exr", channels=2 if kind == "two-channel" else 3, nan=kind == "nan")
    maps = _maps(ws / "m3.npz", [1.0, 8.0])
    r = cli("render", "--face-model", model_file, "--maps", maps, "--envmap", env, "--camera",
            "size=40x30,focal=100", "-o", ws / "y.exr")
    assert r.exit_code == 1
    line = r.stderr.strip()
    want = "NaN or infinite pixel(s) (first at row 3, column 4)" if kind == "nan" else "has 2 channels"
    assert line.startswith(f"reflectmm: error: {env}: environment map: ") and want in line, line
    # build-light-pca refuses the same file for the same reason (alone: nothing usable → error)
    r = cli("build-light-pca", env, "-o", ws / "lm.npz")
    assert r.exit_code == 1 and want in r.stderr and env.name in r.stderr
