"""The README's quick tour, run as written: the shell block under "A quick tour" is executed by bash, line for line,
in an empty folder. Only the settings that make it slow are shrunk, by a `reflectmm` shim first on PATH that appends
options to a few verbs (smaller synthetic images and face mesh, fewer fit iterations, smaller env maps) and then
runs this checkout's reflectmm. A tour that stops (a verb whose inputs the tour never made, a typo in an option)
fails here."""
import os
import re
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

README = Path(__file__).resolve().parents[2] / "README.md"

SHIM = """#!/bin/bash
case "$1 $2" in
  "synth multipie") extra=(--image-size 320x240 --face-vertices 2000);;
  "synth envmaps") extra=(--width 64);;
  *) case "$1" in
       fit-geometry) extra=(--iters 60 --photo-rounds 0);;
       *) extra=();;
     esac;;
esac
exec "{python}" -m reflectmm_cli "$@" "${{extra[@]}}"
"""


def tour_block(text: str) -> str:
    """The first ```sh block after the "A quick tour" heading."""
    m = re.search(r"^## A quick tour\n.*?^```sh\n(.*?)^```", text, flags=re.S | re.M)
    assert m, "README.md has no 'A quick tour' section with a sh block"
    return m.group(1)


def test_the_tour_block_is_found_and_uses_only_known_verbs():
    import click

    from reflectmm_cli.cli import main

    block = tour_block(README.read_text())
    verbs = set(re.findall(r"(?:^|[;&|]\s*|do\s+|\n\s*)reflectmm\s+([a-z-]+)", block))
    assert {"synth", "fit-geometry", "fit-reflectance", "build-pca"} <= verbs
    known = set(main.list_commands(click.Context(main)))
    assert verbs <= known, verbs - known


@pytest.mark.slow
@pytest.mark.skipif(shutil.which("bash") is None, reason="needs bash")
def test_the_readme_tour_runs_as_written(tmp_path):
    block = tour_block(README.read_text())
    (tmp_path / "bin").mkdir()
    shim = tmp_path / "bin" / "reflectmm"
    shim.write_text(SHIM.format(python=sys.executable))
    shim.chmod(0o755)
    (tmp_path / "tour.sh").write_text(block)
    env = dict(os.environ, PATH=f"{tmp_path / 'bin'}{os.pathsep}{os.environ['PATH']}",
               PYTHONPATH=os.pathsep.join([str(README.parent)] + [p for p in [os.environ.get("PYTHONPATH")] if p]),
               OMP_NUM_THREADS="1")
    env.pop("REFLECTMM_WORKSPACE", None)
    r = subprocess.run(["bash", "-e", "-o", "pipefail", "tour.sh"], cwd=tmp_path, env=env, capture_output=True,
                       text=True, timeout=900)
    assert r.returncode == 0, r.stderr[-3000:]
    for f in ("work/fit-reflectance/001.npz", "work/fit-reflectance/002.npz", "work/build-pca/build-pca.npz",
              "face.exr"):
        assert (tmp_path / f).is_file(), f
