"""Mutation tests of every artifact reader (issue 24): real files of each kind — NPZ artifacts (a reflectance model,
a wild shard), EXR, safetensors encoders, TOML recipes and rig tables, .pts landmarks — are truncated, bit-flipped
and zeroed by hypothesis. A reader must either read the file (the mutation hit bytes that do not matter) or refuse
it with a one-line ReflectmmError; never another exception, a hang (hypothesis' deadline) or a traceback."""
from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from reflectmm_cli.errors import ReflectmmError

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "finetune"))

MUT = settings(max_examples=int(__import__("os").environ.get("MUTATION_EXAMPLES", "25")), deadline=5000, suppress_health_check=[HealthCheck.function_scoped_fixture,
                                                                       HealthCheck.too_slow])


@st.composite
def mutation(draw):
    """(kind, position in [0, 1), length or bit) — applied to the file's bytes by :func:`mutate`."""
    kind = draw(st.sampled_from(["truncate", "flip", "zero", "flip_header"]))
    return kind, draw(st.floats(0.0, 0.999)), draw(st.integers(1, 64))


def mutate(data: bytes, m) -> bytes:
    kind, pos, n = m
    b = bytearray(data)
    if kind == "truncate":
        return bytes(b[:int(pos * len(b))])
    if kind == "flip_header":  # the first bytes hold the formats' headers and lengths
        i = int(pos * min(len(b), 256))
        b[i] ^= 1 << (n % 8)
        return bytes(b)
    i = int(pos * len(b))
    if kind == "flip":
        b[i] ^= 1 << (n % 8)
    else:
        b[i:i + n] = bytes(len(b[i:i + n]))
    return bytes(b)


def check_reader(read, data: bytes, path: Path, m):
    path.write_bytes(mutate(data, m))
    try:
        read(path)
    except ReflectmmError as exc:
        msg = str(exc)
        assert msg and "\n" not in msg.strip() and "Traceback" not in msg, msg


@pytest.fixture(scope="module")
def files(tmp_path_factory):
    from _shards import make_dataset

    from reflectmm_cli.artifacts import write_exr
    from reflectmm_cli.finetune.encoder import build_encoder, save_encoder
    from reflectmm_cli.landmarks import write_pts
    from reflectmm_cli.rig import load_rig, save_rig

    tmp = tmp_path_factory.mktemp("mut")
    d = make_dataset(tmp / "d", n_images=2, size=16, mesh_n=5)
    enc = build_encoder("resnet18", 3, d["light"].n_components, width=4, z0=1.0)
    save_encoder(enc, tmp / "enc.safetensors", {"config": {}, "inputs": []})
    write_exr(tmp / "img.exr", {"R": np.random.default_rng(0).random((6, 5), dtype=np.float32),
                                "G": np.ones((6, 5), np.float32), "B": np.zeros((6, 5), np.float32)},
              meta={"schema": "reflectmm.test/1"})
    save_rig(load_rig(None), tmp / "rig.toml")
    write_pts(tmp / "lm.pts", np.random.default_rng(1).uniform(0, 100, (68, 2)))
    (tmp / "recipe.toml").write_text('schema = "reflectmm.recipe/1"\n[stages.c]\nverb = "checksum"\n'
                                     'foreach = ["001"]\ninputs = { files = "recipe.toml" }\n')
    return {"model": Path(d["truth_path"]), "light": Path(d["light_path"]), "shard": Path(d["shards"][0]),
            "encoder": tmp / "enc.safetensors", "exr": tmp / "img.exr", "rig": tmp / "rig.toml",
            "pts": tmp / "lm.pts", "recipe": tmp / "recipe.toml", "tmp": tmp}


def _readers():
    from reflectmm_cli.artifacts import read_artifact, read_exr
    from reflectmm_cli.finetune.encoder import load_encoder
    from reflectmm_cli.finetune.shards import load_shards
    from reflectmm_cli.finetune.train import load_models
    from reflectmm_cli.landmarks import read_landmarks
    from reflectmm_cli.recipes.recipe import load_recipe
    from reflectmm_cli.rig import load_rig

    def model(p):
        read_artifact(p, "reflectance-model")

    return {
        "model": model,
        "light": lambda p: load_models(FILES["model"], p),
        "shard": lambda p: load_shards([p]).batch([0]),
        "encoder": lambda p: load_encoder(p),
        "exr": read_exr,
        "rig": load_rig,
        "pts": read_landmarks,
        "recipe": load_recipe,
    }


FILES: dict = {}


@pytest.mark.parametrize("kind", ["model", "light", "shard", "encoder", "exr", "rig", "pts", "recipe"])
def test_mutated_files_give_a_one_line_error_or_a_valid_read(files, kind):
    FILES.update(files)
    read = _readers()[kind]
    data = files[kind].read_bytes()
    read(files[kind])  # the intact file reads
    target = files["tmp"] / f"mut_{kind}{files[kind].suffix}"

    @MUT
    @given(m=mutation())
    def run(m):
        check_reader(read, data, target, m)

    run()


@pytest.mark.parametrize("member", ["__meta__.npy", "v.npy"])
def test_a_member_that_is_not_an_npy_array_is_a_one_line_error(tmp_path, member):
    """A valid zip whose member has lost its .npy header: numpy hands back raw bytes, which reached
    ``.reshape`` as an internal error (found by the mutations above)."""
    import zipfile

    from reflectmm_cli.artifacts import read_artifact, write_artifact

    good = write_artifact(tmp_path / "a.npz", "x", {"v": np.arange(4.0)})
    bad = tmp_path / "b.npz"
    with zipfile.ZipFile(good) as src, zipfile.ZipFile(bad, "w") as dst:
        for info in src.infolist():
            dst.writestr(info.filename, b"\0" * 16 if info.filename == member else src.read(info.filename))
    with pytest.raises(ReflectmmError, match=f"b.npz: truncated or corrupt NPZ member '{member[:-4]}'"):
        read_artifact(bad, "x")
