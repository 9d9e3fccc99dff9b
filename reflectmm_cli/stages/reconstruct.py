"""Stage ``reconstruct``: β, γ, z per image with a trained encoder, and the renders (full, diffuse, specular,
albedo, lobe weights ×3) through the G-buffer shading path of training (docs/finetune.md).

Inputs (roles): ``encoder`` (finetune's ``*_encoder.safetensors``; not needed with
``--refine --refine-from zero``), ``model`` (the reflectance model, e.g. the
finetuned one), ``light_model``, and either ``data`` (``wild-shard`` files or folders) or ``images`` (a folder of
raw photos) with optional ``landmarks`` and ``masks`` folders and the ``face_model`` (default:
:func:`reflectmm_cli.workspace.find_face_model`) — prepared in memory with prepare-wild's library
(:func:`reflectmm_cli.finetune.reconstruct.shards_from_images`), then the same reconstruction.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path

from reflectmm_cli.errors import ReflectmmError, WrittenThenFailed
from reflectmm_cli.params import Param
from reflectmm_cli.progress import log, progress
from reflectmm_cli.stages.base import Default, Input, Stage, StageContext

VERB = "reconstruct"

_KINDS = {"int": "int", "float": "float", "str": "str"}

#: The stage's input roles (checked in recipes and on the command line; shown in --help).
INPUTS = (
    Input('model', 'reflectance-model', upstream='finetune', default=Default()),
    Input('encoder', 'finetune-encoder', upstream='finetune', default=Default(name='finetune_encoder', suffix='.safetensors')),
    Input('light_model', 'light-model', upstream='build-light-pca', default=Default()),
    Input('data', 'wild-shard', upstream='prepare-wild', many=True),
    Input('images', 'photos', many=True),
    Input('landmarks', 'landmark folder', upstream='detect-landmarks',
          help='--images: <stem>.pts/.txt/.npy (default: the images folder, then ../landmarks)'),
    Input('masks', 'face-parsing label folder', help='--images: CelebAMask-HQ label images <stem>.png'),
    Input('face_model', 'face-model artifact or BFM .mat', upstream='synth-multipie', help='the mesh and its UVs',
          default=Default('face-model', missing='--images needs --face-model (no face model found in the workspace)')),
)


def refine_params(prefix: str = "refine_") -> tuple[Param, ...]:
    """The ``refine`` switch, the start (``encoder`` or ``zero``) and one :class:`Param` per
    :class:`~reflectmm_cli.finetune.refine.RefineConfig` field (``refine_<field>``), from the field metadata; shared by
    every stage that reconstructs (reconstruct, evaluate reconstruction, evaluate relighting)."""
    from reflectmm_cli.finetune.refine import RefineConfig

    out = [Param("refine", "bool", False, help="Refine every image's beta, gamma, z by analysis-by-synthesis "
                                               "(Levenberg-Marquardt, the model fixed) after the encoder."),
           Param("refine_from", "str", "encoder", choices=("encoder", "zero"),
                 help="Start of the refinement: the encoder's prediction, or zero coefficients (no encoder).")]
    for f in dataclasses.fields(RefineConfig):
        md = f.metadata
        kind = _KINDS[str(f.type)]
        rng = md.get("range") or ((0.0, None) if kind == "float" else None)
        out.append(Param(prefix + f.name, kind, f.default, range=rng, choices=md.get("choices"), help=md["help"]))
    return tuple(out)


def refine_config(params, prefix: str = "refine_"):
    """The :class:`~reflectmm_cli.finetune.refine.RefineConfig` of resolved stage parameters, or None without
    ``refine``."""
    from reflectmm_cli.finetune.refine import RefineConfig

    if not params.get("refine"):
        return None
    return RefineConfig(**{f.name: params[prefix + f.name] for f in dataclasses.fields(RefineConfig)})


PARAMS = (
    Param("split", "str", None, choices=("train", "val", "test"), help="Only the images of this split (default: all)."),
    Param("batch_size", "int", 8, range=(1, 4096), help="Images per encoder pass."),
    Param("size", "int", 224, range=(32, 1024), unit="px",
          help="--images: side of the aligned crop (the size the encoder was trained at)."),
    Param("aligned", "bool", False, help="--images: the images are already aligned crops (landmarks in crop pixels)."),
    Param("encoding", "str", "srgb", choices=("srgb", "gamma1.2", "linear"),
          help="--images: how the images are encoded (linearised with it)."),
    Param("allow_skipped", "bool", False,
          help="--images: exit 0 when some images could not be prepared (they are reported either way)."),
    Param("allow_other_model", "bool", False, invalidates_cache=False,
          help="Use an encoder with a model it was not trained for (a warning instead of an error)."),
) + refine_params()


def _outputs(ctx: StageContext) -> list[Path]:
    out = ctx.output_path()
    return [out, out.with_suffix(".png")]


def run(ctx: StageContext) -> list[Path]:
    import numpy as np

    from reflectmm_cli.finetune.data import PrepareConfig
    from reflectmm_cli.finetune.encoder import load_encoder
    from reflectmm_cli.finetune.reconstruct import reconstruct, shards_from_images, write_reconstruction
    from reflectmm_cli.finetune.shards import load_shards
    from reflectmm_cli.finetune.train import load_models
    from reflectmm_cli.geometry.face_model import load_face_model
    from reflectmm_cli.stages.finetune import data_paths
    from reflectmm_cli.workspace import find_face_model

    p = ctx.params
    out = ctx.output_path()
    model, light = load_models(ctx.input("model"), ctx.input("light_model"))
    images = ctx.input_list("images", required=False)
    data = ctx.input_list("data", required=False)
    if bool(images) == bool(data):
        raise ReflectmmError("reconstruct: give either shards (--data) or a folder of images (--images)")
    errors: list[str] = []
    if images:
        fm_path = (ctx.input_list("face_model", required=False) or [find_face_model(ctx.workspace)])[0]
        if fm_path is None:
            raise ReflectmmError("reconstruct --images needs the face model (--face-model; none found in the "
                                 "workspace)")
        one = lambda role: (ctx.input_list(role, required=False) or [None])[0]  # noqa: E731
        cfg = PrepareConfig(size=p["size"], aligned=p["aligned"], encoding=p["encoding"])
        shards, errors = shards_from_images(ctx.input("images"), load_face_model(fm_path), cfg,
                                            landmarks_dir=one("landmarks"), masks_dir=one("masks"),
                                            progress_fn=lambda it: progress(it, desc="prepare", unit="image"))
        for e in errors:
            log.warning(f"reconstruct: skipped: {e}")
    else:
        shards = load_shards(data_paths(data))
    refine = refine_config(p)
    if refine is not None and p["refine_from"] == "zero":
        enc = None
    else:
        enc, emeta = load_encoder(ctx.input("encoder"), ctx.device, model=ctx.input("model"),
                                  allow_other_model=p["allow_other_model"])
        trained = emeta.get("image_size")
        if trained is not None and int(trained) != int(shards.size):
            log.warning(f"reconstruct: warning: the encoder was trained on {trained}² images, these are "
                        f"{shards.size}² (--size); its predictions are unreliable at another scale")
    rec = reconstruct(shards, enc, model, light, split=p.get("split"), batch_size=p["batch_size"],
                      device=ctx.device, refine=refine,
                      progress_fn=(lambda it: progress(it, desc="refine", unit="batch")) if refine else None)
    if refine is not None:
        e = rec.refine_objective
        log.info(f"reconstruct: refined {len(e)} image(s); objective {float(np.median(e[:, 0])):.3g} -> "
                 f"{float(np.median(e[:, 1])):.3g} (median)")
    paths = write_reconstruction(rec, out, inputs=ctx.input_refs(out.parent), params=ctx.resolved_params(),
                                 producer=ctx.producer(), cache_key=ctx.cache_key,
                                 extra_meta={"skipped": errors} if images else None)
    if errors and not p["allow_skipped"]:
        raise WrittenThenFailed(f"reconstruct: {len(errors)} image(s) skipped (listed above; the others are written "
                                f"to {out}; --allow-skipped to accept)")
    return paths


STAGE = Stage(VERB, version=1, run=run, per_identity=False, outputs=_outputs, params=PARAMS,
              help="reconstruct images with a trained encoder (coefficients, layers, lobe-weight maps)", inputs=INPUTS)
