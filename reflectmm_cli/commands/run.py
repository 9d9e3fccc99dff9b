"""``reflectmm run RECIPE.toml``: plan a recipe, run only what is missing or stale.

Thin wrapper over :func:`reflectmm_cli.recipes.run_recipe` (see docs/recipes.md).
"""

from __future__ import annotations

import json
import logging
from pathlib import Path

import click

from reflectmm_cli.commands._common import json_option, parse_ids, silence_stdout, workspace_option
from reflectmm_cli.errors import ReflectmmError
from reflectmm_cli.workspace import default_workspace

log = logging.getLogger("reflectmm")


def _table(rows: list[list[str]]) -> list[str]:
    widths = [max(len(r[i]) for r in rows) for i in range(len(rows[0]))]
    return ["  ".join(c.ljust(w) for c, w in zip(r, widths)).rstrip() for r in rows]


def format_plan(report) -> list[str]:
    """The ``--dry-run`` text: one line per stage and identity with its action and reason."""
    counts = report.counts()
    head = (f"recipe {report.recipe}: {len(report.tasks)} task(s): "
            + ", ".join(f"{n} {k}" for k, n in sorted(counts.items())))
    rows = [["stage", "id", "action", "reason"]]
    for t in report.tasks:
        rows.append([t.stage, t.id if t.id is not None else "-", t.status, t.reason])
    return [head] + _table(rows)


@click.command("run")
@click.argument("recipe", type=click.Path(path_type=Path), required=False)
@workspace_option
@click.option("--dry-run", "-n", is_flag=True, help="Print what would run and why; run nothing.")
@click.option("--force", "force", is_flag=False, flag_value="*", default=None, metavar="[STAGE]",
              help="Rerun every task (no value) or only STAGE's tasks, even if up to date.")
@click.option("--only", default=None, metavar="STAGE",
              help="Run only STAGE's tasks, using the existing outputs of the stages it reads.")
@click.option("--ids", default=None, help="Restrict per-identity stages to these ids (001,002 or 001-010).")
@click.option("--jobs", "-j", type=click.IntRange(min=1), default=1, show_default=True,
              help="Worker processes (pool executor) or LocalCluster workers (dask executor).")
@click.option("--executor", type=click.Choice(["auto", "serial", "pool", "dask"]), default="auto",
              show_default=True, help="auto: dask with --scheduler, pool with --jobs > 1, else serial.")
@click.option("--scheduler", default=None, metavar="tcp://HOST:PORT",
              help="Address of a running Dask scheduler (implies --executor dask).")
@click.option("--allow-empty", is_flag=True, help="Succeed even when a stage's foreach matches no identity.")
@click.option("--set", "overrides", multiple=True, metavar="STAGE.PARAM=VALUE",
              help="Override one stage parameter of the recipe (a TOML value; repeatable), e.g. "
                   "--set synth-wild.count=384.")
@json_option
def run_cmd(recipe, workspace, dry_run, force, only, ids, jobs, executor, scheduler, allow_empty, overrides,
            as_json):
    """Run RECIPE (TOML): plan the stage DAG and run every task whose cache key or outputs changed.

    Paths in the recipe are relative to the workspace.  Prints the written artifact
    paths (or, with --dry-run, a table of stage / id / action / reason); failed tasks
    are listed on stderr and the exit status is 1; rerunning resumes.
    """
    from reflectmm_cli.recipes import load_recipe, run_recipe
    from reflectmm_cli.recipes.executors import executor_kind

    if recipe is None:
        if force not in (None, "*") and (force.endswith(".toml") or Path(force).is_file()):
            recipe, force = Path(force), "*"  # `run --force RECIPE.toml`: the value was the recipe
        else:
            raise click.UsageError("Missing argument 'RECIPE'.")
    ws = (workspace or default_workspace()).resolve()
    if executor == "auto":
        executor = executor_kind("auto", jobs, scheduler)
    id_list = parse_ids(ids) if ids is not None else None
    if ids is not None and not id_list:
        raise ReflectmmError("--ids: no identity given")
    report = run_recipe(load_recipe(recipe, overrides), ws, dry_run=dry_run, force=force, only=only, ids=id_list,
                        executor=executor, jobs=jobs, scheduler=scheduler)
    try:
        if as_json:
            click.echo(json.dumps(report.as_dict(), indent=2, sort_keys=True, default=str))
        elif dry_run:
            for line in format_plan(report):
                click.echo(line)
        else:
            for p in report.outputs():
                click.echo(p)
    except BrokenPipeError:  # `reflectmm run ... | head`: the results are written, the reader has gone
        silence_stdout()
    if dry_run:
        log.info("planned in %.3f s", report.plan_seconds)
        errors = [t for t in report.tasks if t.status == "error"]
        if errors:  # a layout check that a script can trust: the run would fail these
            raise ReflectmmError(f"{len(errors)} task(s) would fail as planned (the 'error' rows above; first: "
                                 f"{errors[0].tid}: {errors[0].reason})")
        return
    counts = report.counts()
    log.info("%s: %d ran, %d skipped, %d failed, %d blocked (plan %.2f s, run %.2f s)", report.recipe,
             counts.get("ok", 0), counts.get("skipped", 0), counts.get("failed", 0), counts.get("blocked", 0),
             report.plan_seconds, report.run_seconds)
    bad = [t for t in report.tasks if t.status in ("failed", "blocked")]
    if bad:
        for t in bad:
            click.echo(f"reflectmm: {t.status}: {t.tid}: {t.error}", err=True)
        nf = sum(t.status == "failed" for t in bad)
        raise ReflectmmError(f"{nf} task(s) failed, {len(bad) - nf} blocked; the others' results are kept — "
                             f"fix the cause and rerun to resume")
    if not allow_empty and report.empty_error():
        raise ReflectmmError(report.empty_error())


COMMANDS = [run_cmd]
