"""Finetuning outputs: the finetuned ``reflectance-model`` artifact (same kind as build-pca's), the encoder
(safetensors + meta), the JSONL log (written during training) and PNG previews (loss curves, 60 model samples
before/after, first 3 components before/after)."""
from __future__ import annotations

import copy
import json
from pathlib import Path

import numpy as np

from reflectmm_cli.errors import ReflectmmError

__all__ = ["finetuned_model", "basis_orthonormality", "loss_curves_png", "vertex_component_grid",
           "write_finetune_outputs", "output_paths"]


def basis_orthonormality(basis: np.ndarray) -> dict:
    """Orthonormality of (M, V, C) bases as flattened vectors: max |⟨b_j,b_k⟩| (j≠k), max |‖b_k‖ − 1|, and
    max |G − I| of the Gram matrix G."""
    B = np.asarray(basis, np.float64).reshape(basis.shape[0], -1)
    G = B @ B.T
    off = G - np.diag(np.diag(G))
    return {"max_abs_offdiag": float(np.abs(off).max()) if len(G) > 1 else 0.0,
            "max_norm_dev": float(np.abs(np.sqrt(np.diag(G)) - 1).max()),
            "max_abs_gram_minus_identity": float(np.abs(G - np.eye(len(G))).max())}


def finetuned_model(initial, vertex_arrays: dict, face_model=None):
    """The finetuned :class:`~reflectmm_cli.model.pca.ReflectanceModel` and a description of what changed.

    The per-vertex parts are the trained ones. The UV maps: with the face model (UVs and triangles) they become
    the initial maps plus the per-vertex *update* interpolated over the UV layout (barycentric, like
    :func:`reflectmm_cli.geometry.vertex_to_uv_map`), so their detail below the mesh resolution is kept and
    sampling them at the vertices returns the finetuned values up to bilinear-lookup error (measured and stored);
    without it the UV maps stay the initial ones and the meta says so (``uv_maps: "initial"``).
    """
    m = copy.deepcopy(initial)
    M = vertex_arrays["vertex_albedo_basis"].shape[0]
    old = {k: np.asarray(getattr(initial, k), np.float32) for k in vertex_arrays}
    info = {"trained_components": int(M)}
    for k, v in vertex_arrays.items():
        full = old[k].copy()
        if k.endswith("_basis"):
            full[:M] = v
        else:
            full = v
        setattr(m, k, full.astype(np.float32))
    if face_model is None:
        info["uv_maps"] = "initial (not updated: no face model to carry the per-vertex update to UV space)"
        return m, info
    from reflectmm_cli.geometry.uv import rasterize_uv, vertex_to_uv_map
    from reflectmm_cli.model.pca import sample_uv_bilinear

    uv, tri = np.asarray(face_model.uv), np.asarray(face_model.triangles)
    if uv.shape[0] != m.vertex_albedo_mean.shape[0]:
        raise ReflectmmError(f"finetune: the face model has {uv.shape[0]} vertices, the reflectance model "
                             f"{m.vertex_albedo_mean.shape[0]}")
    S = initial.size
    r = rasterize_uv(uv, tri, S)
    dom = r.mask & np.asarray(initial.mask, bool)

    def add(uv_map, dvert):  # uv_map (C,S,S); dvert (V,C)
        d = vertex_to_uv_map(dvert, r)
        return (uv_map + np.where(dom[None], d, 0.0)).astype(np.float32)

    m.albedo_mean = add(initial.albedo_mean, m.vertex_albedo_mean - old["vertex_albedo_mean"])
    m.weights_mean = add(initial.weights_mean, m.vertex_weights_mean - old["vertex_weights_mean"])
    m.albedo_basis = np.stack([add(initial.albedo_basis[k], m.vertex_albedo_basis[k] - old["vertex_albedo_basis"][k])
                               for k in range(initial.albedo_basis.shape[0])])
    m.weights_basis = np.stack([add(initial.weights_basis[k],
                                    m.vertex_weights_basis[k] - old["vertex_weights_basis"][k])
                                for k in range(initial.weights_basis.shape[0])])
    back = sample_uv_bilinear(m.albedo_mean, uv) - sample_uv_bilinear(initial.albedo_mean, uv)
    want = m.vertex_albedo_mean - old["vertex_albedo_mean"]
    info["uv_maps"] = "initial + per-vertex update interpolated over the UV layout"
    info["uv_update_roundtrip_rms"] = float(np.sqrt(np.mean((back - want) ** 2)))
    info["vertex_update_rms"] = float(np.sqrt(np.mean(want ** 2)))
    return m, info


