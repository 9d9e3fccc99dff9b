"""Shared data for the recipe tests (imported by conftest and the test modules)."""

from __future__ import annotations

import hashlib
from pathlib import Path

IDS = ["001", "002", "003", "004"]

BASIC = """
schema = "reflectmm.recipe/1"
name = "basic"

[defaults]
fail_if_contains = "BAD"

[stages.manifest]
verb = "checksum"
foreach = ["001", "002", "003", "004"]
inputs = { files = "data/{id}" }

[stages.summary]
verb = "checksum"
inputs = { files = "@manifest.output" }
"""


# per-identity manifests, then a stage whose identities are the manifests that exist ("all found": deferred until
# the manifests are written)
DISCOVER_STAGES = """
[stages.manifest]
verb = "checksum"
foreach = ["002", "004"]
inputs = { files = "data/{id}" }

[stages.found]
verb = "checksum"
foreach = "all found"
params = { discover = "manifest/*.npz" }  # identities = the manifests that exist
inputs = { files = "@manifest.output" }
"""


def make_workspace(w: Path) -> Path:
    """data/<id>/{a,b}.txt for four identities and recipe.toml (BASIC)."""
    for i in IDS:
        d = w / "data" / i
        d.mkdir(parents=True)
        (d / "a.txt").write_text(f"identity {i} image a\n")
        (d / "b.txt").write_text(f"identity {i} image b " + "x" * int(i) + "\n")
    (w / "recipe.toml").write_text(BASIC)
    return w


def sha(path: Path) -> str:
    return hashlib.sha256(Path(path).read_bytes()).hexdigest()
