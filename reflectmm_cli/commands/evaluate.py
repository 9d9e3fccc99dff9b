"""``reflectmm evaluate``: click wrappers of the ``evaluate-truth``, ``evaluate-representation`` and
``evaluate-report`` stages (docs/design.md §1 step 8; reflectmm_cli/stages/evaluate_*.py)."""

from __future__ import annotations

import json
from pathlib import Path

import click

from reflectmm_cli.artifacts import read_artifact
from reflectmm_cli.commands._common import (device_option, emit, given_params, id_callback, json_option,
                                            output_option, param_options, parse_ids, run_stage_cli, workspace_option)
from reflectmm_cli.errors import ReflectmmError
from reflectmm_cli.evaluation.documents import EVAL_KIND
from reflectmm_cli.progress import log
from reflectmm_cli.stages import (evaluate_albedo, evaluate_expressive, evaluate_reconstruction, evaluate_relighting, evaluate_report,
                                  evaluate_representation, evaluate_truth)
from reflectmm_cli.stages.defaults import default_inputs
from reflectmm_cli.workspace import resolve_workspace


@click.group("evaluate")
def evaluate_group():
    """Evaluate fitted maps, representations and a whole run (PSNR/SSIM/LPIPS, errors against ground truth)."""


@evaluate_group.command("truth")
@click.option("--id", "identity", callback=id_callback, required=True, help="Identity (names the output).")
@click.option("--maps", type=click.Path(dir_okay=False, path_type=Path), default=None,
              help="reflectance-maps artifact (default <ws>/fit-reflectance/<id>.npz if present).")
@click.option("--truth", "truth", type=click.Path(dir_okay=False, path_type=Path), default=None,
              help="synth-truth artifact (default <id>.npz of the workspace's truth folder: truth/, synth/truth/ or "
                   "synth-multipie/truth/).")
@click.option("--geometry", type=click.Path(dir_okay=False, path_type=Path), default=None,
              help="geometry artifact to evaluate too.")
@click.option("--face-model", type=click.Path(dir_okay=False, path_type=Path), default=None,
              help="face model whose vertices a per-vertex reflectance truth (plain NPZ) refers to.")
@workspace_option
@output_option
def evaluate_truth_cmd(identity, maps, truth, geometry, face_model, workspace, output):
    """Errors of one identity's fitted maps (and geometry) against the ground truth; JSON on stdout.

    Diffuse albedo RMSE / relative error in linear RGB, specular albedo Σw against spec_albedo, separately for
    observable and flagged texels, raw and after one global least-squares scale. Writes an `evaluation`
    artifact (<ws>/evaluate-truth/<id>.npz or --output).
    """
    inputs = default_inputs(evaluate_truth.STAGE, resolve_workspace(workspace), {
        "maps": [maps], "truth": [truth], "geometry": [geometry], "face_model": [face_model]}, identity=identity)
    paths = run_stage_cli(evaluate_truth.VERB, workspace=workspace, identity=identity, inputs=inputs, output=output)
    art = read_artifact(paths[0], EVAL_KIND)
    click.echo(json.dumps({"outputs": [str(p) for p in paths], "identity": identity,
                           "errors": art.meta["errors"]}, indent=2, sort_keys=True))


@evaluate_group.command("representation")
@click.option("--ids", default=None, help="Identities: reads <ws>/unwrap-uv/<id>.npz (uv-observations).")
@click.option("--input", "-i", "inputs", multiple=True, type=click.Path(dir_okay=False, path_type=Path),
              help="A uv-observations artifact (repeatable).")
@click.option("--lpips-weights", type=click.Path(dir_okay=False, path_type=Path), default=None,
              help="A torch state dict of LPIPS (trunk + lin layers). Without it LPIPS is off.")
@click.option("--face-model", type=click.Path(dir_okay=False, path_type=Path), default=None,
              help="Face model for image space (default: as build-pca).")
@param_options(evaluate_representation.PARAMS)
@workspace_option
@output_option
@json_option
def evaluate_representation_cmd(ids, inputs, lpips_weights, face_model, workspace, output, as_json, **kw):
    """Global exponents vs multi-lobe (the paper's Table 1) on held-out flash images; markdown table on stdout.

    Writes an `evaluation` artifact (<ws>/evaluate-representation/evaluate-representation.npz or --output), the
    table (.md) and a figure (.png) beside it.
    """
    if not parse_ids(ids) and not inputs:
        raise click.UsageError("give --ids or --input")
    params = given_params(kw, evaluate_representation.PARAMS)
    inp = default_inputs(evaluate_representation.STAGE, resolve_workspace(workspace), {
        "observations": inputs, "face_model": [face_model], "lpips_weights": [lpips_weights]},
        ids=parse_ids(ids), params=params)
    paths = run_stage_cli(evaluate_representation.VERB, workspace=workspace, params=params, inputs=inp,
                          output=output)
    if as_json:
        art = read_artifact(paths[0], EVAL_KIND)
        emit(paths, True, {"margin": art.meta.get("margin"), "lpips": art.meta.get("lpips")})
    else:
        click.echo(Path(paths[1]).read_text())
        emit(paths)


