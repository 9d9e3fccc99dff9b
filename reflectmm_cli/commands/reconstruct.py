"""``reflectmm reconstruct``: β, γ, z and renders per image with a trained encoder (thin layer over
:func:`reflectmm_cli.finetune.stage.run_reconstruct`)."""
from __future__ import annotations

from pathlib import Path

import click

from reflectmm_cli.commands._common import device_option, emit, json_option, output_option, run_stage_cli, \
    workspace_option
from reflectmm_cli.stages import StageContext, register_stage


def _outputs(ctx: StageContext) -> list[Path]:
    out = ctx.output_path()
    return [out.with_suffix(".png"), out]


@register_stage("reconstruct", version=1, per_identity=False, outputs=_outputs, cache_params=("split", "batch_size"),
                help="reconstruct images with a trained encoder (coefficients, layers, lobe-weight maps)")
def run_reconstruct_stage(ctx: StageContext) -> list[Path]:
    from reflectmm_cli.finetune.stage import run_reconstruct

    out = ctx.output_path()
    return run_reconstruct(ctx.input("encoder"), ctx.input("model"), ctx.input("light_model"), ctx.input_list("data"),
                           out, split=ctx.param("split"), device=ctx.device,
                           batch_size=int(ctx.param("batch_size", 8)), inputs=ctx.input_refs(out.parent),
                           params={"split": ctx.param("split")}, producer=ctx.producer(), cache_key=ctx.cache_key)


@click.command("reconstruct")
@click.option("--encoder", required=True, type=click.Path(dir_okay=False, path_type=Path),
              help="Encoder safetensors written by finetune.")
@click.option("--model", required=True, type=click.Path(dir_okay=False, path_type=Path),
              help="reflectance-model artifact (e.g. the finetuned one).")
@click.option("--light-model", required=True, type=click.Path(dir_okay=False, path_type=Path))
@click.option("--data", multiple=True, required=True, type=click.Path(dir_okay=False, path_type=Path),
              help="wild-shard artifact (repeatable).")
@click.option("--split", type=click.Choice(["train", "val", "test"]), default=None,
              help="Only the images of this split (default: all).")
@click.option("--batch-size", type=int, default=8, show_default=True)
@device_option
@workspace_option
@output_option
@json_option
def reconstruct_cmd(encoder, model, light_model, data, split, batch_size, device, workspace, output, as_json):
    """Reconstruct images: writes a `reconstruction` artifact (<ws>/reconstruct/reconstruct.npz or --output) with
    β, γ, z, SH lighting and full/diffuse/specular/albedo/lobe-weight layers, plus a PNG (one row per image)."""
    inputs = {"encoder": [encoder], "model": [model], "light_model": [light_model], "data": list(data)}
    out = run_stage_cli("reconstruct", workspace=workspace, params={"split": split, "batch_size": batch_size},
                        inputs=inputs, output=output, device=device)
    emit(out, as_json)


COMMANDS = [reconstruct_cmd]
