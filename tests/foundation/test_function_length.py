"""No function or method of ``reflectmm_cli/`` is longer than 120 lines, except those docs/architecture.md lists.

A function's length is ``end_lineno - lineno + 1`` of its ``def`` (docstring and nested functions included;
decorators not).  The allowed exceptions are read from the section "Functions longer than 120 lines" of
docs/architecture.md, one ``- `path:qualified.name` — reason`` item each, so the document and the test cannot
drift: an unlisted long function fails, and so does a listed one that is no longer long or no longer exists.
"""

from __future__ import annotations

import ast
import re
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
PKG = ROOT / "reflectmm_cli"
DOC = ROOT / "docs" / "architecture.md"
SECTION = "## Functions longer than 120 lines"
MAX_LINES = 120

ENTRY = re.compile(r"^- `(?P<path>[\w/]+\.py):(?P<name>[\w.]+)` — (?P<reason>\S.*)$")


def function_lengths(source: str) -> dict[str, int]:
    """Qualified name (``Class.method``, ``outer.inner``) → length in lines of every function of ``source``."""
    out: dict[str, int] = {}

    def visit(node: ast.AST, prefix: str) -> None:
        for child in ast.iter_child_nodes(node):
            if isinstance(child, (ast.FunctionDef, ast.AsyncFunctionDef, ast.ClassDef)):
                name = prefix + child.name
                if not isinstance(child, ast.ClassDef):
                    out[name] = child.end_lineno - child.lineno + 1
                visit(child, name + ".")
            else:
                visit(child, prefix)

    visit(ast.parse(source), "")
    return out


def long_functions() -> dict[str, int]:
    """``path:qualified name`` → length of every function of ``reflectmm_cli/`` longer than :data:`MAX_LINES`."""
    out = {}
    for path in sorted(PKG.rglob("*.py")):
        rel = path.relative_to(PKG).as_posix()
        for name, n in function_lengths(path.read_text()).items():
            if n > MAX_LINES:
                out[f"{rel}:{name}"] = n
    return out


def allowed(doc_text: str) -> dict[str, str]:
    """``path:qualified name`` → reason, from the section :data:`SECTION` of the architecture document."""
    lines = doc_text.splitlines()
    assert SECTION in lines, f"docs/architecture.md has no section '{SECTION}'"
    out: dict[str, str] = {}
    for line in lines[lines.index(SECTION) + 1:]:
        if line.startswith("## "):
            break
        if not line.startswith("- "):
            continue
        m = ENTRY.match(line)
        assert m, f"docs/architecture.md, '{SECTION}': not '- `path:function` — reason': {line!r}"
        key = f"{m['path']}:{m['name']}"
        assert key not in out, f"docs/architecture.md, '{SECTION}': {key} listed twice"
        out[key] = m["reason"]
    return out


def test_no_function_is_longer_than_120_lines_unless_listed_in_the_architecture_doc():
    long = long_functions()
    listed = allowed(DOC.read_text())
    unlisted = [f"{k} ({n} lines)" for k, n in sorted(long.items()) if k not in listed]
    stale = [k for k in sorted(listed) if k not in long]
    assert not unlisted, (f"functions longer than {MAX_LINES} lines: shorten them, or list them with a reason in "
                          f"docs/architecture.md '{SECTION}': " + ", ".join(unlisted))
    assert not stale, (f"docs/architecture.md '{SECTION}' lists functions that are no longer longer than {MAX_LINES} "
                       f"lines (or no longer exist): remove them: " + ", ".join(stale))


def test_lengths_and_qualified_names():
    src = ("def f():\n    return 1\n\n\nclass C:\n    @staticmethod\n    def m(x):\n        '''doc'''\n\n"
           "        def inner():\n            pass\n        return x\n")
    assert function_lengths(src) == {"f": 2, "C.m": 6, "C.m.inner": 2}
    doc = (f"# A\n\n{SECTION}\n\nText.\n\n- `a/b.py:C.m` — why\n- `c.py:f` — because\n\n## Next\n\n"
           "- `d.py:g` — not in the section\n")
    assert allowed(doc) == {"a/b.py:C.m": "why", "c.py:f": "because"}
