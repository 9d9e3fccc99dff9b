"""Single-image reconstruction with a trained encoder: β, γ, z per image and its renders (full, diffuse and
specular layers, diffuse albedo, lobe-weight maps) through the same G-buffer shading path as training.
This is what ``evaluate`` uses."""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from reflectmm_cli.errors import ReflectmmError

__all__ = ["Reconstruction", "reconstruct", "reconstruct_truth", "truth_model", "write_reconstruction", "RECONSTRUCTION_KIND", "reconstruction_png",
           "shards_from_images"]

RECONSTRUCTION_KIND = "reconstruction"


@dataclass
class Reconstruction:
    """Per image (N of them, S×S, K lobes): ``names`` (N,); ``beta`` (N,M); ``gamma`` (N,N_L); ``z`` (N,3);
    ``sh`` (N,3,(L+1)²) lighting in the light frame; linear layers ``full``, ``diffuse``, ``specular``, ``albedo``
    (N,S,S,3) and ``weights`` (N,S,S,K), 0 outside ``face_mask`` (N,S,S); ``image`` (N,S,S,3) uint8 input;
    ``encoding`` (N,) how the input is encoded; with refinement ``refine_objective`` (N, 2)."""

    names: np.ndarray
    beta: np.ndarray
    gamma: np.ndarray
    z: np.ndarray
    sh: np.ndarray
    full: np.ndarray
    diffuse: np.ndarray
    specular: np.ndarray
    albedo: np.ndarray
    weights: np.ndarray
    face_mask: np.ndarray
    image: np.ndarray
    encoding: np.ndarray
    refine_objective: np.ndarray | None = None  # (N, 2) E_b before and after refinement (finetune/refine.py)

    def arrays(self) -> dict:
        return {k: getattr(self, k) for k in self.__dataclass_fields__ if getattr(self, k) is not None}


def reconstruct(shards, encoder, model, light, *, indices=None, split: str | None = None, batch_size: int = 8,
                device="cpu", refine=None, n_reflectance: int | None = None, n_light: int | None = None,
                progress_fn=None, verb: str = "reconstruct") -> Reconstruction:
    """Reconstruct the images ``indices`` (or all of ``split``, or all) of ``shards``.

    Args:
        shards: :class:`~reflectmm_cli.finetune.shards.ShardSet`; encoder: from :func:`load_encoder`, or None
            with ``refine`` (then the fit starts from β = γ = 0 and the least-squares light scale z);
        model: the (finetuned) reflectance model; light: the light model the encoder was trained with.
        refine: a :class:`~reflectmm_cli.finetune.refine.RefineConfig` to refine every image's β, γ, z by
            analysis-by-synthesis (the model fixed) after the encoder, or None for the encoder alone.
        n_reflectance, n_light: coefficients fitted without an encoder (default: all of each model).
        progress_fn: wraps the iterable of batches (progress on stderr).
        verb: what an input error begins with (the verb, and for an evaluation the method and its model file).
    """
    import torch

    from .render import ModelParams, batch_gbuffer, lighting, scatter_pixels, shade_gbuffer
    from .train import check_inputs

    check_inputs(shards, model, light, verb=verb)
    if encoder is None and refine is None:
        raise ReflectmmError("reconstruct: give an encoder, or refine the images without one")
    if encoder is not None:
        n_reflectance, n_light = encoder.n_reflectance, encoder.n_light
    n_reflectance = model.n_components if n_reflectance is None else int(n_reflectance)
    n_light = light.n_components if n_light is None else int(n_light)
    if n_reflectance > model.n_components or n_light > light.n_components:
        raise ReflectmmError(f"reconstruct: {'the encoder predicts ' if encoder is not None else ''}"
                             f"{n_reflectance} reflectance / {n_light} light coefficients, the models have "
                             f"{model.n_components} / {light.n_components}")
    idx = (np.arange(len(shards)) if indices is None and split is None else
           shards.indices(split) if indices is None else np.asarray(indices, np.int64))
    if len(idx) == 0:
        raise ReflectmmError(f"reconstruct: no images{'' if split is None else f' in split {split!r}'}")
    params = ModelParams(model, device, n_components=n_reflectance)
    out = {k: [] for k in ("beta", "gamma", "z", "sh", "full", "diffuse", "specular", "albedo", "weights")}
    objective = []
    if encoder is not None:
        encoder.eval()
    starts = range(0, len(idx), batch_size)
    with torch.no_grad():
        for s0 in (progress_fn(starts) if progress_fn is not None else starts):
            ib = idx[s0:s0 + batch_size]
            b = shards.batch(ib, with_target=refine is not None)
            gb = batch_gbuffer(b, device)
            if encoder is not None:
                x = torch.as_tensor(b["images"], device=device).permute(0, 3, 1, 2).float() / 255.0
                beta, gamma, z = encoder(x)
            if refine is not None:
                from .refine import initial_z, refine_batch

                if encoder is None:
                    beta = gb.bary.new_zeros((len(ib), n_reflectance))
                    gamma = gb.bary.new_zeros((len(ib), n_light))
                    z = initial_z(params, light, gb, gamma)
                res = refine_batch(params, light, gb, beta, gamma, z, refine,
                                   names=[str(n) for n in shards.names[ib]])
                beta, gamma, z = res.beta, res.gamma, res.z
                objective.append(np.stack([res.objective_start, res.objective_end], 1))
            sh = lighting(light, gamma, z)
            d, s, a, w = shade_gbuffer(params, beta, sh, gb)
            for k, v in (("beta", beta), ("gamma", gamma), ("z", z), ("sh", sh)):
                out[k].append(v.cpu().numpy())
            for k, v in (("full", d + s), ("diffuse", d), ("specular", s), ("albedo", a), ("weights", w)):
                out[k].append(scatter_pixels(v, gb).cpu().numpy())
    cat = {k: np.concatenate(v).astype(np.float32) for k, v in out.items()}
    return Reconstruction(names=shards.names[idx], face_mask=shards.face_mask[idx], image=shards.image[idx],
                          encoding=shards.encoding[idx],
                          refine_objective=np.concatenate(objective) if objective else None, **cat)


