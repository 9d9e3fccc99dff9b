"""Stage ``evaluate-reconstruction``: the paper's Table 2 on the test split of wild shards — each method's encoder
reconstructs the images; face-region PSNR / SSIM / LPIPS (per image, mean ± 95 % CI, and the released code's
protocol) and the reconstructed per-vertex reflectance against the truth (library:
:func:`reflectmm_cli.evaluation.tables.reconstruction_evaluation`; the shards are read and the encoders run by
:mod:`reflectmm_cli.stages.evaluation_inputs`).

Inputs: ``data`` (wild-shard files), ``light_model`` (the light PCA the encoders were trained with),
``model_<name>`` + ``encoder_<name>`` per method (:mod:`reflectmm_cli.evaluation.methods`), optional
``lpips_weights`` (safetensors). Outputs: ``evaluation`` artifact, markdown table (.md) and the side-by-side
figure (.png) beside it.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from reflectmm_cli.artifacts import atomic_write_text, write_artifact, write_png
from reflectmm_cli.evaluation.documents import EVAL_KIND
from reflectmm_cli.evaluation.methods import check_method_names
from reflectmm_cli.errors import ReflectmmError
from reflectmm_cli.params import Param
from reflectmm_cli.progress import log
from reflectmm_cli.stages.base import Input, Stage, StageContext
from reflectmm_cli.stages.reconstruct import refine_config, refine_params

VERB = "evaluate-reconstruction"

#: The stage's input roles (checked in recipes and on the command line; shown in --help).
INPUTS = (
    Input('data', 'wild-shard', upstream='prepare-wild', many=True),
    Input('light_model', 'light-model', upstream='build-light-pca'),
    Input('lpips_weights', 'LPIPS weights (safetensors)'),
    Input('model', 'reflectance-model', prefix=True, help='one method each'),
    Input('encoder', 'finetune-encoder', prefix=True, help='the encoder of method <name>'),
)


def _check_gain(v) -> None:
    if len(v) != 2 or v[0] == v[1]:
        raise ValueError("give two different method names A,B (A − B PSNR is the finetuning gain)")
    check_method_names(v)


def _pairs(v) -> list[tuple[str, str]]:
    return [tuple(x.split(":")) for x in v or ()]


def unequal_budgets(methods, pairs) -> dict[str, list[str]]:
    """``{"A - B": [differences]}`` for each pair of methods (both present) whose encoders were trained with
    different budgets (:func:`~reflectmm_cli.finetune.encoder.budget_differences`): their gain is then not the
    model's alone."""
    from reflectmm_cli.finetune.encoder import budget_differences, read_encoder_meta

    enc = {m.name: m.encoder for m in methods if m.encoder is not None}
    out = {}
    for a, b in pairs:
        if a in enc and b in enc and f"{a} - {b}" not in out:
            d = budget_differences(read_encoder_meta(enc[a]), read_encoder_meta(enc[b]))
            if d:
                out[f"{a} - {b}"] = d
    return out


def _check_pairs(v) -> None:
    for x in v or ():
        pair = x.split(":")
        if len(pair) != 2 or pair[0] == pair[1] or not all(pair):
            raise ValueError(f"'{x}' is not A:B with two different method names")
        check_method_names(pair)


