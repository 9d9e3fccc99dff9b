"""What the evaluate stages read and run before :mod:`reflectmm_cli.evaluation.tables` computes: artifacts
(reflectance models, light model, uv-observations, synth truth, capture, geometry, wild shards) and the
methods' predictions (each encoder's reconstruction, the per-image refinement, the truth ceiling, the
encoder-free coefficient fit). Shared by evaluate-albedo, evaluate-reconstruction, evaluate-relighting and
evaluate-expressive; not a stage itself.

The predictions are generators: one method is loaded, run and handed to the evaluation before the next one
is loaded, so a method's arrays are dropped before the next method runs (as when one function did both), and
the log lines and errors come in the same order.
"""
from __future__ import annotations

from pathlib import Path
from typing import Any, Callable, Iterator, Sequence

import numpy as np

from reflectmm_cli.errors import ReflectmmError
from reflectmm_cli.evaluation.methods import Method
from reflectmm_cli.evaluation.tables import Prediction, Reflectance

__all__ = ["load_model", "load_light_model", "identity_of", "truth_by_identity", "albedo_inputs",
           "select_wild_images", "shard_arrays", "reconstruction_predictions", "relighting_inputs", "input_crop",
           "relighting_reflectances"]


def load_model(path: Path):
    """:class:`reflectmm_cli.model.ReflectanceModel` of a ``reflectance-model`` artifact."""
    from reflectmm_cli.artifacts import read_artifact
    from reflectmm_cli.model.pca import MODEL_KIND, model_from_arrays

    art = read_artifact(path, MODEL_KIND)
    return model_from_arrays(art.arrays, art.meta.get("stats"), path=path)


def load_light_model(path: Path):
    """The light PCA of a ``light-model`` artifact."""
    from reflectmm_cli.artifacts import read_artifact
    from reflectmm_cli.model.light import LIGHT_MODEL_KIND, light_model_from_arrays

    return light_model_from_arrays(read_artifact(path, LIGHT_MODEL_KIND).arrays)


def identity_of(path: Path) -> str:
    """The identity an artifact is about: its meta ``identity``, else the file stem."""
    from reflectmm_cli.artifacts import read_meta

    return str(read_meta(path).get("identity") or Path(path).stem)


def truth_by_identity(paths: Sequence[Path]) -> dict[str, Path]:
    """``<id>.npz`` truth files (given directly or as folders) by identity (file stem)."""
    out: dict[str, Path] = {}
    for p in paths:
        p = Path(p)
        files = sorted(q for q in p.glob("*.npz") if not q.name.startswith(".")) if p.is_dir() else [p]
        for q in files:
            out[q.stem] = q
    return out


# --------------------------------------------------------------------------- Table 3

def albedo_inputs(methods: Sequence[Method], observations: Sequence[Path], truth: Sequence[Path]
                  ) -> tuple[dict[str, Any], dict[str, tuple]]:
    """The models of ``methods`` by name and ``{identity: (uv-observations arrays, truth arrays)}`` for
    :func:`reflectmm_cli.evaluation.tables.albedo_evaluation`. ``truth``: synth-truth files or folders, matched
    by identity; every model must have the observations' UV size."""
    from reflectmm_cli.artifacts import artifact_identity, read_artifact

    if not observations:
        raise ReflectmmError("evaluate albedo: no uv-observations given (input 'observations')")
    truths = truth_by_identity(truth)
    idents: dict[str, tuple] = {}
    for p in observations:
        iid = identity_of(p)
        if iid not in truths:
            raise ReflectmmError(f"evaluate albedo: no truth file for identity '{iid}' (looked for {iid}.npz in the "
                                 "truth input)", p)
        if iid in idents:
            raise ReflectmmError(f"evaluate albedo: identity '{iid}' given twice", p)
        obs = read_artifact(p, "uv-observations").arrays
        tart = read_artifact(truths[iid], "synth-truth")
        told = artifact_identity(tart) or iid
        if told != iid:  # matched by file name: a renamed truth file would score another identity's fit
            raise ReflectmmError(f"evaluate albedo: is identity {told}'s truth, but {p} holds identity {iid}'s "
                                 "observations", truths[iid])
        tr = tart.arrays
        for k in ("albedo", "spec_albedo"):
            if k not in tr:
                raise ReflectmmError(f"evaluate albedo: truth has no '{k}' array (a synth multipie truth file is "
                                     "needed)", truths[iid])
        idents[iid] = (obs, {k: np.asarray(tr[k]) for k in ("albedo", "spec_albedo", "uv_mask") if k in tr})
    models = {}
    for m in methods:
        model = load_model(m.model)
        S_obs = int(np.asarray(next(iter(idents.values()))[0]["mask"]).shape[-1])
        if model.albedo_mean.shape[-1] != S_obs:
            raise ReflectmmError(f"evaluate albedo: model '{m.name}' has UV size {model.albedo_mean.shape[-1]}, the "
                                 f"observations {S_obs} (build the models at the observations' UV size)", m.model)
        models[m.name] = model
    return models, idents


