"""Layering: command modules are click wrappers that nothing imports; stages and the planner need no click."""

from __future__ import annotations

import ast
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
PKG = ROOT / "reflectmm_cli"


def _imports(path: Path) -> list[str]:
    """Every module name an ``import`` / ``from ... import`` statement of ``path`` names (relative ones resolved)."""
    tree = ast.parse(path.read_text(), str(path))
    pkg = ".".join(path.relative_to(ROOT).with_suffix("").parts[:-1])
    out = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            out += [a.name for a in node.names]
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                parts = pkg.split(".")[: len(pkg.split(".")) - node.level + 1]
                base = ".".join(parts + ([base] if base else []))
            out.append(base)
            out += [f"{base}.{a.name}" for a in node.names]
    return out


def test_no_module_imports_a_command_module():
    offenders = []
    for path in sorted(list(PKG.rglob("*.py")) + list((ROOT / "benchmarks").rglob("*.py"))
                       + list((ROOT / "tests").rglob("*.py"))):
        in_commands = path.parent == PKG / "commands"
        for name in _imports(path):
            if not name.startswith("reflectmm_cli.commands"):
                continue
            rest = name[len("reflectmm_cli.commands"):].lstrip(".")
            if in_commands and (rest.startswith("_common") or rest == ""):
                continue  # command modules share the click helpers of commands/_common.py
            if rest == "" and path == PKG / "cli.py":
                continue
            offenders.append(f"{path.relative_to(ROOT)} imports {name}")
    assert offenders == []


def test_the_cli_lists_every_command_module_explicitly():
    from reflectmm_cli.cli import COMMAND_MODULES, load_command

    modules = {p.stem for p in (PKG / "commands").glob("*.py") if not p.stem.startswith("_")}
    assert set(COMMAND_MODULES.values()) == modules
    for name in COMMAND_MODULES:
        assert load_command(name).name == name


def test_every_registered_stage_has_a_module_and_a_declaration():
    from reflectmm_cli.stages import STAGE_MODULES, all_stages

    stages = all_stages()
    modules = {p.stem for p in (PKG / "stages").glob("*.py")} - {"__init__", "base", "registry", "evaluation_inputs", "defaults"}
    assert set(STAGE_MODULES.values()) == modules
    for verb, st in stages.items():
        if verb in STAGE_MODULES:
            assert st.params is not None, verb
            names = [p.name for p in st.params]
            assert len(names) == len(set(names)), verb


def test_planner_and_stages_load_without_click():
    code = ("import sys\n"
            "from reflectmm_cli.recipes import plan, executors\n"
            "from reflectmm_cli.stages import all_stages\n"
            "all_stages()\n"
            "bad = [m for m in sys.modules if m == 'click' or m.startswith('reflectmm_cli.commands')]\n"
            "assert not bad, bad\n")
    r = subprocess.run([sys.executable, "-c", code], cwd=ROOT, capture_output=True, text=True, timeout=120,
                       env={**__import__("os").environ, "PYTHONPATH": str(ROOT)})
    assert r.returncode == 0, r.stderr
