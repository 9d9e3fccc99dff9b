"""The report and the baselines compute from what their stages read: ``evaluation/report.py`` and
``evaluation/baselines.py`` read no artifact; the evaluate-report stage's readers keep the order, the skipping of
unreadable files and the truth matching the report used to do itself."""
from __future__ import annotations

import ast
from pathlib import Path

import numpy as np
import pytest

from reflectmm_cli.artifacts import write_artifact
from reflectmm_cli.errors import ReflectmmError
from reflectmm_cli.stages.evaluate_report import Artifacts, TruthByIdentity

ROOT = Path(__file__).resolve().parents[2]
READERS = {"read_artifact", "read_meta", "read_exr", "load_face_model", "load"}


@pytest.mark.parametrize("module", ["evaluation/report.py", "evaluation/baselines.py"])
def test_the_library_reads_no_artifact(module):
    tree = ast.parse((ROOT / "reflectmm_cli" / module).read_text())
    imported = {a.asname or a.name for n in ast.walk(tree) if isinstance(n, ast.ImportFrom) for a in n.names}
    called = {n.func.id if isinstance(n.func, ast.Name) else n.func.attr
              for n in ast.walk(tree) if isinstance(n, ast.Call) and isinstance(n.func, (ast.Name, ast.Attribute))}
    assert not (READERS & imported), module
    assert not ({"read_artifact", "read_meta", "read_exr"} & called), module


def _art(path: Path, kind: str, **meta) -> Path:
    return write_artifact(path, kind, {"x": np.arange(3.0)}, extra_meta=meta)


def test_artifacts_read_in_order_and_skip_or_raise(tmp_path):
    a = _art(tmp_path / "a.npz", "evaluation", evaluation="albedo")
    bad = tmp_path / "bad.npz"
    bad.write_bytes(b"not an npz")
    b = _art(tmp_path / "b.npz", "evaluation", evaluation="relighting")
    wrong = _art(tmp_path / "w.npz", "geometry")
    items = Artifacts([a, bad, b, wrong], "evaluation", skip=True)
    assert len(items) == 4 and bool(items)  # len and truth: the files given
    got = list(items)
    assert [p for p, _ in got] == [a, b] and got[1][1].meta["evaluation"] == "relighting"
    with pytest.raises(ReflectmmError, match="bad.npz"):
        list(Artifacts([a, bad, b], "evaluation"))
    seen = []
    with pytest.raises(ReflectmmError, match="b.npz: file not found"):
        for p, _ in Artifacts([a, b], "evaluation"):
            seen.append(p)
            b.unlink()  # the next file is read only when the report gets to it
    assert seen == [a]


def test_truth_by_identity_matches_stems_and_reads_on_lookup(tmp_path):
    folder = tmp_path / "truth"
    t1 = _art(folder / "001.npz", "synth-truth")
    _art(folder / "002.npz", "synth-truth")
    (folder / ".003.npz.tmp.npz").write_bytes(b"")
    t9 = _art(tmp_path / "elsewhere" / "009.npz", "synth-truth")
    truth = TruthByIdentity([folder, t9])
    assert sorted(truth) == ["001", "002", "009"] and len(truth) == 3
    assert np.array_equal(truth["001"]["x"], np.arange(3.0)) and truth.get("005") is None
    t1.unlink()
    with pytest.raises(ReflectmmError):
        truth.get("001")  # read when looked up, not before
    (tmp_path / "empty").mkdir()
    assert not TruthByIdentity([]) and not TruthByIdentity([tmp_path / "empty"])
