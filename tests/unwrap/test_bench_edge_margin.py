"""The identity ranges of benchmarks/bench_edge_margin.py: the project's own id parser."""
import pytest

from _benchmarks import load_benchmark

from reflectmm_cli.errors import ReflectmmError


def test_ids_ranges_and_lists_keep_their_width():
    ids = load_benchmark("bench_edge_margin").parse_ids
    assert ids("001-003,007") == ["001", "002", "003", "007"]
    assert ids("8-10") == ["8", "9", "10"]
    assert ids("042") == ["042"]


def test_ids_reject_a_malformed_range():
    with pytest.raises(ReflectmmError, match="bad range '001-'"):
        load_benchmark("bench_edge_margin").parse_ids("001-")
