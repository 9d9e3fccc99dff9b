"""Recipes: TOML descriptions of a pipeline, a caching planner, executors and a run log.

Python API::

    from reflectmm_cli.recipes import load_recipe, run_recipe
    report = run_recipe("recipes/synthetic.toml", "work", executor="pool", jobs=2)
    assert report.ok, [t.error for t in report.by_status("failed")]

See docs/recipes.md.
"""

from reflectmm_cli.recipes.executors import (DaskExecutor, Executor, PoolExecutor, SerialExecutor, TaskSpec,
                                             execute_task, make_executor)
from reflectmm_cli.recipes.plan import Plan, Task, make_plan
from reflectmm_cli.recipes.recipe import Recipe, Ref, StageSpec, load_recipe, parse_recipe_text
from reflectmm_cli.recipes.runner import RunReport, TaskOutcome, plan_recipe, run_recipe

__all__ = ["DaskExecutor", "Executor", "PoolExecutor", "SerialExecutor", "TaskSpec", "execute_task",
           "make_executor", "Plan", "Task", "make_plan", "Recipe", "Ref", "StageSpec", "load_recipe",
           "parse_recipe_text", "RunReport", "TaskOutcome", "plan_recipe", "run_recipe"]