def method_option(f):
    return click.option("--method", "method_specs", multiple=True, type=str, nargs=3,
                        metavar="NAME MODEL ENCODER",
                        help="A method: its name, reflectance-model artifact and encoder safetensors ('-' = no "
                             "encoder). Repeatable; table rows in this order.")(f)


def _methods(specs) -> tuple[dict, list[str]]:
    from reflectmm_cli.evaluation.methods import method_inputs

    if not specs:
        raise click.UsageError("give at least one --method NAME MODEL ENCODER")
    return method_inputs(specs)


def _without_encoders(inputs: dict, verb: str) -> dict:
    """The method inputs without their encoders, for the verbs that fit coefficients instead (albedo, expressive);
    an encoder given anyway is said to be ignored (it was dropped silently)."""
    given = [k[len("encoder_"):] for k, v in inputs.items() if k.startswith("encoder_") and v]
    if given:
        log.warning("evaluate %s: the encoder of method(s) %s is not used (this evaluation fits each model's "
                    "coefficients; give '-')", verb, ", ".join(given))
    return {k: v for k, v in inputs.items() if not k.startswith("encoder_")}


def _emit_table(paths, as_json):
    art = read_artifact(paths[0], EVAL_KIND)
    if as_json:
        emit(paths, True, {"summary": art.meta.get("summary"), "paper_numbers": art.meta.get("paper_numbers"),
                           "command": art.meta.get("command")})
    else:
        click.echo(art.meta.get("table", ""))
        emit(paths)


@evaluate_group.command("reconstruction")
@click.option("--data", multiple=True, required=True, type=click.Path(dir_okay=False, path_type=Path),
              help="wild-shard artifact (repeatable).")
@click.option("--light-model", required=True, type=click.Path(dir_okay=False, path_type=Path),
              help="light-model artifact the encoders were trained with.")
@method_option
@click.option("--lpips-weights", type=click.Path(dir_okay=False, path_type=Path), default=None,
              help="LPIPS weights (safetensors, docs/evaluation.md). Without them LPIPS is 'off'.")
@param_options(evaluate_reconstruction.PARAMS)
@device_option
@workspace_option
@output_option
@json_option
def evaluate_reconstruction_cmd(data, light_model, method_specs, lpips_weights, device, workspace, output, as_json,
                                **kw):
    """The paper's Table 2: each method's encoder reconstructs the test images of wild shards; face-region PSNR /
    SSIM / LPIPS (mean ± 95 % CI and the released protocol) and per-vertex albedo / Σw errors against the truth.

    Writes an `evaluation` artifact (<ws>/evaluate-reconstruction/evaluate-reconstruction.npz or --output), the
    table (.md) and a side-by-side figure (.png) beside it; the table on stdout.
    """
    inputs, names = _methods(method_specs)
    inputs.update(data=list(data), light_model=[light_model])
    if lpips_weights is not None:
        inputs["lpips_weights"] = [lpips_weights]
    params = given_params(kw, evaluate_reconstruction.PARAMS)
    params["methods"] = names
    paths = run_stage_cli(evaluate_reconstruction.VERB, workspace=workspace, params=params, inputs=inputs,
                          output=output, device=device)
    _emit_table(paths, as_json)


@evaluate_group.command("albedo")
@click.option("--ids", default=None, help="Held-out identities: reads <ws>/unwrap-uv/<id>.npz (uv-observations).")
@click.option("--input", "-i", "obs", multiple=True, type=click.Path(dir_okay=False, path_type=Path),
              help="A held-out identity's uv-observations artifact (repeatable).")
@click.option("--truth", "truth", multiple=True, type=click.Path(exists=True, path_type=Path),
              help="synth-truth <id>.npz files or their folder (default: the workspace's truth folder).")
@method_option
@param_options(evaluate_albedo.PARAMS)
@workspace_option
@output_option
@json_option
def evaluate_albedo_cmd(ids, obs, truth, method_specs, workspace, output, as_json, **kw):
    """The paper's Table 3: each model's coefficients fitted to held-out identities' OLAT observations; diffuse and
    specular albedo PSNR / relative errors against the truth. Encoders are not used (give '-').

    Writes an `evaluation` artifact (<ws>/evaluate-albedo/evaluate-albedo.npz or --output) and the table (.md).
    """
    if not parse_ids(ids) and not obs:
        raise click.UsageError("give --ids or --input")
    found = default_inputs(evaluate_albedo.STAGE, resolve_workspace(workspace), {"observations": obs, "truth": truth},
                           ids=parse_ids(ids))
    inputs, names = _methods(method_specs)
    inputs = _without_encoders(inputs, "albedo")
    inputs.update(found)
    params = given_params(kw, evaluate_albedo.PARAMS)
    params["methods"] = names
    paths = run_stage_cli(evaluate_albedo.VERB, workspace=workspace, params=params, inputs=inputs, output=output)
    _emit_table(paths, as_json)


