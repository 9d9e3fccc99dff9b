"""The budget parsing of benchmarks/bench_flash_budget.py."""
import pytest

from _benchmarks import load_benchmark


def test_budget_overrides_take_the_field_types():
    name, over = load_benchmark("bench_flash_budget").parse_budget("long:flash_iters=160,w_flash=100")
    assert name == "long"
    assert over == {"flash_iters": 160, "w_flash": 100.0}
    assert isinstance(over["flash_iters"], int) and isinstance(over["w_flash"], float)


def test_budget_without_overrides_is_the_recipe():
    assert load_benchmark("bench_flash_budget").parse_budget("demo:") == ("demo", {})


def test_budget_refuses_an_unknown_field():
    with pytest.raises(SystemExit, match="no field 'flash_iter'"):
        load_benchmark("bench_flash_budget").parse_budget("x:flash_iter=3")