# --------------------------------------------------------------------------- Table 2

def select_wild_images(data: Sequence[Path], split: str = "test", max_images: int = 0):
    """The wild shards ``data`` (a ShardSet), the indices of their ``split`` images (``all``: every image; the
    first ``max_images`` when > 0) and the one encoding those images share."""
    from reflectmm_cli.finetune.shards import load_shards

    shards = load_shards(list(data))
    idx = np.arange(len(shards)) if split == "all" else shards.indices(split)
    if max_images > 0:
        idx = idx[:max_images]
    if len(idx) == 0:
        raise ReflectmmError(f"evaluate reconstruction: no images of split '{split}' in the shards "
                             f"({', '.join(str(p) for p in data)})")
    encs = sorted({str(e) for e in shards.encoding[idx]})
    if len(encs) != 1:
        raise ReflectmmError(f"evaluate reconstruction: the selected images mix encodings {', '.join(encs)}")
    return shards, idx, encs[0]


def shard_arrays(shards) -> dict[str, np.ndarray]:
    """The arrays :func:`reflectmm_cli.evaluation.reconstruction_eval.evaluate_reconstruction` reads, from a
    ShardSet. The truth's specular albedo is ``truth_vertex_spec_albedo`` (N,V) when present, else Σ of
    ``truth_vertex_weights``."""
    arr = {"image": shards.image, "face_mask": shards.face_mask, "skin_mask": shards.skin_mask,
           "pix_offset": shards.pix_offset, "vert_ids": shards.vert_ids, "names": shards.names}
    t = shards.truth
    if "truth_vertex_albedo" in t:
        arr["truth_vertex_albedo"] = t["truth_vertex_albedo"]
        if "truth_vertex_spec_albedo" in t:
            arr["truth_vertex_weights"] = t["truth_vertex_spec_albedo"]
        elif "truth_vertex_weights" in t:
            arr["truth_vertex_weights"] = t["truth_vertex_weights"]
    return arr


def _vertex_prediction(name: str, model, rec, figure: bool = False) -> Prediction:
    """The renders and the per-vertex reflectance of the predicted β of one reconstruction."""
    from reflectmm_cli.model.pca import sample_model

    va, vw = sample_model(model, rec.beta.astype(np.float64), "vertex")
    pred = {"render": rec.full, "vertex_albedo": np.asarray(va, np.float32),
            "vertex_weights": np.asarray(vw, np.float32)}
    return Prediction(name, pred, (rec.full, rec.diffuse, rec.specular) if figure else None)


