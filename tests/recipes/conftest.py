from __future__ import annotations

from pathlib import Path

import pytest
from recipe_testdata import make_workspace


@pytest.fixture
def ws(tmp_path) -> Path:
    """A workspace with data/<id>/{a,b}.txt for four identities and recipe.toml."""
    return make_workspace(tmp_path / "ws")
