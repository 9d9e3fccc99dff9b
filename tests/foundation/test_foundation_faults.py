"""File-system faults give one line naming the real file: full disk, read-only folders and workspaces, and a
newer artifact that this release must not overwrite."""

from __future__ import annotations

import builtins
import errno
import os
import tempfile
import zipfile
from pathlib import Path

import numpy as np
import pytest

from reflectmm_cli.artifacts import make_meta, write_artifact

RECIPE = ('schema = "reflectmm.recipe/1"\n[stages.manifest]\nverb = "checksum"\nforeach = ["001"]\n'
          'inputs = { files = "data/{id}" }\n')


def _one_error_line(r) -> str:
    assert r.exit_code == 1, (r.stdout, r.stderr)
    lines = [ln for ln in r.stderr.splitlines() if ln.startswith("reflectmm: ")]
    assert lines and "internal error" not in r.stderr and "Traceback" not in r.stderr, r.stderr
    return lines[-1]


@pytest.fixture
def data(tmp_path):
    d = tmp_path / "ws" / "data" / "001"
    d.mkdir(parents=True)
    (d / "a.txt").write_text("hello")
    (tmp_path / "ws" / "r.toml").write_text(RECIPE)
    return tmp_path / "ws"


def test_disk_full_names_the_output(cli, data, monkeypatch):
    def full(*a, **k):
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(zipfile.ZipFile, "writestr", full)
    out = data / "out.npz"
    line = _one_error_line(cli("checksum", data / "data", "-o", out))
    assert line.startswith(f"reflectmm: error: {out}: cannot write: no space left on the device"), line
    assert not list(data.glob(".out.npz*"))  # no temporary file left behind
    r = cli("run", data / "r.toml", "-w", data)
    assert r.exit_code == 1
    assert f"{data / 'manifest' / '001.npz'}: cannot write: no space left" in r.stderr, r.stderr


def _read_only(monkeypatch, root: Path):
    """Make every write under ``root`` fail as on a read-only folder (the tests run as root, so chmod won't)."""
    root = str(root)

    def under(p) -> bool:
        try:
            return os.path.abspath(os.fspath(p)).startswith(root)
        except TypeError:
            return False

    def deny(p):
        raise PermissionError(errno.EACCES, "Permission denied", os.fspath(p))

    real_open, real_mkstemp, real_mkdir = builtins.open, tempfile.mkstemp, Path.mkdir

    def fake_open(file, mode="r", *a, **k):
        if any(c in mode for c in "wax+") and under(file):
            deny(file)
        return real_open(file, mode, *a, **k)

    def fake_mkstemp(suffix=None, prefix=None, dir=None, text=False):
        if dir is not None and under(dir):
            deny(os.path.join(dir, f"{prefix or ''}abc123{suffix or ''}"))
        return real_mkstemp(suffix, prefix, dir, text)

    def fake_mkdir(self, *a, **k):
        if under(self) and not self.exists():
            deny(self)
        return real_mkdir(self, *a, **k)

    monkeypatch.setattr(builtins, "open", fake_open)
    monkeypatch.setattr(tempfile, "mkstemp", fake_mkstemp)
    monkeypatch.setattr(Path, "mkdir", fake_mkdir)


def test_read_only_output_folder_names_the_output_not_the_tmp(cli, data, monkeypatch, tmp_path):
    out_dir = tmp_path / "ro"
    out_dir.mkdir()
    _read_only(monkeypatch, out_dir)
    out = out_dir / "out.npz"
    line = _one_error_line(cli("checksum", data / "data", "-o", out))
    assert line == f"reflectmm: error: {out}: cannot write: permission denied ({out_dir}) [errno 13]", line
    assert ".tmp" not in line


def test_noop_run_on_read_only_workspace_succeeds(cli, data, monkeypatch):
    assert cli("run", data / "r.toml", "-w", data).exit_code == 0
    _read_only(monkeypatch, data)
    r = cli("run", data / "r.toml", "-w", data)
    assert r.exit_code == 0, r.stderr  # nothing to do, nothing written
    assert r.stdout == ""
    # a run with work to do fails with one clear line
    r = cli("run", data / "r.toml", "-w", data, "--force")
    line = _one_error_line(r)
    assert line.startswith(f"reflectmm: error: {data}: cannot write to the workspace (Permission denied: "), line
    assert "1 task(s) need to run (manifest/001)" in line