def reconstruction_predictions(methods: Sequence[Method], shards, idx: np.ndarray, light, *, batch_size: int = 8,
                               device: str = "cpu", allow_other_model: bool = False, refine=None,
                               refine_methods: Sequence[str] | None = None,
                               log: Callable[[str], Any] | None = None) -> Iterator[Prediction]:
    """Table 2's rows, one method at a time: each method's encoder reconstructs the images ``idx`` of
    ``shards`` (:func:`reflectmm_cli.finetune.reconstruct.reconstruct`) → the row ``<name>`` (with its figure
    layers) and, with ``refine``, ``<name>-refined`` (only for ``refine_methods`` when given); then, with
    ``refine`` and the true per-vertex reflectance in the shards, the ``ceiling`` row (the same refinement with each
    image's true reflectance)."""
    from reflectmm_cli.finetune.encoder import load_encoder
    from reflectmm_cli.finetune.reconstruct import reconstruct

    say = log or (lambda s: None)
    for m in methods:
        if m.encoder is None:
            raise ReflectmmError(f"evaluate reconstruction: method '{m.name}' has no encoder (input "
                                 f"'encoder_{m.name}')")
        model = load_model(m.model)
        enc, _meta = load_encoder(m.encoder, device, model=m.model, allow_other_model=allow_other_model)
        say(f"evaluate reconstruction: {m.name}: {len(idx)} images")
        verb = f"evaluate reconstruction: method '{m.name}' ({m.model})"
        rec = reconstruct(shards, enc, model, light, indices=idx, batch_size=batch_size, device=device, verb=verb)
        refined = None
        if refine is not None and (refine_methods is None or m.name in refine_methods):
            say(f"evaluate reconstruction: {m.name}: refining {len(idx)} images")
            refined = reconstruct(shards, enc, model, light, indices=idx, batch_size=batch_size, device=device,
                                  refine=refine, verb=verb)
        yield _vertex_prediction(m.name, model, rec, figure=True)
        if refined is not None:
            yield _vertex_prediction(f"{m.name}-refined", model, refined)
        del rec, refined
    if refine is not None and "truth_vertex_albedo" in shards.truth and "truth_vertex_weights" in shards.truth:
        from reflectmm_cli.finetune.reconstruct import reconstruct_truth

        # the truth's lobe weights belong to the lobes of the models that have as many (the shards do not record
        # the exponents): the first such method's
        K = int(np.shape(shards.truth["truth_vertex_weights"][0])[-1])
        exps = next((e for e in (np.asarray(load_model(m.model).exponents, np.float64) for m in methods)
                     if e.shape == (K,)), None)
        if exps is None:
            say(f"evaluate reconstruction: no ceiling row: no method has the truth's {K} lobes")
        else:
            say(f"evaluate reconstruction: ceiling: refining {len(idx)} images with their true reflectance")
            rc = reconstruct_truth(shards, light, exps, refine, indices=idx, device=device)
            yield Prediction("ceiling", {"render": rc.full})


# --------------------------------------------------------------------------- relighting (Fig. 7)

def relighting_inputs(capture: Path, geometry: Path, face_model: Path, identity: str | None = None,
                      observations: Path | None = None) -> tuple[dict, dict, Any]:
    """The capture's and the geometry's arrays and the face model; each input that records another identity than
    ``identity`` (the task's, else the capture's) is refused (another identity's geometry was accepted)."""
    from reflectmm_cli.artifacts import artifact_identity, check_identity, read_artifact
    from reflectmm_cli.geometry.face_model import load_face_model

    cap = read_artifact(capture, "capture")
    ident = identity if identity is not None else artifact_identity(cap)
    check_identity(cap, ident)
    geo = check_identity(read_artifact(geometry, "geometry"), ident)
    if observations is not None:
        check_identity(read_artifact(observations, members=()), ident)  # its kind is checked where it is used
    return cap.arrays, geo.arrays, load_face_model(face_model)


