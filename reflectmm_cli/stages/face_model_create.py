"""Stage ``face-model-create``: the built-in procedural face model as a ``face-model`` artifact + PNG preview."""
from __future__ import annotations

from pathlib import Path

from reflectmm_cli.geometry.face_model_tools import create_model
from reflectmm_cli.params import SEED_RANGE, Param
from reflectmm_cli.stages.base import Stage, StageContext

VERB = "face-model-create"

PARAMS = (
    Param("vertices", "int", 35000, range=(400, 2_000_000), help="Approximate vertex count (grid resolution)."),
    Param("seed", "int", 0, range=SEED_RANGE, help="Seed of the random low-frequency basis components."),
    Param("shape_components", "int", 40, range=(0, 200), help="Shape basis components."),
    Param("exp_components", "int", 20, range=(0, 100), help="Expression basis components."),
    Param("no_preview", "bool", False, help="Do not write the PNG preview."),
)

#: The stage's input roles (checked in recipes and on the command line; shown in --help).
INPUTS: tuple = ()


def outputs(ctx: StageContext) -> list[Path]:
    """The artifact and (unless no_preview) its PNG preview."""
    out = ctx.output_path()
    return [out] + ([out.with_suffix(".png")] if not ctx.params.get("no_preview") else [])


def run(ctx: StageContext) -> list[Path]:
    p = ctx.params
    return create_model(ctx.output_path(), p["vertices"], p["seed"], p["shape_components"], p["exp_components"],
                        preview=not p["no_preview"],
                        meta={"params": ctx.resolved_params(), "producer": ctx.producer(),
                              "cache_key": ctx.cache_key})


STAGE = Stage(VERB, version=1, run=run, per_identity=False, outputs=outputs, params=PARAMS,
              help="the built-in procedural face model", inputs=INPUTS)
