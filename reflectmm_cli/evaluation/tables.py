"""The evaluate stages' library side: Table 2 (reconstruction on wild shards), Table 3 (albedo of held-out
identities) and Fig. 7 (relighting) for N methods, from artifact paths to numbers, tables and figures
(docs/evaluation.md). Each function is ``result = fn(inputs..., config)``; the stages write the result.

Methods are :class:`reflectmm_cli.evaluation.methods.Method` (name, reflectance-model path, encoder path or
None). Results are dicts with ``arrays`` (the ``evaluation`` artifact's names/values), ``table`` (markdown),
``summary`` (JSON-able numbers per method), ``paper_numbers`` (the values that stand beside the paper's, keyed
as :data:`reflectmm_cli.evaluation.paper_numbers.PAPER_NUMBERS`) and, where there is one, ``figure`` (an
(H,W,3) float image in [0, 1]) with ``figure_rows`` (the label of each figure row).
"""
from __future__ import annotations

from pathlib import Path
from typing import Any, Callable, Mapping, Sequence

import numpy as np

from reflectmm_cli.errors import ReflectmmError

from .methods import Method

__all__ = ["load_model", "identity_of", "truth_by_identity", "albedo_evaluation",
           "reconstruction_evaluation", "input_crop", "relighting_evaluation", "ALBEDO_PROTOCOL",
           "RECONSTRUCTION_PROTOCOL", "RELIGHTING_PROTOCOL"]

ALBEDO_PROTOCOL = ("Each model's coefficients β fitted to the held-out identity's OLAT observations (all pairs; prior "
                   "λ·ȳ²·Σβ²); diffuse albedo PSNR (linear, peak 1) over model domain ∧ truth mask ∧ observed "
                   "texels; specular albedo = Σw against the truth's specular albedo; raw and after one global "
                   "scale fitted on the diffuse albedo; mean ± 95 % CI over identities.")
RECONSTRUCTION_PROTOCOL = ("Each method's encoder reconstructs every selected image; PSNR / SSIM / LPIPS of the "
                           "reconstruction in the face region of the image's display encoding, per image, then "
                           "mean ± 95 % CI; the released code's batch protocol beside it; per-vertex diffuse albedo "
                           "and Σw against the truth over the vertices each image sees, after one per-image scale "
                           "(scaled) and without (raw).")
RELIGHTING_PROTOCOL = ("One image of the identity (room light or one flash) → each method's coefficients (its "
                       "encoder on the aligned crop and the G-buffer of the fitted geometry, or β fitted to the "
                       "input pair's UV observations when the method has no encoder) → re-rendered under each "
                       "held-out flash (point light, cast shadows) and compared with the captured OLAT image over "
                       "the lit face; PSNR / SSIM of clip(x,0,1)^(1/1.2), mean over flashes.")


def load_model(path: Path):
    """:class:`reflectmm_cli.model.ReflectanceModel` of a ``reflectance-model`` artifact."""
    from reflectmm_cli.artifacts import read_artifact
    from reflectmm_cli.model.pca import MODEL_KIND, model_from_arrays

    art = read_artifact(path, MODEL_KIND)
    return model_from_arrays(art.arrays, art.meta.get("stats"))


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


def _psnr_cell(ci: dict) -> str:
    from .face_metrics import format_ci

    return format_ci(ci, 2)


# --------------------------------------------------------------------------- Table 3