PARAMS = (
    Param("methods", "strs", None, check=check_method_names, option="",
          help="Method names in table order (inputs model_<name>, encoder_<name>); default: the model roles, "
               "sorted."),
    Param("split", "str", "test", choices=("train", "val", "test", "all"), help="Images evaluated."),
    Param("region", "str", "face", choices=("face", "skin"),
          help="face = the face model's pixels (the paper's region); skin = skin ∧ not occluded."),
    Param("ci", "str", "t", choices=("t", "bootstrap"), help="95 % confidence interval: Student-t or bootstrap."),
    Param("released_batch", "int", 32, range=(1, 4096), help="Batch size of the released code's protocol."),
    Param("lpips_net", "str", "alex", choices=("alex", "vgg"), help="LPIPS backbone of --lpips-weights."),
    Param("gain", "strs", ["finetuned", "initial"], check=_check_gain,
          help="A,B: A − B mean PSNR stands beside the paper's +0.95 dB (ours over ours w/o finetuning)."),
    Param("more_gains", "strs", ["oracle:initial"], check=_check_pairs,
          help="More A:B pairs whose paired gains are reported beside --gain when both methods are present (the "
               "default: the oracle model over the control, the ceiling of the finetuning gain)."),
    Param("figure_images", "int", 3, range=(0, 64), help="Test images shown in the figure (one row per method)."),
    Param("max_images", "int", 0, range=(0, None), help="Evaluate only the first N selected images (0 = all)."),
    Param("batch_size", "int", 8, range=(1, 4096), invalidates_cache=False, help="Encoder batch size."),
    Param("allow_other_model", "bool", False, invalidates_cache=False,
          help="Use an encoder with a model it was not trained for (a warning instead of an error)."),
) + refine_params() + (
    Param("refine_methods", "strs", None, check=check_method_names,
          help="With --refine: refine only these methods' rows (default: every method)."),
)

ROLE_OPTIONS = {"data": "--data", "light_model": "--light-model", "lpips_weights": "--lpips-weights"}


def _outputs(ctx: StageContext) -> list[Path]:
    out = ctx.output_path()
    return [out, out.with_suffix(".md"), out.with_suffix(".png")]


