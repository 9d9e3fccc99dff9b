"""Issue 24: ids that would lead a verb out of its workspace, outputs that would overwrite their own inputs, and a
group of outputs committed together.

An id is a safe id (letters, digits, '_' and '-'); every way an id enters is checked by the one rule
(``reflectmm_cli.workspace.check_id``) and refused with one line naming the id and the rule, before anything is
read or written.  A run whose output or side file is one of its input files is refused before it computes.
"""

from __future__ import annotations

import errno
import os
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from reflectmm_cli.artifacts import committed_together, write_artifact, write_png
from reflectmm_cli.errors import ReflectmmError
from reflectmm_cli.params import parse_ids
from reflectmm_cli.stages import get_stage, run_stage
from reflectmm_cli.workspace import ID_RULE, check_id, check_inside, stage_output

BAD_IDS = ["../x", "../../outside/pwn", "/abs/pwn", "a/b", "..", ".", "", "a b", "x\n", "ünï", "a" * 129, "a;rm",
           "~root", "a\\b"]
GOOD_IDS = ["001", "w001_000024", "shard_00000", "A-b_9", "a" * 128]


def _one_line_refusal(result, ident: str) -> str:
    assert result.exit_code == 1, result.output
    err = result.stderr.strip()
    assert len(err.splitlines()) == 1 and "Traceback" not in err, err
    assert repr(ident) in err and ID_RULE in err, err
    return err


def _tree(root: Path) -> dict[str, bytes]:
    return {str(p.relative_to(root)): p.read_bytes() for p in sorted(root.rglob("*")) if p.is_file()}


# --------------------------------------------------------------------------- the rule

@pytest.mark.parametrize("ident", GOOD_IDS)
def test_safe_ids_pass(ident):
    assert check_id(ident) == ident


@pytest.mark.parametrize("ident", BAD_IDS)
def test_unsafe_ids_are_refused_naming_the_id_and_the_rule(ident):
    with pytest.raises(ReflectmmError) as exc:
        check_id(ident, "--id")
    msg = str(exc.value)
    assert msg.startswith("--id: ") and repr(ident) in msg and ID_RULE in msg


@given(st.text(max_size=40))
def test_an_accepted_id_composes_a_path_inside_the_workspace(text):
    """Whatever the text: either it is refused, or <ws>/<stage>/<id>.npz is a direct child of <ws>/<stage>."""
    ws = Path("/ws")
    try:
        ident = check_id(text)
    except ReflectmmError:
        return
    p = stage_output(ws, "fit-reflectance", ident)
    assert os.path.normpath(p) == str(p) and p.parent == ws / "fit-reflectance"


def test_composed_paths_must_stay_inside_the_workspace():
    with pytest.raises(ReflectmmError, match="outside the workspace"):
        stage_output(Path("/ws"), "unwrap-uv", "../../etc/passwd")
    with pytest.raises(ReflectmmError, match="outside the workspace"):
        check_inside("/ws/../x.npz", "/ws")
    assert check_inside("/ws/a/../b.npz", "/ws") == Path("/ws/a/../b.npz")


def test_ids_text_and_id_files_are_checked(tmp_path):
    assert parse_ids("001-003,w001_000024") == ["001", "002", "003", "w001_000024"]
    with pytest.raises(ReflectmmError, match=r"^--ids: id '\.\./x' refused"):
        parse_ids("001,../x")
    f = tmp_path / "ids.txt"
    f.write_text("001  # fine\n\n/abs/pwn\n")
    with pytest.raises(ReflectmmError) as exc:
        parse_ids(None, f)
    assert str(exc.value).startswith(f"{f}: line 3: id '/abs/pwn' refused")


def test_the_python_api_refuses_an_unsafe_identity(tmp_path):
    (tmp_path / "a.txt").write_text("a")
    with pytest.raises(ReflectmmError, match=r"stage 'checksum': id '\.\./out' refused"):
        run_stage(get_stage("checksum"), workspace=tmp_path / "ws", identity="../out",
                  inputs={"files": [tmp_path / "a.txt"]})
    assert not (tmp_path / "out.npz").exists()


# --------------------------------------------------------------------------- the command line

def test_checksum_id_cannot_write_outside_the_workspace(cli, tmp_path):
    (tmp_path / "a.txt").write_text("a")
    ws = tmp_path / "ws"
    r = cli("checksum", tmp_path / "a.txt", "--id", "../outside/pwn", "-w", ws)
    _one_line_refusal(r, "../outside/pwn")
    assert not (tmp_path / "outside").exists() and not ws.exists()


