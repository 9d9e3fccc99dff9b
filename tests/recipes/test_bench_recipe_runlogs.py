"""The run-log comparison of benchmarks/bench_recipe.py (the demo's time table in docs/benchmarks.md)."""
import json
from pathlib import Path

import pytest

from _benchmarks import load_benchmark


def _log(ws: Path, rows):
    d = ws / ".reflectmm"
    d.mkdir(parents=True)
    (d / "runlog.jsonl").write_text("".join(json.dumps(r) + "\n" for r in rows))


def test_the_last_run_its_span_and_stage_sums(tmp_path):
    bench = load_benchmark("bench_recipe")
    ws = tmp_path / "ws"
    _log(ws, [
        {"run": "old", "stage": "a", "status": "ok", "time": "2026-01-01T00:00:50+00:00", "duration": 50.0},
        {"run": "new", "stage": "a", "status": "ok", "time": "2026-01-01T01:00:10+00:00", "duration": 10.0},
        {"run": "new", "stage": "b", "status": "ok", "time": "2026-01-01T01:00:08+00:00", "duration": 6.0},
        {"run": "new", "stage": "b", "status": "ok", "time": "2026-01-01T01:00:30+00:00", "duration": 20.0},
        {"run": "new", "stage": "c", "status": "skipped", "time": "2026-01-01T01:00:31+00:00", "duration": 0.0},
    ])
    rows = bench.last_run(ws)
    assert {r["run"] for r in rows} == {"new"} and len(rows) == 3
    span, total, per_stage = bench.run_summary(rows)
    # earliest start: a ends at 10 s after 01:00 having run 10 s -> starts at 0; last end 30 s
    assert span == pytest.approx(30.0) and total == pytest.approx(36.0)
    assert per_stage == {"a": 10.0, "b": 26.0}


def test_a_workspace_where_nothing_ran_is_refused(tmp_path):
    bench = load_benchmark("bench_recipe")
    ws = tmp_path / "ws"
    _log(ws, [{"run": "x", "stage": "a", "status": "skipped", "time": "2026-01-01T00:00:00+00:00",
               "duration": 0.0}])
    with pytest.raises(SystemExit, match="no task ran"):
        bench.last_run(ws)