@evaluate_group.command("expressive")
@click.option("--truth", "truth", type=click.Path(exists=True, file_okay=False, path_type=Path), default=None,
              help="A synth wild folder (manifest.npz, identities/) (default: <ws>/synth-wild).")
@method_option
@param_options(evaluate_expressive.PARAMS)
@workspace_option
@output_option
@json_option
def evaluate_expressive_cmd(truth, method_specs, workspace, output, as_json, **kw):
    """Expressive power (synthetic data): the held-out wild identities' true per-vertex albedo and lobe weights
    projected onto each model (one free scale, the model's prior) and onto an oracle of the same size built from
    the training identities' truth; the gap to the oracle that --gain A,B closes. Encoders are not used (give '-').

    Writes an `evaluation` artifact (<ws>/evaluate-expressive/evaluate-expressive.npz or --output) and its table.
    """
    found = default_inputs(evaluate_expressive.STAGE, resolve_workspace(workspace), {"truth": [truth]})
    inputs, names = _methods(method_specs)
    inputs = _without_encoders(inputs, "expressive")
    inputs.update(found)
    params = given_params(kw, evaluate_expressive.PARAMS)
    params["methods"] = names
    paths = run_stage_cli(evaluate_expressive.VERB, workspace=workspace, params=params, inputs=inputs,
                          output=output)
    _emit_table(paths, as_json)


@evaluate_group.command("relighting")
@click.option("--id", "identity", callback=id_callback, required=True, help="The held-out identity (names the output).")
@click.option("--capture", type=click.Path(dir_okay=False, path_type=Path), default=None,
              help="capture artifact (default <ws>/preprocess-multipie/<id>.npz).")
@click.option("--geometry", type=click.Path(dir_okay=False, path_type=Path), default=None,
              help="geometry artifact (default <ws>/fit-geometry/<id>.npz).")
@click.option("--face-model", type=click.Path(dir_okay=False, path_type=Path), default=None,
              help="Face model (default: the workspace's).")
@click.option("--light-model", type=click.Path(dir_okay=False, path_type=Path), default=None,
              help="light-model artifact the encoders were trained with (needed by methods with an encoder).")
@click.option("--observations", type=click.Path(dir_okay=False, path_type=Path), default=None,
              help="The identity's uv-observations, for methods without an encoder (encoder-free fit).")
@method_option
@param_options(evaluate_relighting.PARAMS)
@device_option
@workspace_option
@output_option
@json_option
def evaluate_relighting_cmd(identity, capture, geometry, face_model, light_model, observations, method_specs, device,
                            workspace, output, as_json, **kw):
    """Relighting (the paper's Figure 7): reconstruct one image of a held-out identity (room light or one flash)
    with each method, re-render under held-out flashes, PSNR / SSIM against the captured OLAT images.

    Writes an `evaluation` artifact (<ws>/evaluate-relighting/<id>.npz or --output), the table (.md) and the figure
    (.png) beside it.
    """
    found = default_inputs(evaluate_relighting.STAGE, resolve_workspace(workspace), {
        "capture": [capture], "geometry": [geometry], "face_model": [face_model], "light_model": [light_model],
        "observations": [observations]}, identity=identity)
    inputs, names = _methods(method_specs)
    inputs.update(found)
    params = given_params(kw, evaluate_relighting.PARAMS)
    params["methods"] = names
    paths = run_stage_cli(evaluate_relighting.VERB, workspace=workspace, identity=identity, params=params,
                          inputs=inputs, output=output, device=device)
    _emit_table(paths, as_json)


@evaluate_group.command("report")
@click.option("--truth-dir", type=click.Path(exists=True, file_okay=False, path_type=Path), default=None,
              help="Folder of synth-truth <id>.npz (default <ws>/truth or <ws>/synth/truth).")
@click.option("--out", "out", type=click.Path(dir_okay=False, path_type=Path), default=None,
              help="Markdown report path (default <ws>/evaluate-report/evaluate-report.md).")
@workspace_option
@json_option
def evaluate_report_cmd(truth_dir, out, workspace, as_json):
    """Closing report of a workspace: per-identity and mean errors against ground truth for every stage that has
    outputs (geometry, reflectance, PCA, Tables 1-3, relighting, finetuning samples), with the PNG previews linked,
    each table with the command that made it, and the paper's numbers beside ours."""
    ws = resolve_workspace(workspace)
    inputs = default_inputs(evaluate_report.STAGE, ws, {"truth": [truth_dir]})
    if not inputs:
        raise ReflectmmError(f"evaluate report: nothing to report in {ws} (no fit-geometry/, fit-reflectance/, "
                             "build-pca/, evaluate-representation/, evaluate-reconstruction/, evaluate-albedo/, "
                             "evaluate-relighting/ or finetune/ outputs)")
    paths = run_stage_cli(evaluate_report.VERB, workspace=workspace, inputs=inputs,
                          output=out)
    emit(paths, as_json)


COMMANDS = [evaluate_group]