def albedo_evaluation(methods: Sequence[Method], observations: Sequence[Path], truth: Sequence[Path], *,
                      prior: float = 1e-4, oracle: bool = False, ours: str = "finetuned",
                      progress_fn: Callable | None = None) -> dict[str, Any]:
    """Table 3 for ``methods`` on the held-out identities of ``observations`` (uv-observations artifacts; the
    identity from their meta or file stem) with their ``truth`` (synth-truth files or folders, by identity).

    Every model must have the observations' UV size. Returns the module's result dict; ``summary[name]`` holds
    the mean ± CI of ``raw``/``scaled`` ``diffuse_psnr``, ``specular_psnr``, ``diffuse_rel``, ``specular_rel``.
    """
    from reflectmm_cli.artifacts import read_artifact

    from .albedo_eval import albedo_table_rows, evaluate_albedo
    from .reconstruction_eval import markdown_table
    from .results import evaluation_arrays, to_document

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
        tr = read_artifact(truths[iid], "synth-truth").arrays
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
    res = evaluate_albedo(models, idents, prior=prior, oracle=oracle, progress_fn=progress_fn)
    rows = albedo_table_rows(res)
    cells = []
    summary = {}
    for r in rows:
        summary[r["model"]] = {k: v for k, v in r.items() if k not in ("model",)}
        cells.append({"model": r["model"], "identities": str(r["identities"]),
                      "diffuse PSNR (dB)": _psnr_cell(r["raw.diffuse_psnr"]),
                      "specular PSNR (dB)": _psnr_cell(r["raw.specular_psnr"]),
                      "diffuse rel.": _psnr_cell(r["raw.diffuse_rel"]).replace("nan", "–"),
                      "specular rel.": _psnr_cell(r["raw.specular_rel"]).replace("nan", "–"),
                      "diffuse PSNR, scaled": _psnr_cell(r["scaled.diffuse_psnr"]),
                      "specular PSNR, scaled": _psnr_cell(r["scaled.specular_psnr"])})
    paper = {}
    if ours in summary:
        paper = {"table3.diffuse_psnr": summary[ours]["raw.diffuse_psnr"]["mean"],
                 "table3.specular_psnr": summary[ours]["raw.specular_psnr"]["mean"]}
    doc = {"per_identity": res.per_identity, "fits": res.fits, "summary": summary}
    return {"arrays": evaluation_arrays(to_document(doc)), "table": markdown_table(cells),
            "summary": to_document(summary), "paper_numbers": paper, "identities": sorted(idents),
            "protocol": ALBEDO_PROTOCOL}


# --------------------------------------------------------------------------- Table 2

def _shard_arrays(shards) -> dict[str, np.ndarray]:
    """The arrays :func:`.reconstruction_eval.evaluate_reconstruction` reads, from a ShardSet. The truth's
    specular albedo is ``truth_vertex_spec_albedo`` (N,V) when present, else Σ of ``truth_vertex_weights``."""
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


#: Table 2's measures whose finetuning gain is reported (image measures: higher is better; reflectance errors:
#: lower is better — the gain of an error is its decrease).
GAIN_MEASURES = (("image", "psnr", "PSNR (dB)", 1.0), ("image", "ssim", "SSIM", 1.0),
                 ("scaled", "albedo_rel", "albedo rel (scaled)", -1.0), ("scaled", "spec_rel", "Σw rel (scaled)", -1.0))


def paired_gains(a: Mapping[str, Any], b: Mapping[str, Any], *, level: float = 0.95,
                 method: str = "t") -> dict[str, dict[str, Any]]:
    """Per measure, the per-image difference A − B (for error measures B − A, so that a positive gain is an
    improvement) of two methods evaluated on the same images, with the mean's confidence interval.

    Args:
        a, b: :func:`.reconstruction_eval.evaluate_reconstruction` results of the two methods (same images).
    Returns:
        ``{measure: {"per_image": (N,), "summary": mean_ci}}`` for the measures of :data:`GAIN_MEASURES` that both
        have.
    """
    from .face_metrics import mean_ci

    out = {}
    for part, key, _label, sign in GAIN_MEASURES:
        if part == "image":
            va = a["image"]["per_image"].per_image.get(key)
            vb = b["image"]["per_image"].per_image.get(key)
        else:
            ra, rb = a.get("reflectance"), b.get("reflectance")
            va = None if ra is None else ra["per_image"][part].get(key)
            vb = None if rb is None else rb["per_image"][part].get(key)
        if va is None or vb is None:
            continue
        d = sign * (np.asarray(va, np.float64) - np.asarray(vb, np.float64))
        d = d[np.isfinite(d)]
        if d.size:
            out[key] = {"per_image": d, "summary": mean_ci(d, level=level, method=method)}
    return out


