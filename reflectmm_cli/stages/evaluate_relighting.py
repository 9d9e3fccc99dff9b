"""Stage ``evaluate-relighting``: the paper's Fig. 7 on a held-out synthetic Multi-PIE identity — reconstruct
from one image with each method, re-render under held-out flashes, compare with the captured OLAT images
(library: :func:`reflectmm_cli.evaluation.tables.relighting_evaluation`; the artifacts are read and the encoders
run by :mod:`reflectmm_cli.stages.evaluation_inputs`).

Per identity. Inputs: ``capture`` (preprocess-multipie), ``geometry`` (fit-geometry), ``face_model``,
``light_model`` (for methods with an encoder), ``model_<name>`` [+ ``encoder_<name>``] per method, optional
``observations`` (uv-observations; the encoder-free fit of a method without an encoder). Outputs:
``evaluation`` artifact ``<ws>/evaluate-relighting/<id>.npz``, markdown table, figure PNG.
"""

from __future__ import annotations

from pathlib import Path

from reflectmm_cli.artifacts import atomic_write_text, write_artifact, write_png
from reflectmm_cli.evaluation.documents import EVAL_KIND
from reflectmm_cli.evaluation.methods import check_method_names
from reflectmm_cli.params import Param
from reflectmm_cli.progress import log
from reflectmm_cli.stages.base import Default, Input, Stage, StageContext
from reflectmm_cli.stages.reconstruct import refine_config, refine_params

VERB = "evaluate-relighting"

PARAMS = (
    Param("methods", "strs", None, check=check_method_names, option="",
          help="Method names in table order (inputs model_<name> [, encoder_<name>]); default: the model roles, "
               "sorted."),
    Param("view", "str", "05_1", help="The camera of the input image and of the held-out OLAT images."),
    Param("input", "str", "room", help="The input image: 'room' (room light) or a flash id (that flash's shot)."),
    Param("holdout", "strs", None, help="Held-out flashes re-rendered (default: every flash but the input's)."),
    Param("scale", "str", "global", choices=("global", "none"),
          help="global = one least-squares scale per method over all held-out flashes (albedo/light ambiguity)."),
    Param("size", "int", 224, range=(32, 1024), unit="px", help="Side of the aligned crop given to the encoders."),
    Param("encoding", "str", "gamma1.2", choices=("gamma1.2", "srgb", "linear"),
          help="Encoding of the images the encoders were trained on (synth wild: gamma1.2)."),
    Param("exposure", "float", 1.0, range=(0.0, 1e6), low_open=True,
          help="Factor on the linear input image before encoding it for the encoders."),
    Param("prior", "float", 1e-4, range=(0.0, 1e6), help="λ of the encoder-free coefficient fit."),
    Param("allow_other_model", "bool", False, invalidates_cache=False,
          help="Use an encoder with a model it was not trained for (a warning instead of an error)."),
) + refine_params()

ROLE_OPTIONS = {"capture": "--capture", "geometry": "--geometry", "face_model": "--face-model",
                "light_model": "--light-model", "observations": "--observations"}

#: The stage's input roles (checked in recipes and on the command line; shown in --help).
INPUTS = (
    Input('capture', 'capture', upstream='preprocess-multipie', many=True, default=Default(checked=False)),
    Input('face_model', 'face-model artifact or BFM .mat', upstream='synth-multipie', help='the mesh and its UVs',
          default=Default('face-model', geometry='geometry',
                          missing='evaluate relighting: no --face-model given and none found in {workspace}')),
    Input('geometry', 'geometry', upstream='fit-geometry', many=True, default=Default(checked=False)),
    Input('light_model', 'light-model', upstream='build-light-pca'),
    Input('observations', 'uv-observations', upstream='unwrap-uv', many=True),
    Input('model', 'reflectance-model', prefix=True, help='one method each'),
    Input('encoder', 'finetune-encoder', prefix=True, help='the encoder of method <name>'),
)


def _outputs(ctx: StageContext) -> list[Path]:
    out = ctx.output_path()
    return [out, out.with_suffix(".md"), out.with_suffix(".png")]


def run(ctx: StageContext) -> list[Path]:
    from reflectmm_cli.evaluation.methods import command_line, methods_from_inputs
    from reflectmm_cli.evaluation.tables import relighting_evaluation, relighting_selection
    from reflectmm_cli.stages.evaluation_inputs import relighting_inputs, relighting_reflectances

    p = ctx.params
    methods = methods_from_inputs(ctx.inputs, p.get("methods"), stage=VERB)
    lm = ctx.input_list("light_model", required=False)
    ob = ctx.input_list("observations", required=False)
    cap, geo, fm = relighting_inputs(ctx.input("capture"), ctx.input("geometry"), ctx.input("face_model"),
                                     identity=ctx.identity, observations=ob[0] if ob else None)
    sel = relighting_selection(cap, geo, view=p["view"], input_light=p["input"], holdout=p.get("holdout"),
                               source=ctx.input("capture"))
    reflectances = relighting_reflectances(methods, cap, geo, fm, sel, light_model=lm[0] if lm else None,
                                           observations=ob[0] if ob else None, view=p["view"],
                                           input_light=p["input"], size=int(p["size"]), encoding=p["encoding"],
                                           exposure=float(p["exposure"]), prior=float(p["prior"]),
                                           device=ctx.device, allow_other_model=p["allow_other_model"],
                                           refine=refine_config(p))
    res = relighting_evaluation(reflectances, cap, geo, fm, sel, view=p["view"], input_light=p["input"],
                                scale=p["scale"], log=log.info)
    out = ctx.output_path()
    png = out.with_suffix(".png")
    cmd = command_line(["evaluate", "relighting"], p, ctx.inputs, workspace=ctx.workspace, output=out,
                       role_options=ROLE_OPTIONS, identity=ctx.identity, declared=PARAMS)
    ident = ctx.identity or out.stem
    md = (f"# Relighting: identity {ident}, view {res['view']}, input {res['input']}\n\n{res['protocol']}\n\n"
          f"Held-out flashes: {', '.join(res['holdout'])}.\n\n{res['table']}\n\n"
          f"Figure `{png.name}` (flash {res['holdout'][0]}): first row " + res["figure_rows"][0] +
          "; then one row per method (" + ", ".join(res["figure_rows"][1:]) + "): captured OLAT | relit | diffuse | "
          "specular | error (white at 0.2).\n\n" + f"Command: `{cmd}`\n")
    write_png(png, res["figure"])
    atomic_write_text(out.with_suffix(".md"), md)
    write_artifact(out, EVAL_KIND, res["arrays"], params=ctx.resolved_params(), inputs=ctx.input_refs(out.parent),
                   producer=ctx.producer(), cache_key=ctx.cache_key,
                   extra_meta={"evaluation": "relighting", "identity": ident, "command": cmd,
                               "table": res["table"], "methods": [m.name for m in methods], "view": res["view"],
                               "input": res["input"], "holdout": res["holdout"], "summary": res["summary"],
                               "coefficients_from": res["paths"], "protocol": res["protocol"]})
    log.info(res["table"])
    return [out, out.with_suffix(".md"), png]


STAGE = Stage(VERB, version=1, run=run, per_identity=True, outputs=_outputs, params=PARAMS,
              help="the paper's Fig. 7: relight one image of a held-out identity under held-out flashes", inputs=INPUTS)