def test_fit_reflectance_id_cannot_read_or_overwrite_a_file_outside(cli, tmp_path):
    """The issue's case: --id ../../some/dir/evil read some/dir/evil.npz and wrote its result over it."""
    evil = tmp_path / "some" / "dir" / "evil.npz"
    evil.parent.mkdir(parents=True)
    write_artifact(evil, "uv-observations", {"x": np.zeros(3)})
    before = _tree(tmp_path)
    ws = tmp_path / "a" / "work"
    ws.mkdir(parents=True)
    ident = "../../../some/dir/evil"
    assert (ws / "unwrap-uv" / f"{ident}.npz").resolve() == evil.resolve()  # the path the convention composed
    _one_line_refusal(cli("fit-reflectance", "--id", ident, "-w", ws), ident)
    assert _tree(tmp_path) == before


@pytest.mark.parametrize("argv", [
    ["unwrap-uv", "--id", "{bad}"], ["fit-geometry", "--id", "{bad}"], ["evaluate", "truth", "--id", "{bad}"],
    ["evaluate", "relighting", "--id", "{bad}"], ["preprocess-multipie", "--root", "{tmp}", "--id", "{bad}"],
    ["preprocess-multipie", "--root", "{tmp}", "--ids", "001,{bad}"], ["build-pca", "--ids", "001,{bad}"],
    ["calibrate-rig", "--ids", "{bad}"], ["evaluate", "representation", "--ids", "{bad}"],
    ["evaluate", "albedo", "--ids", "{bad}"], ["prepare-wild", "--images", "{tmp}", "--shard", "{bad}"],
    ["run", "{tmp}/recipe.toml", "--ids", "{bad}"]])
@pytest.mark.parametrize("bad", ["../x", "/abs/pwn"])
def test_every_id_option_refuses_unsafe_ids_before_anything_runs(cli, tmp_path, argv, bad):
    (tmp_path / "recipe.toml").write_text('schema = "reflectmm.recipe/1"\n[stages.c]\nverb = "checksum"\n'
                                          'foreach = ["001"]\ninputs = { files = "recipe.toml" }\n')
    before = _tree(tmp_path)
    args = [a.format(bad=bad, tmp=tmp_path) for a in argv] + ["-w", tmp_path / "ws"]
    _one_line_refusal(cli(*args), bad)
    assert _tree(tmp_path) == before


def test_fit_reflectance_input_name_must_be_a_safe_id_or_give_id(cli, tmp_path):
    src = tmp_path / "my scan.npz"
    write_artifact(src, "uv-observations", {"x": np.zeros(3)})
    err = _one_line_refusal(cli("fit-reflectance", "--input", src, "-w", tmp_path / "ws"), "my scan")
    assert "give --id" in err


# --------------------------------------------------------------------------- no output overwrites its input

def test_an_output_that_is_its_own_input_is_refused(cli, tmp_path):
    src = tmp_path / "a.txt"
    src.write_text("precious")
    r = cli("checksum", src, "-o", src, "-w", tmp_path / "ws")
    assert r.exit_code == 1 and "would overwrite its own input 'files'" in r.stderr, r.stderr
    assert len(r.stderr.strip().splitlines()) == 1
    assert src.read_text() == "precious"


@pytest.mark.parametrize("how", ["symlink", "hardlink", "dotdot"])
def test_the_overwrite_guard_sees_through_links_and_dotdot(cli, tmp_path, how):
    src = tmp_path / "d" / "a.txt"
    src.parent.mkdir()
    src.write_text("precious")
    out = tmp_path / "out.npz"
    if how == "symlink":
        out.symlink_to(src)
    elif how == "hardlink":
        os.link(src, out)
    else:
        out = tmp_path / "d" / ".." / "d" / "a.txt"
    r = cli("checksum", src, "-o", out, "-w", tmp_path / "ws")
    assert r.exit_code == 1 and "would overwrite its own input" in r.stderr, r.stderr
    assert src.read_text() == "precious"


def test_a_side_file_that_is_an_input_is_refused(tmp_path):
    """fit-reflectance writes <out>.exr and <out>_<name>.png beside its output: none may be an input either."""
    from reflectmm_cli.stages.base import check_no_overwrite

    stage = get_stage("fit-reflectance")
    obs = tmp_path / "x_albedo.png"  # an input that happens to carry a preview's name
    obs.write_bytes(b"not really")
    ctx = stage.context(workspace=tmp_path, identity="x", inputs={"observations": [obs]}, output=tmp_path / "x.npz")
    with pytest.raises(ReflectmmError, match=r"x_albedo\.png: would overwrite its own input 'observations'"):
        check_no_overwrite(stage, ctx)
    ctx = ctx.with_(output=tmp_path / "y.npz")
    check_no_overwrite(stage, ctx)  # another output name: fine


