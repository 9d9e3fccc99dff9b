import os

import pytest
from hypothesis import HealthCheck, settings

os.environ.setdefault("OMP_NUM_THREADS", "2")

settings.register_profile("ci", max_examples=60, deadline=None,
                          suppress_health_check=[HealthCheck.too_slow])
settings.register_profile("dev", max_examples=30, deadline=None,
                          suppress_health_check=[HealthCheck.too_slow])
settings.load_profile("ci" if os.environ.get("CI") else "dev")


@pytest.fixture
def cli():
    """Invoke the reflectmm CLI in-process: cli(*args) -> click Result (stdout and stderr separate)."""
    from click.testing import CliRunner

    from reflectmm_cli.cli import main

    runner = CliRunner()

    def invoke(*args, **kwargs):
        return runner.invoke(main, [str(a) for a in args], catch_exceptions=False, **kwargs)

    return invoke


@pytest.fixture
def recipe_error(cli, tmp_path):
    """recipe_error(stage, body) -> the one-line error of ``run --dry-run`` on a recipe with one stage
    ``[stages.<stage>]`` whose TOML lines are ``body``; asserts a non-zero exit and that the line names the recipe's
    file and the stage."""
    def run(stage: str, body: str) -> str:
        recipe = tmp_path / "r.toml"
        recipe.write_text(f'schema = "reflectmm.recipe/1"\n[stages.{stage}]\n{body}')
        r = cli("run", recipe, "-w", tmp_path, "--dry-run")
        assert r.exit_code != 0
        line = r.stderr.strip()
        assert len(line.splitlines()) == 1 and str(recipe) in line and f"[stages.{stage}]" in line, line
        return line

    return run


@pytest.fixture
def reflectmm_log():
    """The messages logged on the ``reflectmm`` logger during the test (warnings and above), caught by a handler
    of its own: the CLI's logging set-up stops propagation to the root logger, which pytest's caplog listens on."""
    import logging

    msgs: list[str] = []

    class _Catch(logging.Handler):
        def emit(self, record):
            msgs.append(record.getMessage())

    logger = logging.getLogger("reflectmm")
    handler = _Catch(level=logging.WARNING)
    logger.addHandler(handler)
    try:
        yield msgs
    finally:
        logger.removeHandler(handler)


#: runs the CLI (``python SCRIPT VERB ...``) with every NPZ member write slowed down: each write first leaves a
#: marker file named by its pid in ``$MARKERS``, so a test knows that a temporary file is half written, then sleeps
#: a minute. At module level, so the pool's workers get it too (the forkserver imports the main script).
SLOW_WRITES = """
import os, sys, time, zipfile
from pathlib import Path

_writestr = zipfile.ZipFile.writestr


def _slow(self, *args, **kwargs):
    Path(os.environ["MARKERS"], str(os.getpid())).write_text("writing")
    time.sleep(60)
    return _writestr(self, *args, **kwargs)


zipfile.ZipFile.writestr = _slow

if __name__ == "__main__":
    from reflectmm_cli.cli import main

    sys.argv[0] = "reflectmm"
    main()
"""


@pytest.fixture
def slow_writes(tmp_path):
    """(script, markers folder): see :data:`SLOW_WRITES`; pass ``MARKERS=<markers folder>`` in the environment."""
    script, markers = tmp_path / "slow_writes.py", tmp_path / "markers"
    script.write_text(SLOW_WRITES)
    markers.mkdir()
    return script, markers
