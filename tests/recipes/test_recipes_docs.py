"""The recipes shown in docs/recipes.md are valid and plan against the registered verbs."""

from __future__ import annotations

import re
from pathlib import Path

from reflectmm_cli.recipes import parse_recipe_text
from reflectmm_cli.stages import get_stage

DOC = Path(__file__).resolve().parents[2] / "docs" / "recipes.md"


def test_every_toml_block_in_the_recipe_docs_parses_and_names_known_verbs():
    blocks = re.findall(r"```toml\n(.*?)```", DOC.read_text(), re.S)
    assert len(blocks) >= 2
    for text in blocks:
        recipe = parse_recipe_text(text, DOC)
        for spec in recipe.stages.values():
            assert get_stage(spec.verb).verb == spec.verb
        assert recipe.order()