def gains_table(gains: Mapping[str, Mapping[str, Any]]) -> str:
    """Markdown table of :func:`paired_gains` results: one row per compared pair, one column per measure."""
    from .face_metrics import format_ci

    labels = {key: label for _p, key, label, _s in GAIN_MEASURES}
    rows = []
    for pair, g in gains.items():
        row = {"gain": pair}
        for _p, key, label, _s in GAIN_MEASURES:
            digits = 2 if key == "psnr" else 4 if key == "ssim" else 3
            row[labels[key]] = format_ci(g[key]["summary"], digits) if key in g else "–"
        rows.append(row)
    from .reconstruction_eval import markdown_table

    return markdown_table(rows)


def reconstruction_evaluation(methods: Sequence[Method], data: Sequence[Path], light_model: Path, *,
                              split: str = "test", region: str = "face", lpips=None, lpips_name: str = "off",
                              batch_size: int = 8, released_batch: int = 32, ci: str = "t", figure_images: int = 3,
                              max_images: int = 0, gain: Sequence[str] = ("finetuned", "initial"),
                              device: str = "cpu", allow_other_model: bool = False, refine=None,
                              log: Callable[[str], Any] | None = None) -> dict[str, Any]:
    """Table 2 for ``methods`` (each with an encoder) on the ``split`` images of the wild shards ``data``.

    With ``refine`` (a :class:`~reflectmm_cli.finetune.refine.RefineConfig`) every method also gets a refined row
    (``<name>-refined``: the encoder's prediction refined per image, the model fixed) and, when the shards carry
    the true per-vertex reflectance, a ``ceiling`` row (the same refinement with each image's true reflectance).
    The gain A − B is reported per measure as the mean of the per-image differences with its confidence interval
    (:func:`paired_gains`), for the encoder-only and, with ``refine``, the refined rows.

    Each method: :func:`reflectmm_cli.finetune.reconstruct.reconstruct` with its encoder, model and the light
    model → per-vertex reflectance of the predicted β (``sample_model``) → :func:`.reconstruction_eval.
    evaluate_reconstruction`. ``gain`` = (A, B): A − B mean PSNR stands beside the paper's +0.95 dB (ours over
    ours w/o finetuning) when both methods are present. The figure: for each of the first ``figure_images``
    images one row per method with :data:`.figures.PANELS`.
    """
    from reflectmm_cli.artifacts import read_artifact
    from reflectmm_cli.finetune.encoder import load_encoder
    from reflectmm_cli.finetune.reconstruct import reconstruct
    from reflectmm_cli.finetune.shards import load_shards
    from reflectmm_cli.model.light import LIGHT_MODEL_KIND, light_model_from_arrays
    from reflectmm_cli.model.pca import sample_model

    from .figures import grid, method_panels
    from .reconstruction_eval import encode_like, evaluate_reconstruction, markdown_table, table_row
    from .results import evaluation_arrays, to_document

    say = log or (lambda s: None)
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
    encoding = encs[0]
    light = light_model_from_arrays(read_artifact(light_model, LIGHT_MODEL_KIND).arrays)
    sarr = _shard_arrays(shards)
    if "truth_vertex_albedo" not in sarr:
        say("evaluate reconstruction: the shards carry no truth_vertex_albedo: image metrics only")
    nfig = min(int(figure_images), len(idx))
    fig_rows: list[list[np.ndarray]] = [[] for _ in range(nfig)]
    labels: list[list[str]] = [[] for _ in range(nfig)]
    rows, results, per_method = [], {}, {}
    for m in methods:
        if m.encoder is None:
            raise ReflectmmError(f"evaluate reconstruction: method '{m.name}' has no encoder (input "
                                 f"'encoder_{m.name}')")
        model = load_model(m.model)
        enc, _meta = load_encoder(m.encoder, device, model=m.model, allow_other_model=allow_other_model)
        say(f"evaluate reconstruction: {m.name}: {len(idx)} images")
        rec = reconstruct(shards, enc, model, light, indices=idx, batch_size=batch_size, device=device)
        variants = [(m.name, rec)]
        if refine is not None:
            say(f"evaluate reconstruction: {m.name}: refining {len(idx)} images")
            variants.append((f"{m.name}-refined", reconstruct(shards, enc, model, light, indices=idx,
                                                              batch_size=batch_size, device=device, refine=refine)))
        for name, rv in variants:
            va, vw = sample_model(model, rv.beta.astype(np.float64), "vertex")
            pred = {"render": rv.full, "vertex_albedo": np.asarray(va, np.float32),
                    "vertex_weights": np.asarray(vw, np.float32)}
            out = evaluate_reconstruction(pred, sarr, encoding=encoding, select=idx, region=region, lpips=lpips,
                                          method=ci, batch_size=released_batch)
            results[name] = out
            rows.append(table_row(name, out["image"], out["reflectance"]))
            per_method[name] = {"psnr": out["image"]["per_image"].summary["psnr"]["mean"],
                                "ssim": out["image"]["per_image"].summary["ssim"]["mean"]}
        for r in range(nfig):
            i = int(idx[r])
            inp = shards.image[i].astype(np.float64) / 255.0
            fig_rows[r].append(method_panels(inp, encode_like(rec.full[r], encoding),
                                             encode_like(rec.diffuse[r], encoding),
                                             encode_like(rec.specular[r], encoding), shards.face_mask[i]))
            labels[r].append(f"{shards.names[i]} — {m.name}")
        del rec, va, vw, pred
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
            out = evaluate_reconstruction({"render": rc.full}, sarr, encoding=encoding, select=idx, region=region,
                                          lpips=lpips, method=ci, batch_size=released_batch)
            results["ceiling"] = out
            rows.append(table_row("ceiling", out["image"], None))
            per_method["ceiling"] = {"psnr": out["image"]["per_image"].summary["psnr"]["mean"],
                                     "ssim": out["image"]["per_image"].summary["ssim"]["mean"]}
    paper = {}
    gains = {}
    if len(gain) == 2 and gain[0] in per_method and gain[1] in per_method:
        paper["table2.psnr_gain_finetune"] = per_method[gain[0]]["psnr"] - per_method[gain[1]]["psnr"]
        for suffix in ("", "-refined"):
            a, b = gain[0] + suffix, gain[1] + suffix
            if a in results and b in results:
                gains[f"{a} - {b}"] = paired_gains(results[a], results[b], method=ci)
    flat_rows = [r for rr in fig_rows for r in rr]
    doc = {name: {"image": {"per_image": out["image"]["per_image"], "released": out["image"]["released"]},
                  "reflectance": (None if out["reflectance"] is None else
                                  {"scale": out["reflectance"]["scale"], "summary": out["reflectance"]["summary"],
                                   "per_image": out["reflectance"]["per_image"]})}
           for name, out in results.items()}
    summary = {name: {"image": to_document(out["image"]["per_image"].summary),
                      "released": to_document(out["image"]["released"]),
                      "reflectance": None if out["reflectance"] is None else to_document(out["reflectance"]["summary"])}
               for name, out in results.items()}
    if gains:
        doc["gains"] = {k: {m: {"per_image": g["per_image"], "summary": g["summary"]} for m, g in v.items()}
                        for k, v in gains.items()}
    return {"arrays": evaluation_arrays(doc), "table": markdown_table(rows), "summary": summary,
            "paper_numbers": paper, "gains": {k: {m: to_document(g["summary"]) for m, g in v.items()}
                                              for k, v in gains.items()},
            "gains_table": gains_table(gains) if gains else "",
            "ceiling": "ceiling" in results, "figure": grid(flat_rows) if flat_rows else None,
            "figure_rows": [lab for ll in labels for lab in ll], "n_images": int(len(idx)),
            "images": [str(shards.names[i]) for i in idx], "encoding": encoding, "lpips": lpips_name,
            "protocol": RECONSTRUCTION_PROTOCOL}


