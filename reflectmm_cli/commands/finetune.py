"""``reflectmm finetune``: update-by-reconstruction of the reflectance model on in-the-wild shards (DESIGN.md §7).

Thin layer over :func:`reflectmm_cli.finetune.stage.run_finetune`; every hyper-parameter is declared once in
:class:`reflectmm_cli.finetune.config.FinetuneConfig`.
"""
from __future__ import annotations

import dataclasses
from pathlib import Path

import click

from reflectmm_cli.commands._common import device_option, emit, json_option, output_option, run_stage_cli, \
    workspace_option
from reflectmm_cli.finetune.config import ARCHS, FinetuneConfig
from reflectmm_cli.progress import log
from reflectmm_cli.stages import StageContext, register_stage

_CONFIG_KEYS = tuple(f.name for f in dataclasses.fields(FinetuneConfig) if f.name != "extra")


def _config(params: dict) -> FinetuneConfig:
    given = {k: params[k] for k in _CONFIG_KEYS if params.get(k) is not None and k != "variant"}
    if "betas" in given:
        given["betas"] = tuple(given["betas"])
    if params.get("variant", "paper") == "released":
        return FinetuneConfig.released(**given)
    return FinetuneConfig(**given)


def _outputs(ctx: StageContext) -> list[Path]:
    from reflectmm_cli.finetune.outputs import output_paths

    p = output_paths(ctx.output_path())
    return [p["encoder"], p["loss_png"], p["model"]]


@register_stage("finetune", version=1, per_identity=False, outputs=_outputs,
                cache_params=_CONFIG_KEYS + ("samples",),
                help="finetune the reflectance model on in-the-wild shards (update-by-reconstruction)")
def run_finetune_stage(ctx: StageContext) -> list[Path]:
    from reflectmm_cli.finetune.stage import run_finetune

    cfg = _config(ctx.params)
    out = ctx.output_path()
    one = lambda role: (ctx.input_list(role, required=False) or [None])[0]  # noqa: E731
    return run_finetune(ctx.input("model"), ctx.input("light_model"), ctx.input_list("data"), cfg, out,
                        face_model_path=one("face_model"), identity_weights=one("identity_weights"),
                        init_weights=one("init_weights"), resume=bool(ctx.param("resume", False)),
                        device=ctx.device, threads=ctx.param("threads"), samples=int(ctx.param("samples", 60)),
                        inputs=ctx.input_refs(out.parent), params=cfg.to_dict(), producer=ctx.producer(),
                        cache_key=ctx.cache_key, log=log.info)


@click.command("finetune")
@click.option("--model", "model", required=True, type=click.Path(dir_okay=False, path_type=Path),
              help="Initial reflectance-model artifact (build-pca, with its per-vertex part).")
@click.option("--light-model", required=True, type=click.Path(dir_okay=False, path_type=Path),
              help="light-model artifact (build-light-pca).")
@click.option("--data", multiple=True, required=True, type=click.Path(dir_okay=False, path_type=Path),
              help="wild-shard artifact (repeatable).")
@click.option("--face-model", type=click.Path(dir_okay=False, path_type=Path), default=None,
              help="face model for the PNG previews and the UV-map update (default: the one the shards name).")
@click.option("--variant", type=click.Choice(["paper", "released"]), default="paper", show_default=True,
              help="Defaults of the paper or of the released training code (docs/finetune.md).")
@click.option("--arch", type=click.Choice(ARCHS), default=None, help="Encoder (default resnet50).")
@click.option("--width", type=int, default=None, help="Channels of the first ResNet stage (default 64).")
@click.option("--epochs1", type=int, default=None, help="Phase-1 epochs (encoder only; default 20).")
@click.option("--epochs2", type=int, default=None, help="Phase-2 epochs (encoder + model; default 2).")
@click.option("--lr1", type=float, default=None, help="Phase-1 learning rate (default 1e-4).")
@click.option("--lr2", type=float, default=None, help="Phase-2 encoder learning rate (default 1e-5).")
@click.option("--model-lr", type=float, default=None, help="Phase-2 model learning rate (default 1e-5).")
@click.option("--batch-size", type=int, default=None, help="Images per step (default 8).")
@click.option("--seed", type=int, default=None, help="Seed (default 0).")
@click.option("--w-photo", type=float, default=None, help="Photometric weight (default 2).")
@click.option("--w-per", type=float, default=None, help="Perceptual (identity) weight (default 0.1).")
@click.option("--w-coef", type=float, default=None, help="Coefficient prior weight (default 0.001).")
@click.option("--w-upd", type=float, default=None, help="Model-update weight (default 10).")
@click.option("--w-light", type=float, default=None, help="Monochrome-light weight (default 10).")
@click.option("--components", "n_reflectance", type=int, default=None, help="N_R (default: all of the model).")
@click.option("--light-components", "n_light", type=int, default=None, help="N_L (default: all of the light model).")
@click.option("--checkpoint-every", type=int, default=None, help="Steps between checkpoints (default 500).")
@click.option("--identity-weights", type=click.Path(dir_okay=False, path_type=Path), default=None,
              help="ArcFace iresnet safetensors (insightface key names) for L_per; without it L_per is off.")
@click.option("--init-weights", type=click.Path(dir_okay=False, path_type=Path), default=None,
              help="ImageNet ResNet trunk as safetensors with torchvision key names.")
@click.option("--resume", is_flag=True, help="Continue from the checkpoint in <output stem>_work/.")
@click.option("--threads", type=int, default=None, help="torch CPU threads (default: torch's).")
@click.option("--samples", type=int, default=60, show_default=True, help="Model samples in the before/after PNGs.")
@device_option
@workspace_option
@output_option
@json_option
def finetune_cmd(model, light_model, data, face_model, variant, identity_weights, init_weights, resume, threads,
                 samples, device, workspace, output, as_json, **opts):
    """Finetune the reflectance model and train the reconstruction encoder on wild-shard data.

    Writes the finetuned reflectance-model artifact (<ws>/finetune/finetune.npz or --output), the encoder
    (finetune_encoder.safetensors), the checkpoint and JSONL log (finetune_work/), and PNGs (loss curves, samples
    and components before/after).
    """
    inputs = {"model": [model], "light_model": [light_model], "data": list(data)}
    for role, p in (("face_model", face_model), ("identity_weights", identity_weights),
                    ("init_weights", init_weights)):
        if p is not None:
            inputs[role] = [p]
    params = {k: v for k, v in opts.items() if v is not None}
    params.update(variant=variant, resume=resume, threads=threads, samples=samples)
    out = run_stage_cli("finetune", workspace=workspace, params=params, inputs=inputs, output=output, device=device)
    emit(out, as_json)


COMMANDS = [finetune_cmd]