# --------------------------------------------------------------------------- outputs committed together

def test_committed_together_writes_all_or_nothing(tmp_path):
    a, b = tmp_path / "a.png", tmp_path / "b.npz"
    write_png(a, np.zeros((2, 2)))
    old = a.read_bytes()
    with pytest.raises(RuntimeError):
        with committed_together():
            write_png(a, np.ones((2, 2)))
            assert a.read_bytes() == old  # not replaced inside the block
            raise RuntimeError("a later step fails")
    assert a.read_bytes() == old and sorted(p.name for p in tmp_path.iterdir()) == ["a.png"]  # no temp left
    (tmp_path / "c.png").mkdir()  # a folder in the way of the last file: nothing is replaced
    with pytest.raises(ReflectmmError, match="c.png: cannot write: a folder is in the way"):
        with committed_together():
            write_png(a, np.ones((2, 2)))
            write_artifact(b, "x", {"v": np.zeros(2)})
            write_png(tmp_path / "c.png", np.ones((2, 2)))
    assert a.read_bytes() == old and not b.exists()
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a.png", "c.png"]
    with committed_together():
        write_png(a, np.ones((2, 2)))
        write_artifact(b, "x", {"v": np.zeros(2)})
    assert a.read_bytes() != old and b.is_file()


def test_committed_together_renames_the_primary_last(tmp_path, monkeypatch):
    """The file whose cache key vouches for the others is renamed after them: a run cut short while renaming leaves
    the previous primary, so the next plan reruns the task instead of trusting a mix of old and new files."""
    primary, exr, png = tmp_path / "m.npz", tmp_path / "m.exr", tmp_path / "m_prev.png"
    order: list[str] = []
    real_replace = os.replace

    def record(src, dst):
        order.append(Path(dst).name)
        return real_replace(src, dst)

    monkeypatch.setattr(os, "replace", record)
    with committed_together(last=primary):
        write_png(png, np.zeros((2, 2)))
        write_artifact(primary, "x", {"v": np.zeros(2)})
        write_png(exr.with_suffix(".b.png"), np.zeros((2, 2)))
    assert order == ["m_prev.png", "m.b.png", "m.npz"]
    old = primary.read_bytes()

    def refuse_second(src, dst):  # a secondary that cannot be replaced (an immutable file, a kill)
        if Path(dst).name == "m.b.png":
            raise OSError(errno.EPERM, "Operation not permitted")
        return real_replace(src, dst)

    monkeypatch.setattr(os, "replace", refuse_second)
    with pytest.raises(ReflectmmError, match="m.b.png: cannot write: operation not permitted"):
        with committed_together(last=primary):
            write_artifact(primary, "x", {"v": np.ones(2)})
            write_png(exr.with_suffix(".b.png"), np.ones((2, 2)))
    assert primary.read_bytes() == old
    assert not [p for p in tmp_path.iterdir() if p.name.startswith(".")]  # no temporary file left


def test_a_failed_verb_keeps_every_previous_output(cli, tmp_path, monkeypatch):
    """render writes its EXR (the primary) and then a PNG: a PNG that cannot be written used to leave the new EXR
    over the previous one, with exit 1."""
    import reflectmm_cli.artifacts as artifacts

    assert cli("face-model", "create", "--out", tmp_path / "fm.npz", "--vertices", "800").exit_code == 0
    maps = tmp_path / "maps.npz"
    write_artifact(maps, "reflectance-maps", {"albedo": np.full((3, 8, 8), 0.5, np.float32),
                                              "weights": np.zeros((3, 8, 8), np.float32),
                                              "exponents": np.array([1.0, 8.0, 64.0])})
    out = tmp_path / "r.exr"
    common = ["render", "--face-model", tmp_path / "fm.npz", "--maps", maps, "--camera", "size=32x24,focal=80",
              "-o", out]
    assert cli(*common, "--point-light", "0,0,900").exit_code == 0
    before = {p.name: p.read_bytes() for p in (out, out.with_suffix(".png"))}

    def full(*a, **k):
        raise OSError(errno.ENOSPC, "No space left on device")

    real_png = artifacts.write_png

    def png_fails(path, *a, **k):
        with artifacts.atomic_path(path) as tmp:
            Path(tmp).write_bytes(b"partial")
            full()
        return real_png(path, *a, **k)

    monkeypatch.setattr(artifacts, "write_png", png_fails)
    r = cli(*common, "--point-light", "300,0,900")
    assert r.exit_code == 1 and "no space left on the device" in r.stderr and "r.png" in r.stderr
    assert {p.name: p.read_bytes() for p in (out, out.with_suffix(".png"))} == before
    assert not [p for p in tmp_path.iterdir() if p.name.startswith(".")]
