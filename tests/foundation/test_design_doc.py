"""The project owns its design: every citation of a design section points to docs/design.md, whose numbered
sections exist, and nothing cites a design document outside the repository."""
import re
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
FILES = [p for pattern in ("reflectmm_cli/**/*.py", "tests/**/*.py", "benchmarks/*.py", "docs/*.md", "recipes/*.toml",
                           "README.md", "Makefile")
         for p in ROOT.glob(pattern)]
EXTERNAL = "DESIGN" + ".md"  # written in two parts so that this file does not cite it


def test_no_file_cites_an_external_design_document():
    hits = [str(p.relative_to(ROOT)) for p in FILES if EXTERNAL in p.read_text(errors="replace")]
    assert not hits, hits


def test_every_cited_design_section_exists():
    text = (ROOT / "docs" / "design.md").read_text()
    sections = {int(m) for m in re.findall(r"^## (\d+)\. ", text, flags=re.M)}
    cited = {}
    for p in FILES:
        for m in re.findall(r"design\.md §(\d+)", p.read_text(errors="replace")):
            cited.setdefault(int(m), str(p.relative_to(ROOT)))
    assert cited, "no citation found: the pattern or the file list is wrong"
    missing = {n: f for n, f in cited.items() if n not in sections}
    assert not missing, missing