def truth_model(albedo, weights, exponents) -> dict:
    """A reflectance "model" with no components whose mean is one image's true per-vertex reflectance:
    ``albedo`` (V,3), ``weights`` (V,K) — what the ceiling of a refinement is measured with."""
    a = np.asarray(albedo, np.float32)
    w = np.asarray(weights, np.float32)
    if a.ndim != 2 or a.shape[1] != 3 or w.ndim != 2 or w.shape[0] != a.shape[0]:
        raise ReflectmmError(f"reconstruct: true reflectance must be (V,3) and (V,K), got {a.shape} and {w.shape}")
    return {"vertex_albedo_mean": a, "vertex_albedo_basis": np.zeros((0,) + a.shape, np.float32),
            "vertex_weights_mean": w, "vertex_weights_basis": np.zeros((0,) + w.shape, np.float32),
            "sigma": np.zeros(0, np.float32), "exponents": np.asarray(exponents, np.float64)}


def reconstruct_truth(shards, light, exponents, refine, *, indices=None, split: str | None = None,
                      n_light: int | None = None, device="cpu", progress_fn=None) -> Reconstruction:
    """The ceiling of a refinement (synthetic data): every image refined with its *true* per-vertex diffuse albedo
    and lobe weights (the shard's ``truth_vertex_albedo``/``truth_vertex_weights``) in place of the model; only the
    light (γ, z) is fitted. The remaining error is what no reflectance model can remove (light-model span, shading
    approximation, shadows, noise), so that (model's refined PSNR) / (this PSNR) says how much is the model's fault.
    """
    import torch

    from .refine import initial_z, refine_batch
    from .render import ModelParams, batch_gbuffer, lighting, scatter_pixels, shade_gbuffer

    if "truth_vertex_albedo" not in shards.truth or "truth_vertex_weights" not in shards.truth:
        raise ReflectmmError("reconstruct: the shards hold no true per-vertex reflectance (synthetic data only)")
    idx = (np.arange(len(shards)) if indices is None and split is None else
           shards.indices(split) if indices is None else np.asarray(indices, np.int64))
    n_light = light.n_components if n_light is None else int(n_light)
    out = {k: [] for k in ("beta", "gamma", "z", "sh", "full", "diffuse", "specular", "albedo", "weights")}
    objective = []
    with torch.no_grad():
        for i in (progress_fn(idx) if progress_fn is not None else idx):
            params = ModelParams(truth_model(shards.truth["truth_vertex_albedo"][i],
                                             shards.truth["truth_vertex_weights"][i], exponents), device)
            gb = batch_gbuffer(shards.batch([i]), device)
            gamma = gb.bary.new_zeros((1, n_light))
            beta = gb.bary.new_zeros((1, 0))
            res = refine_batch(params, light, gb, beta, gamma, initial_z(params, light, gb, gamma), refine,
                               names=[str(shards.names[i])])
            sh = lighting(light, res.gamma, res.z)
            d, s, a, w = shade_gbuffer(params, res.beta, sh, gb)
            objective.append(np.stack([res.objective_start, res.objective_end], 1))
            for k, v in (("beta", res.beta), ("gamma", res.gamma), ("z", res.z), ("sh", sh)):
                out[k].append(v.cpu().numpy())
            for k, v in (("full", d + s), ("diffuse", d), ("specular", s), ("albedo", a), ("weights", w)):
                out[k].append(scatter_pixels(v, gb).cpu().numpy())
    cat = {k: np.concatenate(v).astype(np.float32) for k, v in out.items()}
    return Reconstruction(names=shards.names[idx], face_mask=shards.face_mask[idx], image=shards.image[idx],
                          encoding=shards.encoding[idx], refine_objective=np.concatenate(objective), **cat)