def run(ctx: StageContext) -> list[Path]:
    from reflectmm_cli.evaluation.metrics import load_lpips
    from reflectmm_cli.evaluation.methods import command_line, methods_from_inputs
    from reflectmm_cli.evaluation.tables import gap_sentence, psnr_gap_closed, reconstruction_evaluation
    from reflectmm_cli.stages.evaluation_inputs import (load_light_model, reconstruction_predictions,
                                                        select_wild_images, shard_arrays)

    p = ctx.params
    methods = methods_from_inputs(ctx.inputs, p.get("methods"), need_encoder=True, stage=VERB)
    names = [m.name for m in methods]
    missing = [g for g in p["gain"] if g not in names]
    if missing and list(p["gain"]) != ["finetuned", "initial"]:  # the default applies when both are present
        raise ReflectmmError(f"{VERB}: --gain names {', '.join(missing)}, not among the methods "
                             f"({', '.join(names)})")
    unknown = [m for m in (p.get("refine_methods") or []) if m not in names]
    if unknown:
        raise ReflectmmError(f"{VERB}: --refine-methods names {', '.join(unknown)}, not among the methods "
                             f"({', '.join(names)})")
    more = _pairs(p.get("more_gains"))
    unequal = unequal_budgets(methods, [tuple(p["gain"])] + more)
    for pair, diff in unequal.items():
        log.warning(f"{VERB}: warning: the encoders of '{pair}' were trained with different budgets ("
                    f"{'; '.join(diff)}): that gain is not the model's alone")
    lw = ctx.input_list("lpips_weights", required=False)
    lp = load_lpips(lw[0] if lw else None, p["lpips_net"])
    shards, idx, encoding = select_wild_images(ctx.input_list("data"), p["split"], int(p["max_images"]))
    light = load_light_model(ctx.input("light_model"))
    sarr = shard_arrays(shards)
    if "truth_vertex_albedo" not in sarr:
        log.info("evaluate reconstruction: the shards carry no truth_vertex_albedo: image metrics only")
    predictions = reconstruction_predictions(methods, shards, idx, light, batch_size=int(p["batch_size"]),
                                             device=ctx.device, allow_other_model=p["allow_other_model"],
                                             refine=refine_config(p), refine_methods=p.get("refine_methods"),
                                             log=log.info)
    res = reconstruction_evaluation(predictions, sarr, idx, encoding=encoding, region=p["region"], lpips=lp,
                                    lpips_name=(f"on ({p['lpips_net']})" if lp is not None
                                                else "off (no weights given)"),
                                    released_batch=int(p["released_batch"]), ci=p["ci"],
                                    figure_images=int(p["figure_images"]), gain=p["gain"],
                                    more_gains=more)
    out = ctx.output_path()
    png = out.with_suffix(".png")
    cmd = command_line(["evaluate", "reconstruction"], p, ctx.inputs, workspace=ctx.workspace, output=out,
                       role_options=ROLE_OPTIONS, declared=PARAMS)
    md = (f"# Table 2: reconstruction on {res['n_images']} '{p['split']}' images\n\n{res['protocol']}\n\n"
          f"{res['table']}\n\nLPIPS: {res['lpips']}. Images encoded as {res['encoding']}.\n")
    if p.get("refine"):
        md += ("\nRows `<method>-refined`: the encoder's β, γ, z refined per image by analysis-by-synthesis with the "
               "model fixed (docs/finetune.md, \"Per-image refinement\")."
               + (" Row `ceiling`: the same refinement with each image's true per-vertex reflectance, so that "
                  "(method's refined PSNR) / (ceiling PSNR) shows how much of the remaining error is the model's."
                  if res["ceiling"] else "") + "\n")
    if res["gains_table"]:
        md += ("\n## The finetuning gain (per image, same images; mean ± 95 % CI)\n\nA − B of each image, averaged; "
               "for the reflectance errors B − A, so that a positive gain is an improvement everywhere."
               + (" `oracle - initial`: the oracle model over the control, the ceiling of the finetuning gain at "
                  "this encoder budget (what the best model of this size for this population gives)."
                  if "oracle - initial" in res["gains"] else "") + "\n\n"
               f"{res['gains_table']}\n")
        md += "".join(f"\n**Not at equal encoder budget:** `{k}`: {'; '.join(v)}.\n" for k, v in unequal.items())
    gap = psnr_gap_closed(res["gains"], p["gain"], unequal)
    gap_text = gap_sentence(gap, p["gain"], res["gains"]) if gap else ""
    if gap_text:
        md += "\n" + gap_text + "\n"
    if res["figure"] is not None:
        md += (f"\nFigure `{png.name}`: columns input | reconstruction | diffuse | specular | error (|recon − input|, "
               "white at 0.2); rows: " + "; ".join(res["figure_rows"]) + ".\n")
    md += f"\nCommand: `{cmd}`\n"
    write_png(png, res["figure"] if res["figure"] is not None else np.zeros((8, 8, 3)))
    atomic_write_text(out.with_suffix(".md"), md)
    write_artifact(out, EVAL_KIND, res["arrays"], params=ctx.resolved_params(), inputs=ctx.input_refs(out.parent),
                   producer=ctx.producer(), cache_key=ctx.cache_key,
                   extra_meta={"evaluation": "reconstruction", "command": cmd, "table": res["table"],
                               "methods": [m.name for m in methods], "images": res["images"],
                               "lpips": res["lpips"], "encoding": res["encoding"], "summary": res["summary"],
                               "paper_numbers": res["paper_numbers"], "figure_rows": res["figure_rows"],
                               "protocol": res["protocol"], "gains": res["gains"],
                               "gains_table": res["gains_table"], "unequal_budgets": unequal,
                               "psnr_gap_closed": gap, "psnr_gap_sentence": gap_text})
    log.info(res["table"])
    return [out, out.with_suffix(".md"), png]


# version 2: + the encoders' unequal budgets and the gap to the oracle closed in PSNR
# version 3: no share of an oracle gain whose interval holds zero
STAGE = Stage(VERB, version=3, run=run, per_identity=False, outputs=_outputs, params=PARAMS,
              help="the paper's Table 2: reconstruction quality and reflectance error on wild test images", inputs=INPUTS)
