"""The executable's contract: help, version, verbosity, stdout/stderr split, one-line errors, exit codes."""

from __future__ import annotations

import json
import subprocess
import sys

import numpy as np

from reflectmm_cli import __version__
from reflectmm_cli.artifacts import SCHEMA_MAJOR, read_artifact, sha256_file, write_artifact, write_exr, make_meta


def test_help_lists_verbs(cli):
    r = cli("--help")
    assert r.exit_code == 0
    for verb in ("checksum", "inspect", "run"):
        assert verb in r.stdout
    assert cli("-h").exit_code == 0


def test_version(cli):
    r = cli("--version")
    assert r.exit_code == 0 and __version__ in r.stdout


def test_unknown_verb_and_bad_option_are_usage_errors(cli):
    assert cli("no-such-verb").exit_code == 2
    assert cli("inspect", "--no-such-option", "x").exit_code == 2


def test_checksum_writes_artifact_and_prints_path_only(cli, tmp_path):
    f = tmp_path / "a.txt"
    f.write_text("abc")
    r = cli("checksum", f, "--workspace", tmp_path / "ws", "--id", "007")
    assert r.exit_code == 0, r.stderr
    out = tmp_path / "ws" / "checksum" / "007.npz"
    assert r.stdout.strip().splitlines() == [str(out)]
    art = read_artifact(out, "checksum")
    import hashlib

    assert list(art["sha256"]) == [hashlib.sha256(b"abc").hexdigest()]
    assert list(art["size"]) == [3]
    assert art.meta["inputs"][0]["sha256"] == sha256_file(f)


def test_json_output_is_one_document(cli, tmp_path):
    f = tmp_path / "a.txt"
    f.write_text("abc")
    r = cli("checksum", f, "-o", tmp_path / "m.npz", "--json")
    assert r.exit_code == 0
    assert json.loads(r.stdout) == {"outputs": [str(tmp_path / "m.npz")]}


def test_missing_input_is_one_line_exit_1_no_traceback(cli, tmp_path):
    missing = tmp_path / "nope.txt"
    r = cli("checksum", missing, "--workspace", tmp_path)
    assert r.exit_code == 1
    assert r.stdout == ""
    lines = r.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("reflectmm: error: ") and str(missing) in lines[0]
    assert "Traceback" not in r.stderr


def test_verbose_error_shows_traceback(cli, tmp_path):
    r = cli("-v", "checksum", tmp_path / "nope.txt", "--workspace", tmp_path)
    assert r.exit_code == 1 and "Traceback" in r.stderr


def test_quiet_silences_info_logs(cli, tmp_path):
    d = tmp_path / "data"
    d.mkdir()
    (d / "x").write_text("1")
    recipe = tmp_path / "r.toml"
    recipe.write_text('schema = "reflectmm.recipe/1"\n[stages.m]\nverb = "checksum"\ninputs = { files = "data" }\n')
    # a subprocess: the log handler writes to the process's real stderr
    def run(*args):
        return subprocess.run([sys.executable, "-m", "reflectmm_cli", *map(str, args)], capture_output=True,
                              text=True, timeout=60)

    loud = run("run", recipe, "-w", tmp_path)
    assert loud.returncode == 0 and "1 ran" in loud.stderr
    quiet = run("-q", "run", recipe, "-w", tmp_path, "--force")
    assert quiet.returncode == 0 and quiet.stderr == ""
    assert quiet.stdout.strip() == str(tmp_path / "m" / "m.npz")
    debug = run("-v", "run", recipe, "-w", tmp_path, "--dry-run")
    assert debug.returncode == 0 and "planned in" in debug.stderr and "up to date" in debug.stdout


def test_console_script_runs_as_a_subprocess(tmp_path):
    r = subprocess.run([sys.executable, "-m", "reflectmm_cli", "--version"], capture_output=True, text=True,
                       timeout=60)
    assert r.returncode == 0 and __version__ in r.stdout


# --------------------------------------------------------------------------- inspect

