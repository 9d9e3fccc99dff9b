"""The ``reflectmm`` executable: one group of verbs, each a thin wrapper over a library function.

Results go to stdout (artifact paths one per line, or one JSON document with
``--json``); logs and progress bars go to stderr.  Any :class:`ReflectmmError`
becomes one line ``reflectmm: error: ...`` and exit status 1 (a traceback only with
``-v``); usage errors exit 2.
"""

from __future__ import annotations

import sys
import traceback

import click

from reflectmm_cli import __version__
from reflectmm_cli.errors import ReflectmmError
from reflectmm_cli.progress import configure_logging
from reflectmm_cli.signals import TERMINATED_EXIT, Terminated, terminate_as_interrupt


#: The verbs: command name → module of reflectmm_cli.commands (the only place that imports them).
COMMAND_MODULES: dict[str, str] = {
    "build-baseline": "build_baseline",
    "build-light-pca": "build_light_pca",
    "build-pca": "build_pca",
    "calibrate-rig": "calibrate_rig",
    "checksum": "checksum",
    "detect-landmarks": "detect_landmarks",
    "evaluate": "evaluate",
    "face-model": "face_model",
    "finetune": "finetune",
    "fit-geometry": "fit_geometry",
    "fit-reflectance": "fit_reflectance",
    "inspect": "inspect",
    "prepare-wild": "prepare_wild",
    "preprocess-multipie": "preprocess_multipie",
    "reconstruct": "reconstruct",
    "render": "render",
    "run": "run",
    "synth": "synth",
    "unwrap-uv": "unwrap_uv",
    "view": "view",
}


def load_command(name: str) -> click.Command | None:
    """The click command of a verb (imports only its module)."""
    import importlib

    module = COMMAND_MODULES.get(name)
    if module is None:
        return None
    mod = importlib.import_module(f"reflectmm_cli.commands.{module}")
    cmd = next((c for c in mod.COMMANDS if c.name == name), None)
    if cmd is not None:
        _add_inputs_help(cmd, name)
    return cmd


def _add_inputs_help(cmd: click.Command, verb: str) -> None:
    """Append the stage's declared input roles (``Stage.inputs``) to ``--help``; for a group (``evaluate``,
    ``synth``, ``face-model``) to each subcommand ``<group>-<sub>``."""
    from reflectmm_cli.stages.registry import STAGE_MODULES, get_stage

    if isinstance(cmd, click.Group):
        for sub_name, sub in cmd.commands.items():
            _add_inputs_help(sub, f"{verb}-{sub_name}")
        return
    if verb not in STAGE_MODULES or getattr(cmd, "_inputs_help", False):
        return
    inputs = get_stage(verb).inputs
    if inputs:
        lines = "\n".join(f"  {i.describe()}" for i in inputs)
        head = "\b\nInput roles (recipes: inputs = { role = ... }):\n"
        cmd.epilog = ((cmd.epilog + "\n\n") if cmd.epilog else "") + head + lines
    cmd._inputs_help = True


class _Group(click.Group):
    """Loads a verb's module from :data:`COMMAND_MODULES` when it is used, and turns errors into one line."""

    def list_commands(self, ctx: click.Context) -> list[str]:
        return sorted(set(COMMAND_MODULES) | set(self.commands))

    def get_command(self, ctx: click.Context, name: str):
        if name not in self.commands:
            cmd = load_command(name)
            if cmd is None:
                return None
            self.add_command(cmd)
        return self.commands.get(name)

    # verbosity flags are accepted after the verb too (`reflectmm run r.toml -q`); no verb defines its own
    _GLOBAL_FLAGS = ("-q", "--quiet", "-v", "-vv", "-vvv", "--verbose")

    def parse_args(self, ctx: click.Context, args: list[str]) -> list[str]:
        args = list(args)
        verb = next((i for i, a in enumerate(args) if not a.startswith("-")), None)
        if verb is not None:
            end = verb + args[verb:].index("--") if "--" in args[verb:] else len(args)
            moved = [a for a in args[verb + 1:end] if a in self._GLOBAL_FLAGS]
            if moved:
                rest = [a for a in args[verb + 1:end] if a not in self._GLOBAL_FLAGS]
                args = moved + args[:verb + 1] + rest + args[end:]
        return super().parse_args(ctx, args)

    def invoke(self, ctx: click.Context):
        verbose = ctx.params.get("verbose", 0)
        try:
            # SIGTERM (a scheduler's timeout, scancel) unwinds like Ctrl-C: atomic writes remove their temporary files
            with terminate_as_interrupt():
                return super().invoke(ctx)
        except ReflectmmError as exc:
            if verbose:
                traceback.print_exc(file=sys.stderr)
            click.echo(f"reflectmm: error: {exc}", err=True)
            ctx.exit(1)
        except (click.exceptions.Exit, click.ClickException, click.Abort):
            raise
        except BrokenPipeError:
            # stdout closed early (`reflectmm ... | head`): not an error of ours; stop quietly
            import os

            try:
                devnull = os.open(os.devnull, os.O_WRONLY)
                os.dup2(devnull, sys.stdout.fileno())
            except (OSError, ValueError):
                pass
            ctx.exit(141)
        except Terminated:
            click.echo("reflectmm: terminated (SIGTERM)", err=True)
            ctx.exit(TERMINATED_EXIT)
        except KeyboardInterrupt:
            click.echo("reflectmm: interrupted", err=True)
            ctx.exit(130)
        except MemoryError:
            click.echo("reflectmm: error: out of memory", err=True)
            ctx.exit(1)
        except Exception as exc:  # an unexpected failure is still a failure: never exit 0
            if verbose:
                traceback.print_exc(file=sys.stderr)
            msg = " ".join(str(exc).split())[:400]
            click.echo(f"reflectmm: internal error: {type(exc).__name__}: {msg} (run with -v for a traceback)",
                       err=True)
            ctx.exit(1)


@click.group(cls=_Group, context_settings={"help_option_names": ["-h", "--help"], "max_content_width": 110})
@click.version_option(__version__, "--version", prog_name="reflectmm")
@click.option("-v", "--verbose", count=True, help="More logging (debug) and tracebacks on errors.")
@click.option("-q", "--quiet", is_flag=True, help="Only warnings and errors on stderr; no progress or info.")
@click.pass_context
def main(ctx: click.Context, verbose: int, quiet: bool) -> None:
    """Build a 3D morphable face reflectance model (diffuse albedo + multi-lobe Blinn-Phong).

    Every verb reads and writes versioned artifacts (NPZ/EXR) in a workspace
    (--workspace, $REFLECTMM_WORKSPACE, or the current directory).  Results are
    printed on stdout, logs and progress on stderr.
    """
    configure_logging(-1 if quiet else verbose)
    ctx.ensure_object(dict)
    ctx.obj["verbose"] = verbose


if __name__ == "__main__":  # pragma: no cover
    main()
