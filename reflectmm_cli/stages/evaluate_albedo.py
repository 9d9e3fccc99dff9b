"""Stage ``evaluate-albedo``: the paper's Table 3 on held-out synthetic identities — each method's coefficients
fitted to the identity's OLAT observations, diffuse and specular albedo PSNR / relative errors against the truth
(library: :mod:`reflectmm_cli.evaluation.albedo_eval`, :mod:`reflectmm_cli.evaluation.tables`; the inputs are read
by :func:`reflectmm_cli.stages.evaluation_inputs.albedo_inputs`).

Inputs: ``observations`` (uv-observations of the held-out identities), ``truth`` (their synth-truth files or
the folder holding them, matched by identity), ``model_<name>`` per method (:mod:`.methods`). Outputs: an
``evaluation`` artifact (``<ws>/evaluate-albedo/evaluate-albedo.npz``), the markdown table beside it.
"""

from __future__ import annotations

from pathlib import Path

from reflectmm_cli.artifacts import atomic_write_text, write_artifact
from reflectmm_cli.evaluation.documents import EVAL_KIND
from reflectmm_cli.evaluation.methods import check_method_names
from reflectmm_cli.params import Param
from reflectmm_cli.progress import log, progress
from reflectmm_cli.stages.base import Default, Input, Stage, StageContext

VERB = "evaluate-albedo"

PARAMS = (
    Param("methods", "strs", None, check=check_method_names, option="",
          help="Method names in table order (inputs model_<name>); default: the names of the model roles, sorted."),
    Param("prior", "float", 1e-4, range=(0.0, 1e6),
          help="λ of the coefficient prior λ·ȳ²·Σβ² (relative to the mean squared radiance)."),
    Param("oracle", "bool", False,
          help="Also report each model's projection of the true diffuse albedo (the best it can represent)."),
    Param("ours", "str", "finetuned",
          help="The method whose numbers stand beside the paper's Table 3 ('ours')."),
    Param("max_identities", "int", 0, range=(0, None), help="Evaluate only the first N identities (0 = all)."),
)

ROLE_OPTIONS = {"observations": "--input", "truth": "--truth"}

#: The stage's input roles (checked in recipes and on the command line; shown in --help).
INPUTS = (
    Input('observations', 'uv-observations', upstream='unwrap-uv', many=True, default=Default(checked=False)),
    Input('truth', 'ground-truth NPZ files or their folder', upstream='synth-multipie', many=True,
          default=Default('truth')),
    Input('model', 'reflectance-model', prefix=True, help='one method each'),
)


def _outputs(ctx: StageContext) -> list[Path]:
    out = ctx.output_path()
    return [out, out.with_suffix(".md")]


def run(ctx: StageContext) -> list[Path]:
    from reflectmm_cli.evaluation.methods import command_line, methods_from_inputs
    from reflectmm_cli.evaluation.tables import albedo_evaluation
    from reflectmm_cli.stages.evaluation_inputs import albedo_inputs

    p = ctx.params
    methods = methods_from_inputs(ctx.inputs, p.get("methods"), stage=VERB)
    obs = ctx.input_list("observations")
    if int(p["max_identities"]) > 0:
        obs = obs[: int(p["max_identities"])]
    out = ctx.output_path()
    models, identities = albedo_inputs(methods, obs, ctx.input_list("truth"))
    res = albedo_evaluation(models, identities, prior=float(p["prior"]), oracle=bool(p["oracle"]),
                            ours=str(p["ours"]), progress_fn=lambda it: progress(it, desc="albedo", unit="fit"))
    cmd = command_line(["evaluate", "albedo"], p, ctx.inputs, workspace=ctx.workspace, output=out,
                       role_options=ROLE_OPTIONS, declared=PARAMS)
    write_artifact(out, EVAL_KIND, res["arrays"], params=ctx.resolved_params(), inputs=ctx.input_refs(out.parent),
                   producer=ctx.producer(), cache_key=ctx.cache_key,
                   extra_meta={"evaluation": "albedo", "command": cmd, "table": res["table"],
                               "methods": [m.name for m in methods], "identities": res["identities"],
                               "paper_numbers": res["paper_numbers"], "summary": res["summary"],
                               "protocol": res["protocol"]})
    atomic_write_text(out.with_suffix(".md"), f"# Table 3: albedo of held-out identities\n\n{res['protocol']}\n\n"
                      f"{res['table']}\n\nCommand: `{cmd}`\n")
    log.info(res["table"])
    return [out, out.with_suffix(".md")]


STAGE = Stage(VERB, version=1, run=run, per_identity=False, outputs=_outputs, params=PARAMS,
              help="the paper's Table 3: albedo of held-out identities per reflectance model", inputs=INPUTS)