def test_inspect_npz_text_and_json(cli, tmp_path):
    x = np.array([[1.0, np.nan], [np.inf, -3.0]], dtype=np.float32)
    p = write_artifact(tmp_path / "a.npz", "render", {"img": x, "mask": np.array([True, False, True]),
                                                      "names": np.array(["a", "b"])},
                       params={"p": 8}, inputs=[{"role": "obs", "path": "o.npz", "sha256": "ab" * 32}],
                       producer={"stage": "render", "stage_version": 3}, cache_key="ck")
    r = cli("inspect", p)
    assert r.exit_code == 0
    assert "kind:      render" in r.stdout and "cache_key: ck" in r.stdout and "p = 8" in r.stdout
    assert "obs: o.npz  sha256 " + "ab" * 32 in r.stdout
    assert "[-3, 1]  non-finite: 2" in r.stdout
    r = cli("inspect", p, "--json")
    doc = json.loads(r.stdout)
    a = doc["artifacts"][0]
    assert a["kind"] == "render" and a["schema"] == "reflectmm.render/1" and a["producer"]["stage_version"] == 3
    img = next(v for v in a["arrays"] if v["name"] == "img")
    assert img == {"name": "img", "shape": [2, 2], "dtype": "float32", "min": -3.0, "max": 1.0, "nonfinite": 2,
                   "nan": 1}
    mask = next(v for v in a["arrays"] if v["name"] == "mask")
    assert mask["true"] == 2
    assert doc["errors"] == []


def test_inspect_exr(cli, tmp_path):
    ch = {"albedo.R": np.full((4, 3), 0.25, np.float32), "albedo.G": np.linspace(0, 1, 12, dtype=np.float32)
          .reshape(4, 3)}
    p = write_exr(tmp_path / "a.exr", ch, make_meta("reflectance-maps", params={"S": 4}))
    doc = json.loads(cli("inspect", p, "--json").stdout)["artifacts"][0]
    assert doc["format"] == "exr" and doc["kind"] == "reflectance-maps"
    g = next(v for v in doc["arrays"] if v["name"] == "albedo.G")
    assert g["min"] == 0.0 and g["max"] == 1.0 and g["shape"] == [4, 3]


def test_inspect_reports_each_bad_file_and_still_inspects_the_good_ones(cli, tmp_path):
    good = write_artifact(tmp_path / "good.npz", "render", {"x": np.arange(4)})
    plain = tmp_path / "plain.npz"
    np.savez(plain, x=np.zeros(2))
    trunc = tmp_path / "trunc.npz"
    trunc.write_bytes(good.read_bytes()[:200])
    exr = tmp_path / "bad.exr"
    exr.write_bytes(b"garbage" * 30)
    missing = tmp_path / "missing.npz"
    r = cli("inspect", plain, good, trunc, exr, missing)
    assert r.exit_code == 1
    assert "good.npz" in r.stdout and "[0, 3]" in r.stdout
    errs = r.stderr.strip().splitlines()
    assert len(errs) == 4
    for f, what in ((plain, "not a reflectmm artifact"), (trunc, "truncated or corrupt"),
                    (exr, "corrupt EXR"), (missing, "file not found")):
        line = next(e for e in errs if str(f) in e)
        assert line.startswith("reflectmm: error: ") and what in line


def test_inspect_names_a_file_type_it_does_not_read(cli, tmp_path):
    files = [tmp_path / "enc.safetensors", tmp_path / "rig.toml", tmp_path / "img.png", tmp_path / "noext"]
    for f in files:
        f.write_bytes(b"\x89PNG\r\n" if f.suffix == ".png" else b"[a]\nb = 1\n")
    r = cli("inspect", *files)
    assert r.exit_code == 1
    errs = r.stderr.strip().splitlines()
    assert len(errs) == len(files)
    for f, suffix in zip(files, (".safetensors", ".toml", ".png", "no suffix")):
        assert f"reflectmm: error: {f}: not a supported artifact type ({suffix}; inspect reads NPZ and EXR " \
               "artifacts and viewer HTML pages)" in errs
    zipped = tmp_path / "art.bin"  # an artifact under another name is still read
    zipped.write_bytes(write_artifact(tmp_path / "a.npz", "render", {"x": np.arange(2)}).read_bytes())
    assert cli("inspect", zipped).exit_code == 0


def test_inspect_shows_newer_schema_with_a_note(cli, tmp_path):
    p = write_artifact(tmp_path / "n.npz", "geometry", {"x": np.zeros(1)},
                       extra_meta={"schema": f"reflectmm.geometry/{SCHEMA_MAJOR['geometry'] + 1}"})
    r = cli("inspect", p)
    assert r.exit_code == 0 and "newer than this release reads" in r.stdout