def input_crop(image_window: np.ndarray, crop_origin, landmarks_full: np.ndarray, K, R, t, vertices, face_model, *,
               size: int = 224, encoding: str = "gamma1.2", exposure: float = 1.0) -> dict[str, Any]:
    """The encoder's input from one capture image: the Deep3D-aligned S×S crop and its G-buffer.

    Args:
        image_window: (h,w,3) linear image of the stored capture window; crop_origin: (x0, y0) of the window in
            the full frame; landmarks_full: (68,2) landmarks in full-frame pixels;
        K, R, t: the view's full-frame camera (model → OpenCV camera); vertices: (V,3) the identity's fitted
            vertices (mm, model space); face_model: for the triangles and the alignment's mean-shape points.
        encoding: how the encoder's training images were encoded (the crop is stored so: uint8 codes);
        exposure: factor on the linear image before encoding.
    Returns:
        ``{"image" (S,S,3) uint8, "gbuffer" (geometry.gbuffer dict incl. face_mask), "K" (3,3) crop intrinsics,
        "transform" (2,3) window → crop}``. The crop's camera is the view's camera composed with the crop's
        similarity (pixel centres at integer coordinates in both), so the G-buffer lines up with the crop.
    """
    from reflectmm_cli.evaluation.reconstruction_eval import encode_like
    from reflectmm_cli.finetune.align import align_image
    from reflectmm_cli.geometry import RayScene
    from reflectmm_cli.geometry.gbuffer import gbuffer_for_image

    x0, y0 = (float(v) for v in np.asarray(crop_origin).reshape(2))
    lm = np.asarray(landmarks_full, np.float64) - np.array([x0, y0])
    al = align_image(np.asarray(image_window, np.float32), lm, face_model, size)
    codes = np.clip(np.round(encode_like(float(exposure) * al.image, encoding) * 255.0), 0, 255).astype(np.uint8)
    Kw = np.array(K, np.float64)
    Kw[0, 2] -= x0
    Kw[1, 2] -= y0
    A3 = np.vstack([np.asarray(al.transform, np.float64), [0.0, 0.0, 1.0]])
    Kc = A3 @ Kw
    gb = gbuffer_for_image(face_model, None, None, np.asarray(R, np.float64), np.asarray(t, np.float64), Kc, size,
                           scene=RayScene(np.asarray(vertices, np.float64), np.asarray(face_model.triangles)))
    if len(gb["pix_yx"]) == 0:
        raise ReflectmmError("relighting: the fitted face does not cover any pixel of the aligned crop")
    return {"image": codes, "gbuffer": gb, "K": Kc, "transform": np.asarray(al.transform)}


def _one_image_shardset(image_u8: np.ndarray, gb: dict, encoding: str, sh_order: int):
    """A one-image :class:`reflectmm_cli.finetune.shards.ShardSet` (what ``reconstruct`` reads)."""
    from reflectmm_cli.finetune.shards import ShardSet

    S = int(image_u8.shape[0])
    P = int(len(gb["pix_yx"]))
    fm = np.asarray(gb["face_mask"], bool)[None]
    return ShardSet(names=np.array(["input"]), split=np.array(["test"]), image=image_u8[None], face_mask=fm,
                    skin_mask=fm.copy(), pix_offset=np.array([0, P], np.int64), pix_yx=gb["pix_yx"],
                    vert_ids=gb["vert_ids"], bary=gb["bary"], normal=gb["normal"], view=gb["view"],
                    visible=gb["visible"], encoding=np.array([encoding]), size=S, sh_order=int(sh_order))


def _landmarks_full(capture, geometry, face_model, c: int, g: int) -> np.ndarray:
    """(68,2) full-frame landmarks of the view: the capture's when finite, else the fitted geometry's landmark
    vertices projected with the view's camera."""
    lm = np.asarray(capture["landmarks"][c], np.float64) if "landmarks" in capture else np.full((68, 2), np.nan)
    if np.isfinite(lm).all():
        return lm
    from reflectmm_cli.geometry.camera import project

    v = np.asarray(geometry["vertices"], np.float64)[np.asarray(face_model.landmarks)]
    uv, _ = project(v, np.asarray(geometry["K"][g], np.float64), np.asarray(geometry["R"][g], np.float64),
                    np.asarray(geometry["t"][g], np.float64))
    return uv