def loss_curves_png(history: list, width: int = 720, height: int = 360) -> np.ndarray:
    """(H,W,3) uint8 image: log10 of each loss term per step (thin) and validation totals (dots)."""
    import cv2

    steps = [h for h in history if h.get("type") == "step"]
    vals = [h for h in history if h.get("type") == "val" and "val_total" in h]
    img = np.full((height, width, 3), 255, np.uint8)
    if not steps:
        return img
    keys = [k for k in ("loss", "photo", "per", "coef", "light", "upd", "norm", "ortho") if k in steps[-1]]
    colours = [(0, 0, 0), (217, 51, 26), (128, 26, 153), (26, 128, 26), (230, 153, 0), (26, 77, 230),
               (77, 153, 230), (153, 102, 51)]
    g = np.array([h["global_step"] for h in steps], np.float64)
    def lg(x):  # zero / absent terms (e.g. the priors at step 1, L_upd before phase 2) are not drawn
        x = np.asarray(x, np.float64)
        return np.where(x > 0, np.log10(np.where(x > 0, x, 1.0)), np.nan)

    series = {k: lg([h.get(k, np.nan) for h in steps]) for k in keys}
    allv = np.concatenate([v[np.isfinite(v)] for v in series.values()] +
                          [lg([h["val_total"] for h in vals])] if vals else
                          [v[np.isfinite(v)] for v in series.values()])
    lo, hi = float(allv.min()), float(allv.max())
    hi = hi if hi > lo else lo + 1
    L, R, T, Bm = 60, 130, 20, 30
    X = lambda s: L + (s - g.min()) / max(g.max() - g.min(), 1) * (width - L - R)  # noqa: E731
    Y = lambda v: T + (hi - v) / (hi - lo) * (height - T - Bm)  # noqa: E731
    cv2.rectangle(img, (L, T), (width - R, height - Bm), (153, 153, 153), 1)
    for lv in np.arange(np.floor(lo), np.ceil(hi) + 1):
        if lo <= lv <= hi:
            cv2.putText(img, f"1e{int(lv)}", (4, int(Y(lv)) + 4), cv2.FONT_HERSHEY_PLAIN, 0.9, (77, 77, 77), 1)
    for i, k in enumerate(keys):
        v = series[k]
        pts = np.stack([X(g), Y(v)], -1)[np.isfinite(v)].astype(np.int32)
        if len(pts) > 1:
            cv2.polylines(img, [pts], False, colours[i % len(colours)], 1, cv2.LINE_AA)
        cv2.putText(img, k, (width - R + 8, T + 14 + 16 * i), cv2.FONT_HERSHEY_PLAIN, 1.0, colours[i % len(colours)], 1)
    for h in vals:
        cv2.circle(img, (int(X(h["global_step"])), int(Y(np.log10(max(h["val_total"], 1e-12))))), 3, (0, 0, 0), -1)
    cv2.putText(img, "val (dots)", (width - R + 8, T + 14 + 16 * len(keys)), cv2.FONT_HERSHEY_PLAIN, 1.0, (0, 0, 0), 1)
    p2 = [h["global_step"] for h in steps if h["phase"] == 2]
    if p2:
        x2 = int(X(p2[0]))
        cv2.line(img, (x2, T), (x2, height - Bm), (102, 102, 102), 1)
        cv2.putText(img, "phase 2", (x2 + 3, height - Bm - 5), cv2.FONT_HERSHEY_PLAIN, 0.9, (102, 102, 102), 1)
    cv2.putText(img, "global step", (width // 2 - 40, height - 8), cv2.FONT_HERSHEY_PLAIN, 1.0, (51, 51, 51), 1)
    return img


def vertex_component_grid(model, vertices, triangles, n_components: int = 3, spread: float = 2.0,
                          width: int = 112) -> np.ndarray:
    """Rows: component k; columns: diffuse albedo (sRGB) at −spread·σ, mean, +spread·σ, then lobe weights ×3 at the
    same β — the per-vertex model rendered flat (no shading) on the face model's mean shape."""
    from reflectmm_cli.model.pca import sample_model
    from reflectmm_cli.model.preview import BG, VertexSplat, srgb_preview

    splat = VertexSplat(vertices, triangles, width)
    rows = []
    for k in range(min(n_components, model.n_components)):
        cells_a, cells_w = [], []
        for s in (-spread, 0.0, spread):
            beta = np.zeros(k + 1)
            beta[k] = s
            a, w = sample_model(model, beta, space="vertex")
            wv = w if w.shape[1] == 3 else np.repeat(w.sum(1, keepdims=True), 3, 1)
            for vals, cells, tf in ((a, cells_a, srgb_preview), (np.clip(wv * 3, 0, 1), cells_w, lambda x: x)):
                img = splat.render(vals)
                img = np.where(np.isnan(img), BG, tf(np.nan_to_num(img)))
                cells.append(np.pad(img, ((1, 1), (1, 1), (0, 0)), constant_values=1.0))
        rows.append(np.concatenate(cells_a + cells_w, 1))
    return np.concatenate(rows, 0)


def output_paths(out: Path) -> dict:
    """Every file the finetune stage writes next to its primary output ``out`` (the model artifact)."""
    out = Path(out)
    s = out.stem
    return {"model": out, "encoder": out.with_name(s + "_encoder.safetensors"),
            "encoder_phase1": out.with_name(s + "_encoder_phase1.safetensors"),
            "log": out.with_name(s + "_work") / "log.jsonl", "workdir": out.with_name(s + "_work"),
            "loss_png": out.with_name(s + "_loss.png"), "samples_before": out.with_name(s + "_samples_before.png"),
            "samples_after": out.with_name(s + "_samples_after.png"),
            "components_before": out.with_name(s + "_components_before.png"),
            "components_after": out.with_name(s + "_components_after.png")}


def write_finetune_outputs(result, initial, out: Path, *, face_model=None, inputs=None, params=None, producer=None,
                           cache_key=None, samples: int = 60, seed: int = 0, log=None) -> list[Path]:
    """Write the finetuned model artifact, the encoder and the PNGs; return the paths (model artifact last).

    The files are committed together (:func:`reflectmm_cli.artifacts.committed_together`): if anything fails, no
    output of an earlier run is replaced, so the encoder always pairs with the model beside it.  ``samples`` = 0
    writes no sample PNGs; a preview PNG this run does not write (an earlier run's) is removed after the commit."""
    from reflectmm_cli.artifacts import committed_together

    with committed_together(last=out):
        written = _write_outputs(result, initial, out, face_model=face_model, inputs=inputs, params=params,
                                 producer=producer, cache_key=cache_key, samples=samples, seed=seed, log=log)
    paths = output_paths(out)
    for key in ("samples_before", "samples_after", "components_before", "components_after"):
        if paths[key] not in written:
            paths[key].unlink(missing_ok=True)
    return written


def _write_outputs(result, initial, out: Path, *, face_model, inputs, params, producer, cache_key, samples: int,
                   seed: int, log) -> list[Path]:
    from reflectmm_cli.artifacts import write_artifact, write_png
    from reflectmm_cli.model.pca import MODEL_KIND, model_arrays

    from .encoder import save_encoder

    say = log or (lambda s: None)
    paths = output_paths(out)
    new, info = finetuned_model(initial, result.params.vertex_arrays(), face_model)
    ortho = {"before": basis_orthonormality(initial.vertex_albedo_basis[:result.params.n_components]),
             "after": basis_orthonormality(new.vertex_albedo_basis[:result.params.n_components])}
    M = result.params.n_components
    upd = {}
    for k, v0 in result.initial.items():
        v = getattr(new, k)[:M] if k.endswith("basis") else getattr(new, k)
        upd[k] = float(np.sqrt(np.mean((np.asarray(v, np.float64) - v0) ** 2)))
    written = []
    enc_meta = {"config": result.config.to_dict(), "perceptual": result.perceptual, "steps": result.steps,
                "inputs": inputs or [], "producer": producer or {}, "image_size": result.image_size}
    written.append(save_encoder(result.encoder, paths["encoder"], enc_meta))
    if result.phase1_encoder is not None and result.config.epochs2 > 0:
        # the encoder of the "without finetuning" method: phase 1 only, on the initial (frozen) model
        from reflectmm_cli.artifacts import atomic_write_bytes

        written.append(atomic_write_bytes(paths["encoder_phase1"], Path(result.phase1_encoder).read_bytes()))
    write_png(paths["loss_png"], loss_curves_png(result.history))
    written.append(paths["loss_png"])
    if face_model is not None:
        from reflectmm_cli.model.preview import render_samples

        V, T = np.asarray(face_model.mean_shape), np.asarray(face_model.triangles)
        for tag, mdl in (("before", initial), ("after", new)):
            if samples > 0:
                img, _ = render_samples(mdl, V, T, n=samples, seed=seed, uv=None)
                written.append(write_png(paths[f"samples_{tag}"], img))
            written.append(write_png(paths[f"components_{tag}"], vertex_component_grid(mdl, V, T)))
        if samples <= 0:
            say("finetune: --samples 0: no sample PNGs")
    else:
        say("finetune: no face model (give --face-model or shards whose meta names one): no sample/component PNGs")
    vals = [h for h in result.history if h.get("type") == "val" and "val_total" in h]
    extra = {"finetune": {"variant": result.config.variant, "perceptual": result.perceptual, "steps": result.steps,
                          "n_train": result.n_train, "n_val": result.n_val, "z0": result.z0,
                          "diffuse_basis_orthonormality": ortho, "update_rms": upd, **info,
                          "final_validation": vals[-1] if vals else None,
                          "encoder": paths["encoder"].name, "log": str(paths["log"].relative_to(out.parent)),
                          **({"model_solve": result.stats["model_solve"]} if "model_solve" in result.stats else {})},
             "ids": list(initial.ids), "n_components": int(new.n_components),
             "method": "build-pca model finetuned by update-by-reconstruction (docs/finetune.md)"}
    write_artifact(out, MODEL_KIND, model_arrays(new), params=params or {}, inputs=inputs or [], producer=producer,
                   cache_key=cache_key, extra_meta=json.loads(json.dumps(extra, default=float)))
    written.append(out)
    return written