def test_inspect_text_caps_long_input_lists(cli, tmp_path):
    refs = [{"role": "image", "path": f"img_{k:03d}.png", "sha256": f"{k:064x}"} for k in range(30)]
    p = write_artifact(tmp_path / "c.npz", "capture", {"x": np.zeros((2, 3))}, inputs=refs)
    r = cli("inspect", p)
    assert "inputs (30):" in r.stdout and "image: ... 23 more (--json lists all)" in r.stdout
    assert "x  (2, 3)  float64  [0, 0]" in r.stdout
    assert len(json.loads(cli("inspect", p, "--json").stdout)["artifacts"][0]["inputs"]) == 30


def _sub(*args):
    return subprocess.run([sys.executable, "-m", "reflectmm_cli", *map(str, args)], capture_output=True, text=True,
                          timeout=120)


def test_quiet_and_verbose_after_the_verb(tmp_path):
    d = tmp_path / "data"
    d.mkdir()
    (d / "x").write_text("1")
    recipe = tmp_path / "r.toml"
    recipe.write_text('schema = "reflectmm.recipe/1"\n[stages.m]\nverb = "checksum"\ninputs = { files = "data" }\n')
    quiet = _sub("run", recipe, "-w", tmp_path, "-q")
    assert quiet.returncode == 0 and quiet.stderr == "", quiet.stderr
    debug = _sub("run", recipe, "--dry-run", "-w", tmp_path, "-v")
    assert debug.returncode == 0 and "planned in" in debug.stderr
    assert _sub("checksum", d, "--quiet", "-w", tmp_path).stderr == ""


def test_quiet_keeps_warnings(tmp_path):
    # build-light-pca's skip notices are warnings, not progress chatter: -q keeps them
    from reflectmm_cli.artifacts import write_exr

    rng = np.random.default_rng(0)
    for i in range(2):
        img = rng.uniform(0.5, 2.0, (8, 16)).astype(np.float32)
        write_exr(tmp_path / f"e{i}.exr", {"R": img, "G": img * 0.5, "B": img * 0.7})
    (tmp_path / "junk.exr").write_bytes(b"junk")
    r = _sub("-q", "build-light-pca", tmp_path, "--order", 2, "-o", tmp_path / "out" / "lm.npz")
    assert r.returncode == 0, r.stderr
    assert "skipping" in r.stderr and "junk.exr" in r.stderr and "components explaining" not in r.stderr


def test_progress_is_plain_lines_when_stderr_is_not_a_terminal(capsys):
    from reflectmm_cli.progress import configure_logging, progress

    configure_logging(0)
    assert list(progress(range(20), desc="work", unit="step")) == list(range(20))
    err = capsys.readouterr().err
    assert "\r" not in err
    lines = err.strip().splitlines()
    assert len(lines) == 10 and lines[0].startswith("work: 2/20 step (10%") and lines[-1].startswith(
        "work: 20/20 step (100%")
    assert list(progress(iter(range(150)), desc="gen")) == list(range(150))
    assert [ln.split(" (")[0] for ln in capsys.readouterr().err.strip().splitlines()] == \
        ["gen: 1 it", "gen: 10 it", "gen: 100 it"]
    configure_logging(-1)
    list(progress(range(5)))
    assert capsys.readouterr().err == ""
    configure_logging(0)


# --------------------------------------------------------------------------- signals

def test_sigterm_while_a_verb_writes_says_so_and_leaves_no_temporary_file(tmp_path, slow_writes):
    # a batch scheduler's timeout or scancel: the process died silently (143), leaving `.out.npz.XXXX.tmp`
    import os
    import signal
    import time

    (tmp_path / "data").mkdir()
    (tmp_path / "data" / "a.txt").write_text("hello")
    out = tmp_path / "out" / "out.npz"
    out.parent.mkdir()
    out.write_bytes(b"the previous result")
    script, markers = slow_writes
    proc = subprocess.Popen([sys.executable, str(script), "checksum", str(tmp_path / "data"), "-o", str(out)],
                            env={**os.environ, "MARKERS": str(markers)}, stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True)
    try:
        deadline = time.monotonic() + 60
        while not any(markers.iterdir()) and proc.poll() is None and time.monotonic() < deadline:
            time.sleep(0.02)
        assert any(out.parent.glob(".out.npz.*")), "the temporary file was not being written"
        proc.send_signal(signal.SIGTERM)
        stdout, stderr = proc.communicate(timeout=30)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    assert proc.returncode == 143, stderr
    assert stderr.strip().splitlines() == ["reflectmm: terminated (SIGTERM)"], stderr
    assert stdout == ""
    assert sorted(p.name for p in out.parent.iterdir()) == ["out.npz"]  # no temporary file left
    assert out.read_bytes() == b"the previous result"