def test_newer_artifact_is_not_overwritten(cli, data):
    out = data / "manifest" / "001.npz"
    meta = make_meta("checksum")
    meta["schema"] = "reflectmm.checksum/9"
    meta["producer"]["version"] = "9.0.0"
    write_artifact(out, "checksum", {"names": np.array(["x"])})
    # forge the newer schema directly (this release cannot write it)
    import json

    with zipfile.ZipFile(out) as zf:
        members = {n: zf.read(n) for n in zf.namelist()}
    buf = __import__("io").BytesIO()
    np.save(buf, np.array(json.dumps(meta)), allow_pickle=False)
    members["__meta__.npy"] = buf.getvalue()
    with zipfile.ZipFile(out, "w") as zf:
        for n, b in members.items():
            zf.writestr(n, b)
    before = out.read_bytes()
    line = _one_error_line(cli("checksum", data / "data" / "001", "--id", "001", "-w", data, "-o", out))
    assert line.startswith(f"reflectmm: error: {out}: holds schema reflectmm.checksum/9, written by reflectmm 9.0.0"
                           ), line
    r = cli("run", data / "r.toml", "-w", data)
    assert r.exit_code == 1 and "refuses to overwrite" in r.stderr
    assert out.read_bytes() == before


def test_an_output_folder_that_cannot_be_written_is_found_before_computing(cli, data, monkeypatch, tmp_path):
    import reflectmm_cli.stages.checksum as checksum

    out_dir = tmp_path / "ro"
    out_dir.mkdir()
    computed = []
    real = checksum.checksum_files
    monkeypatch.setattr(checksum, "checksum_files", lambda paths: computed.append(paths) or real(paths))
    _read_only(monkeypatch, out_dir)
    line = _one_error_line(cli("checksum", data / "data", "-o", out_dir / "sub" / "out.npz"))
    assert "out.npz: cannot write: permission denied" in line and not computed


class _FailingExrOutput:
    """An OpenImageIO writer that fails as on a full disk: text naming the temporary file, no errno."""

    def __init__(self, name):
        self.name = name

    def open(self, name, spec):
        Path(name).write_bytes(b"partial")
        return True

    def write_image(self, data):
        return False

    def close(self):
        return True

    def geterror(self):
        return f'Failed OpenEXR write: Failed to write pixel data to image file "{self.name}". File output failed.'


@pytest.mark.parametrize("free_bytes", [0, 1 << 40], ids=["disk-full", "other-failure"])
def test_exr_write_failure_names_the_output_and_a_full_disk(tmp_path, monkeypatch, free_bytes):
    from types import SimpleNamespace

    from reflectmm_cli import artifacts
    from reflectmm_cli.errors import ReflectmmError

    real = artifacts._oiio()
    fake = SimpleNamespace(ImageSpec=real.ImageSpec, geterror=real.geterror,
                           ImageOutput=SimpleNamespace(create=_FailingExrOutput))
    monkeypatch.setattr(artifacts, "_oiio", lambda: fake)
    monkeypatch.setattr(os, "statvfs", lambda p: SimpleNamespace(f_bfree=free_bytes // 4096,
                                                                 f_bavail=free_bytes // 4096, f_frsize=4096))
    out = tmp_path / "full.exr"
    with pytest.raises(ReflectmmError) as err:
        artifacts.write_exr(out, {"albedo.R": np.zeros((8, 8))}, {"a": 1})
    msg = str(err.value)
    assert "\n" not in msg and ".full.exr." not in msg and msg.startswith(f"{out}: cannot write"), msg
    if free_bytes == 0:
        assert msg == f"{out}: cannot write: no space left on the device [errno 28]"
    else:  # not a matter of space: OpenImageIO's text, naming the output instead of the temporary file
        assert "Failed to write pixel data" in msg and str(out) in msg
    assert list(tmp_path.iterdir()) == []  # the temporary file is removed
