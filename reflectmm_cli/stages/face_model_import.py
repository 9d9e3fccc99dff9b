"""Stage ``face-model-import``: BFM09 / Deep3DFaceRecon .mat → ``face-model`` artifact (+ PNG preview)."""
from __future__ import annotations

from pathlib import Path

from reflectmm_cli.geometry.face_model_tools import import_model
from reflectmm_cli.params import Param
from reflectmm_cli.stages.base import Input, Stage, StageContext
from reflectmm_cli.stages.face_model_create import outputs

VERB = "face-model-import"

PARAMS = (
    Param("units", "str", "auto", choices=("auto", "um", "mm", "dm", "m"),
          help="Units of the file's coordinates: auto (from the extent), um, mm, dm or m."),
    Param("landmarks_base", "int", 1, range=(0, 1), help="Whether --landmarks indices are 0- or 1-based."),
    Param("no_preview", "bool", False, help="Do not write the PNG preview."),
)

#: The stage's input roles (checked in recipes and on the command line; shown in --help).
INPUTS = (
    Input('model', 'BFM09 01_MorphableModel.mat or BFM_model_front.mat'),
    Input('exp', 'expression basis (Exp_Pca.bin)'),
    Input('exp_std', 'expression std (std_exp.txt)'),
    Input('exp_index', 'expression vertex index'),
    Input('landmarks', '68 landmark vertex indices'),
)


def run(ctx: StageContext) -> list[Path]:
    out = ctx.output_path()
    exp = ctx.inputs.get("exp") or [None]
    std = ctx.inputs.get("exp_std") or [None]
    idx = ctx.inputs.get("exp_index") or [None]
    lmk = ctx.inputs.get("landmarks") or [None]
    paths, _ = import_model(ctx.input("model"), out, exp_path=exp[0], exp_std=std[0], exp_index=idx[0],
                            units=ctx.params["units"], landmarks=lmk[0],
                            landmarks_base=ctx.params["landmarks_base"], preview=not ctx.params["no_preview"],
                            meta={"params": ctx.resolved_params(), "inputs": ctx.input_refs(out.parent),
                                  "producer": ctx.producer(), "cache_key": ctx.cache_key})
    return paths


STAGE = Stage(VERB, version=1, run=run, per_identity=False, outputs=outputs, params=PARAMS,
              help="convert BFM09 / Deep3DFaceRecon .mat to a face-model artifact", inputs=INPUTS)