def _fit_reflectance(m: Method, model, obs, *, view: str, input_light: str, observations: Path,
                     prior: float) -> Reflectance:
    """A method without an encoder: β fitted to the observations of the input pair alone → UV maps."""
    from reflectmm_cli.evaluation.albedo_eval import fit_coefficients
    from reflectmm_cli.model.pca import sample_model

    ov, of = _names(obs["view_names"]), _names(obs["flash_ids"])
    if view not in ov or input_light not in of:
        raise ReflectmmError(f"relighting: the observations have no pair (view {view}, flash {input_light})",
                             observations)
    pv, pf = np.asarray(obs["pair_view"]), np.asarray(obs["pair_flash"])
    j = int(np.flatnonzero((pv == ov.index(view)) & (pf == of.index(input_light)))[0])
    beta, _st = fit_coefficients(model, obs, prior=prior, pairs=[j])
    C, W = sample_model(model, beta, "uv")
    return Reflectance(m.name, "uv", C, W, np.asarray(model.exponents, np.float64), "fit (no encoder)", beta)


def _names(a) -> list[str]:
    return [str(x) for x in np.asarray(a).reshape(-1)]


def relighting_reflectances(methods: Sequence[Method], capture: dict, geometry: dict, face_model, selection: dict,
                            *, light_model: Path | None = None, observations: Path | None = None,
                            view: str = "05_1", input_light: str = "room", size: int = 224,
                            encoding: str = "gamma1.2", exposure: float = 1.0, prior: float = 1e-4,
                            device: str = "cpu", allow_other_model: bool = False, refine=None) -> Iterator[Reflectance]:
    """Each method's reflectance from ONE image (``selection``: :func:`reflectmm_cli.evaluation.tables.
    relighting_selection`), one method at a time.

    A method with an encoder: the image's Deep3D crop and G-buffer from the fitted geometry (:func:`input_crop`,
    made once) → ``reconstruct`` → per-vertex reflectance of β. A method without
    one: β fitted to the ``observations`` (uv-observations) of the input pair alone
    (``albedo_eval.fit_coefficients``; needs a flash input) → UV maps.
    """
    from reflectmm_cli.artifacts import read_artifact
    from reflectmm_cli.model.pca import sample_model

    c, g = selection["c"], selection["g"]
    crop = light = obs = None
    for m in methods:
        model = load_model(m.model)
        if m.encoder is None:
            if observations is None:
                raise ReflectmmError(f"relighting: method '{m.name}' has no encoder: give the identity's "
                                     "uv-observations (input 'observations') for the encoder-free fit")
            if input_light == "room":
                raise ReflectmmError(f"relighting: method '{m.name}' has no encoder and the input is the room-light "
                                     "image: the encoder-free fit needs a flash input (--input FLASH)")
            if obs is None:
                obs = read_artifact(observations, "uv-observations").arrays
            yield _fit_reflectance(m, model, obs, view=view, input_light=input_light, observations=observations,
                                   prior=prior)
            continue
        from reflectmm_cli.finetune.encoder import load_encoder
        from reflectmm_cli.finetune.reconstruct import reconstruct

        if light_model is None:
            raise ReflectmmError(f"relighting: method '{m.name}' has an encoder but no light model was given "
                                 "(input 'light_model')")
        if light is None:
            light = load_light_model(light_model)
            lm = _landmarks_full(capture, geometry, face_model, c, g)
            crop = input_crop(selection["input"], np.asarray(capture["crop_origin"])[c], lm, geometry["K"][g],
                              geometry["R"][g], geometry["t"][g], geometry["vertices"], face_model, size=size,
                              encoding=encoding, exposure=exposure)
        enc, _ = load_encoder(m.encoder, device, model=m.model, allow_other_model=allow_other_model)
        ss = _one_image_shardset(crop["image"], crop["gbuffer"], encoding, light.order)
        rec = reconstruct(ss, enc, model, light, indices=[0], device=device, refine=refine)
        alb, wts = sample_model(model, rec.beta[0].astype(np.float64), "vertex")
        yield Reflectance(m.name, "vertex", alb, wts, np.asarray(model.exponents, np.float64),
                          "encoder" if refine is None else "encoder + refine", rec.beta[0])