# --------------------------------------------------------------------------- relighting (Fig. 7)

def _names(a) -> list[str]:
    return [str(x) for x in np.asarray(a).reshape(-1)]


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
    from reflectmm_cli.finetune.align import align_image
    from reflectmm_cli.geometry import RayScene
    from reflectmm_cli.geometry.gbuffer import gbuffer_for_image

    from .reconstruction_eval import encode_like

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


def relighting_evaluation(methods: Sequence[Method], capture: Path, geometry: Path, face_model: Path, *,
                          light_model: Path | None = None, observations: Path | None = None, view: str = "05_1",
                          input_light: str = "room", holdout: Sequence[str] | None = None, size: int = 224,
                          encoding: str = "gamma1.2", exposure: float = 1.0, scale: str = "global",
                          prior: float = 1e-4, device: str = "cpu", allow_other_model: bool = False,
                          refine=None, log: Callable[[str], Any] | None = None) -> dict[str, Any]:
    """Fig. 7 for one held-out identity: each method reconstructs from ONE image of ``view`` (``input_light`` =
    ``"room"`` — the room-light shot — or a flash id — the flash shot, room + OLAT), and is re-rendered under
    the ``holdout`` flashes (default: every flash but the input's).

    A method with an encoder: the image's Deep3D crop and G-buffer from the fitted geometry (:func:`input_crop`)
    → ``reconstruct`` → per-vertex reflectance of β. A method without one: β fitted to the ``observations``
    (uv-observations) of the input pair alone (``albedo_eval.fit_coefficients``; needs a flash input) → UV maps.
    Returns the module's result dict (``summary[name]`` = scale, PSNR, SSIM, per flash).
    """
    from reflectmm_cli.artifacts import read_artifact
    from reflectmm_cli.geometry.face_model import load_face_model
    from reflectmm_cli.model.pca import sample_model

    from .figures import grid
    from .metrics import encode_for_metrics
    from .reconstruction_eval import markdown_table
    from .relighting import capture_targets, relight, relighting_metrics, relighting_rows, scene_from_artifacts
    from .results import evaluation_arrays, to_document

    say = log or (lambda s: None)
    cap = read_artifact(capture, "capture").arrays
    geo = read_artifact(geometry, "geometry").arrays
    fm = load_face_model(face_model)
    cv, cf = _names(cap["view_names"]), _names(cap["flash_ids"])
    gv = _names(geo["view_names"] if "view_names" in geo else geo["camera_names"])
    gf = _names(geo["flash_ids"])
    if view not in cv or view not in gv:
        raise ReflectmmError(f"relighting: view '{view}' not in the capture ({', '.join(cv)}) and the geometry "
                             f"({', '.join(gv)})", capture)
    c, g = cv.index(view), gv.index(view)
    flashes = [f for f in cf if f in gf]
    if input_light != "room" and input_light not in flashes:
        raise ReflectmmError(f"relighting: input '{input_light}' is neither 'room' nor a flash of the capture "
                             f"({', '.join(flashes)})", capture)
    held = [f for f in flashes if f != input_light] if not holdout else [str(f) for f in holdout]
    for f in held:
        if f not in flashes:
            raise ReflectmmError(f"relighting: held-out flash '{f}' is not a flash of the capture and the geometry "
                                 f"({', '.join(flashes)})", capture)
        if f == input_light:
            raise ReflectmmError(f"relighting: flash '{f}' is the input image and cannot be held out")
    if not held:
        raise ReflectmmError("relighting: no held-out flash left")
    if input_light == "room":
        if "room" not in cap:
            raise ReflectmmError("relighting: the capture has no room-light image ('room' array)", capture)
        inp_lin = np.asarray(cap["room"][c], np.float64)
    else:
        inp_lin = np.asarray(cap["olat"][c, cf.index(input_light)], np.float64)
        if "room" in cap:
            inp_lin = inp_lin + np.asarray(cap["room"][c], np.float64)
    targets = capture_targets(cap, view, held)
    scene_v = scene_from_artifacts(cap, geo, fm.triangles, view)
    scene_uv = None
    crop = light = obs = None
    renders, metrics, used = {}, {}, {}
    for m in methods:
        model = load_model(m.model)
        exps = np.asarray(model.exponents, np.float64)
        if m.encoder is not None:
            from reflectmm_cli.finetune.encoder import load_encoder
            from reflectmm_cli.finetune.reconstruct import reconstruct
            from reflectmm_cli.model.light import LIGHT_MODEL_KIND, light_model_from_arrays

            if light_model is None:
                raise ReflectmmError(f"relighting: method '{m.name}' has an encoder but no light model was given "
                                     "(input 'light_model')")
            if light is None:
                light = light_model_from_arrays(read_artifact(light_model, LIGHT_MODEL_KIND).arrays)
                lm = _landmarks_full(cap, geo, fm, c, g)
                crop = input_crop(inp_lin, np.asarray(cap["crop_origin"])[c], lm, geo["K"][g], geo["R"][g],
                                  geo["t"][g], geo["vertices"], fm, size=size, encoding=encoding, exposure=exposure)
            enc, _ = load_encoder(m.encoder, device, model=m.model, allow_other_model=allow_other_model)
            ss = _one_image_shardset(crop["image"], crop["gbuffer"], encoding, light.order)
            rec = reconstruct(ss, enc, model, light, indices=[0], device=device, refine=refine)
            alb, wts = sample_model(model, rec.beta[0].astype(np.float64), "vertex")
            renders[m.name] = relight(scene_v, alb, wts, exps, held)
            metrics[m.name] = relighting_metrics(scene_v, renders[m.name], targets, scale=scale)
            used[m.name] = {"path": "encoder" if refine is None else "encoder + refine", "beta": rec.beta[0]}
        else:
            from .albedo_eval import fit_coefficients

            if observations is None:
                raise ReflectmmError(f"relighting: method '{m.name}' has no encoder: give the identity's "
                                     "uv-observations (input 'observations') for the encoder-free fit")
            if input_light == "room":
                raise ReflectmmError(f"relighting: method '{m.name}' has no encoder and the input is the room-light "
                                     "image: the encoder-free fit needs a flash input (--input FLASH)")
            if obs is None:
                obs = read_artifact(observations, "uv-observations").arrays
            ov, of = _names(obs["view_names"]), _names(obs["flash_ids"])
            if view not in ov or input_light not in of:
                raise ReflectmmError(f"relighting: the observations have no pair (view {view}, flash {input_light})",
                                     observations)
            pv, pf = np.asarray(obs["pair_view"]), np.asarray(obs["pair_flash"])
            j = int(np.flatnonzero((pv == ov.index(view)) & (pf == of.index(input_light)))[0])
            beta, _st = fit_coefficients(model, obs, prior=prior, pairs=[j])
            C, W = sample_model(model, beta, "uv")
            if scene_uv is None:
                scene_uv = scene_from_artifacts(cap, geo, fm.triangles, view, uv=fm.uv)
            renders[m.name] = relight(scene_uv, C, W, exps, held)
            metrics[m.name] = relighting_metrics(scene_uv, renders[m.name], targets, scale=scale)
            used[m.name] = {"path": "fit (no encoder)", "beta": beta}
        say(f"relighting: {m.name}: PSNR {metrics[m.name]['psnr']:.2f} dB, SSIM {metrics[m.name]['ssim']:.4f} "
            f"({used[m.name]['path']})")
    rows = [{"method": n, "coefficients from": used[n]["path"], "PSNR (dB)": f"{v['psnr']:.2f}",
             "SSIM": f"{v['ssim']:.4f}", "scale": f"{v['scale']:.3f}"} for n, v in metrics.items()]
    fid = held[0]
    fig = relighting_rows(scene_v, encode_for_metrics(inp_lin), renders, targets, fid,
                          scales={n: metrics[n]["scale"] for n in metrics})
    doc = {n: {"scale": v["scale"], "psnr": v["psnr"], "ssim": v["ssim"], "per_flash": v["per_flash"],
               "beta": used[n]["beta"]} for n, v in metrics.items()}
    out = {"arrays": evaluation_arrays(doc), "table": markdown_table(rows),
           "summary": to_document({n: {k: v for k, v in d.items() if k != "beta"} for n, d in doc.items()}),
           "paper_numbers": {}, "figure": grid(fig),
           "figure_rows": [f"input ({input_light}) | captured OLAT of flash {fid}"] + list(metrics),
           "holdout": held, "view": view, "input": input_light,
           "paths": {n: used[n]["path"] for n in used}, "protocol": RELIGHTING_PROTOCOL}
    if crop is not None:
        out["crop"] = crop["image"]
    return out
