"""Library side of the ``finetune`` and ``reconstruct`` stages: read the inputs, run, write the outputs.

``run_finetune(model_path, light_path, data_paths, config, out, ...)`` and ``run_reconstruct(...)`` are what a
thin command or recipe stage calls (config → function → outputs).
"""
from __future__ import annotations

from pathlib import Path

from reflectmm_cli.errors import ReflectmmError

__all__ = ["load_models", "find_face_model", "run_finetune", "run_reconstruct"]


def load_models(model_path, light_path):
    """(ReflectanceModel, LightModel) from their artifacts."""
    from reflectmm_cli.artifacts import read_artifact
    from reflectmm_cli.model.pca import MODEL_KIND, model_from_arrays
    from reflectmm_cli.model.light import LIGHT_MODEL_KIND, light_model_from_arrays

    art = read_artifact(model_path, MODEL_KIND)
    model = model_from_arrays(art.arrays, art.meta.get("stats"))
    light = light_model_from_arrays(read_artifact(light_path, LIGHT_MODEL_KIND).arrays)
    return model, light


def find_face_model(explicit, shards):
    """The face model to render previews with: the explicit path, else the one the shards' meta names (if it
    exists), else None."""
    from reflectmm_cli.geometry.face_model import load_face_model

    if explicit:
        return load_face_model(explicit)
    fm = shards.face_model or {}
    p = fm.get("resolved")
    if p and Path(p).is_file():
        return load_face_model(p)
    return None


def run_finetune(model_path, light_path, data_paths, config, out: Path, *, face_model_path=None,
                 identity_weights=None, init_weights=None, resume=False, device="cpu", threads=None, samples=60,
                 inputs=None, params=None, producer=None, cache_key=None, log=None) -> list[Path]:
    """Read → :func:`~reflectmm_cli.finetune.train.finetune` → :func:`~reflectmm_cli.finetune.outputs.
    write_finetune_outputs`. The checkpoint and the JSONL log live in ``<out stem>_work/``."""
    from .identity import load_identity_net
    from .outputs import output_paths, write_finetune_outputs
    from .shards import load_shards
    from .train import finetune

    say = log or (lambda s: None)
    model, light = load_models(model_path, light_path)
    shards = load_shards(data_paths)
    identity = None
    if identity_weights:
        identity = load_identity_net(identity_weights, device)
        say(f"finetune: perceptual loss on ({identity.name} from {Path(identity_weights).name})")
    else:
        say("finetune: perceptual loss off (no --identity-weights given)")
    fm = find_face_model(face_model_path, shards)
    paths = output_paths(out)
    res = finetune(shards, model, light, config, paths["workdir"], device=device, identity=identity,
                   init_weights=init_weights, resume=resume, log=say, threads=threads)
    return write_finetune_outputs(res, model, Path(out), face_model=fm, inputs=inputs, params=params,
                                  producer=producer, cache_key=cache_key, samples=samples, seed=config.seed, log=say)


def run_reconstruct(encoder_path, model_path, light_path, data_paths, out: Path, *, split=None, device="cpu",
                    batch_size=8, inputs=None, params=None, producer=None, cache_key=None) -> list[Path]:
    from .encoder import load_encoder
    from .reconstruct import reconstruct, write_reconstruction
    from .shards import load_shards

    model, light = load_models(model_path, light_path)
    shards = load_shards(data_paths)
    enc, meta = load_encoder(encoder_path, device)
    if split is not None and split not in ("train", "val", "test"):
        raise ReflectmmError(f"reconstruct: --split must be train, val or test, got {split!r}")
    rec = reconstruct(shards, enc, model, light, split=split, batch_size=batch_size, device=device)
    return write_reconstruction(rec, out, inputs=inputs, params=params, producer=producer, cache_key=cache_key)