def shards_from_images(images_dir, face_model, config=None, *, landmarks_dir=None, masks_dir=None,
                       progress_fn=None):
    """In-memory G-buffers of raw photos, for :func:`reconstruct`: prepare-wild's library (alignment to the
    Deep3DFaceRecon crop, single-image geometry fit, G-buffer, skin mask —
    :func:`reflectmm_cli.finetune.data.prepare_wild_images`) without writing a shard.

    Args:
        images_dir: folder of images; landmarks ``<stem>.pts|.txt|.npy`` in ``landmarks_dir`` (default: the images
            folder, then a sibling ``landmarks/``); optional CelebAMask-HQ label images in ``masks_dir``.
        face_model: the :class:`~reflectmm_cli.geometry.face_model.FaceModel` the reflectance model's vertices
            belong to; config: :class:`~reflectmm_cli.finetune.data.PrepareConfig` (crop size, ``aligned``,
            ``encoding``, fit iterations).
    Returns:
        ``(ShardSet, errors)``: the images that could be prepared, and one line per skipped image (naming its file).
    """
    from .data import PrepareConfig, list_wild_inputs, prepare_wild_images
    from .shards import shardset_from_arrays

    cfg = config or PrepareConfig()
    inputs = list_wild_inputs(images_dir, landmarks_dir, masks_dir)
    arrays, _, errors = prepare_wild_images(inputs, face_model, cfg, progress_fn=progress_fn)
    if not arrays:
        raise ReflectmmError(f"reconstruct: no image of {images_dir} could be prepared ({errors[0]})")
    return shardset_from_arrays(arrays, encoding=cfg.encoding), errors


def reconstruction_png(rec: Reconstruction, i: int) -> np.ndarray:
    """One row for image i (paper Fig. 4 style): input | reconstruction | diffuse | specular | albedo |
    lobe weights ×3 (RGB = lobes 1, 2, 3) — sRGB display, grey background outside the face."""
    from reflectmm_cli.model.preview import BG, srgb_preview

    from .data import linearize

    m = rec.face_mask[i][..., None]
    inp = srgb_preview(linearize(rec.image[i], str(rec.encoding[i])))
    w = rec.weights[i]
    wv = w[..., :3] if w.shape[-1] >= 3 else np.repeat(w.sum(-1, keepdims=True), 3, -1)
    cells = [inp, np.where(m, srgb_preview(rec.full[i]), inp)]
    cells += [np.where(m, srgb_preview(rec.diffuse[i]), BG), np.where(m, srgb_preview(rec.specular[i]), BG),
              np.where(m, srgb_preview(rec.albedo[i]), BG), np.where(m, np.clip(wv * 3, 0, 1), BG)]
    return np.concatenate([np.pad(c, ((1, 1), (1, 1), (0, 0)), constant_values=1.0) for c in cells], 1)


def write_reconstruction(rec: Reconstruction, out: Path, *, png_rows: int = 16, inputs=None, params=None,
                         producer=None, cache_key=None, extra_meta=None) -> list[Path]:
    """The ``reconstruction`` artifact (all arrays, float16 images) and a PNG of the first ``png_rows`` images."""
    from reflectmm_cli.artifacts import write_artifact, write_png

    out = Path(out)
    arrays = rec.arrays()
    for k in ("full", "diffuse", "specular", "albedo", "weights"):
        arrays[k] = arrays[k].astype(np.float16)
    png = out.with_suffix(".png")
    n = min(png_rows, len(rec.names))
    write_png(png, np.concatenate([reconstruction_png(rec, i) for i in range(n)], 0))
    write_artifact(out, RECONSTRUCTION_KIND, arrays, params=params or {}, inputs=inputs or [], producer=producer,
                   cache_key=cache_key, extra_meta={"columns_png": ["input", "reconstruction", "diffuse", "specular",
                                                                    "albedo", "lobe weights x3"], **(extra_meta or {})})
    return [png, out]
