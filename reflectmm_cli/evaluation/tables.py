"""The evaluate stages' computation: Table 2 (reconstruction on wild shards), Table 3 (albedo of held-out
identities) and Fig. 7 (relighting) for N methods, from the arrays and predictions the stages give
(docs/evaluation.md). Nothing here reads a file or runs an encoder: the stages do, with
:mod:`reflectmm_cli.stages.evaluation_inputs`, and hand over the models, the arrays and, per method, a
:class:`Prediction` (Table 2) or a :class:`Reflectance` (Fig. 7) — lazily, one method at a time.

Results are dicts with ``arrays`` (the ``evaluation`` artifact's names/values), ``table`` (markdown),
``summary`` (JSON-able numbers per method), ``paper_numbers`` (the values that stand beside the paper's, keyed
as :data:`reflectmm_cli.evaluation.paper_numbers.PAPER_NUMBERS`) and, where there is one, ``figure`` (an
(H,W,3) float image in [0, 1]) with ``figure_rows`` (the label of each figure row).
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Callable, Iterable, Mapping, Sequence

import numpy as np

from reflectmm_cli.errors import ReflectmmError

__all__ = ["albedo_evaluation", "Prediction", "reconstruction_evaluation", "paired_gains", "gains_table",
           "psnr_gap_closed", "gap_sentence", "gain_text", "interval_holds_zero", "Reflectance",
           "relighting_selection", "relighting_evaluation", "ALBEDO_PROTOCOL", "RECONSTRUCTION_PROTOCOL",
           "RELIGHTING_PROTOCOL", "GAIN_MEASURES"]

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


def _psnr_cell(ci: dict) -> str:
    from .face_metrics import format_ci

    return format_ci(ci, 2)


# --------------------------------------------------------------------------- Table 3

def albedo_evaluation(models: Mapping[str, Any], identities: Mapping[str, tuple], *, prior: float = 1e-4,
                      oracle: bool = False, ours: str = "finetuned",
                      progress_fn: Callable | None = None) -> dict[str, Any]:
    """Table 3 for the reflectance ``models`` (by method name, in table order) on the held-out ``identities``
    (``{identity: (uv-observations arrays, truth arrays albedo / spec_albedo [/ uv_mask])}``; the models have
    the observations' UV size).

    Returns the module's result dict; ``summary[name]`` holds the mean ± CI of ``raw``/``scaled``
    ``diffuse_psnr``, ``specular_psnr``, ``diffuse_rel``, ``specular_rel``.
    """
    from .albedo_eval import albedo_table_rows, evaluate_albedo
    from .reconstruction_eval import markdown_table
    from .results import evaluation_arrays, to_document

    res = evaluate_albedo(dict(models), dict(identities), prior=prior, oracle=oracle, progress_fn=progress_fn)
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
            "summary": to_document(summary), "paper_numbers": paper, "identities": sorted(identities),
            "protocol": ALBEDO_PROTOCOL}


# --------------------------------------------------------------------------- Table 2

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


@dataclass
class Prediction:
    """One row of Table 2 as a stage predicted it for the selected images (in their order).

    ``pred``: what :func:`.reconstruction_eval.evaluate_reconstruction` reads — ``render`` (N,S,S,3) linear and,
    for the reflectance errors, ``vertex_albedo`` (N,V,3) and ``vertex_weights`` (N,V,K); ``figure``: the
    (full, diffuse, specular) linear renders (N,S,S,3) when the row has figure panels, else None.
    """
    name: str
    pred: dict[str, np.ndarray]
    figure: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None


def _figure_panels(fig_rows: list[list], labels: list[list[str]], p: Prediction, shard: Mapping[str, np.ndarray],
                   idx: np.ndarray, encoding: str) -> None:
    """Append the :data:`.figures.PANELS` of ``p`` to each figure row (the first images of ``idx``)."""
    from .figures import method_panels
    from .reconstruction_eval import encode_like

    full, diffuse, specular = p.figure
    for r in range(len(fig_rows)):
        i = int(idx[r])
        inp = shard["image"][i].astype(np.float64) / 255.0
        fig_rows[r].append(method_panels(inp, encode_like(full[r], encoding), encode_like(diffuse[r], encoding),
                                         encode_like(specular[r], encoding), shard["face_mask"][i]))
        labels[r].append(f"{shard['names'][i]} — {p.name}")


def _table2_gains(per_method: Mapping[str, dict], results: Mapping[str, dict], gain: Sequence[str], ci: str,
                  more: Sequence[Sequence[str]] = ()) -> tuple[dict[str, float], dict[str, dict]]:
    """The paper's number (A − B mean PSNR) and the paired gains of A over B, encoder-only and refined; then the
    same paired gains of each pair of ``more`` whose two methods are present."""
    paper = {}
    gains = {}
    if len(gain) == 2 and gain[0] in per_method and gain[1] in per_method:
        paper["table2.psnr_gain_finetune"] = per_method[gain[0]]["psnr"] - per_method[gain[1]]["psnr"]
    for pa, pb in [tuple(gain)] + [tuple(x) for x in more]:
        if pa not in per_method or pb not in per_method:
            continue
        for suffix in ("", "-refined"):
            a, b = pa + suffix, pb + suffix
            if a in results and b in results and f"{a} - {b}" not in gains:
                gains[f"{a} - {b}"] = paired_gains(results[a], results[b], method=ci)
    return paper, gains


def psnr_gap_closed(gains: dict, gain, unequal: dict) -> dict[str, float]:
    """The share of the oracle's PSNR gain that ``gain`` = (A, B) reaches, ``(A − B) / (oracle − B)`` of the mean
    paired PSNR gains, encoder-only and refined (issue 21's "gap closed" for Table 2), where both gains are
    reported at equal encoder budgets.  NaN where the oracle's gain is not above zero by its confidence interval:
    a share of a gain that may be nothing measures nothing (:func:`gap_sentence` says so)."""
    a, b = gain
    out = {}
    for suffix, label in (("", "encoder-only"), ("-refined", "refined")):
        ab, ob = gains.get(f"{a}{suffix} - {b}{suffix}"), gains.get(f"oracle{suffix} - {b}{suffix}")
        if ab is None or ob is None or a == "oracle" or f"{a} - {b}" in unequal or f"oracle - {b}" in unequal:
            continue
        den = float(ob["psnr"]["mean"])
        measured = den > 0 and not interval_holds_zero(ob["psnr"])
        out[label] = float(ab["psnr"]["mean"]) / den if measured else float("nan")
    return out


def gain_text(summary: Mapping[str, Any]) -> str:
    """``+0.12 ± 0.32 dB`` of a :func:`~.face_metrics.mean_ci` summary of a PSNR gain."""
    half = float(summary.get("half_width", float("nan")))
    return f"{float(summary['mean']):+.2f}" + (f" ± {half:.2f}" if np.isfinite(half) else "") + " dB"


def interval_holds_zero(summary: Mapping[str, Any]) -> bool:
    """Whether a gain's :func:`~.face_metrics.mean_ci` summary is not above zero by its interval (its lower end at
    or below zero, or no interval)."""
    lo = float(summary.get("lo", float("nan")))
    return not lo > 0


def gap_sentence(gap: dict[str, float], gain, gains: Mapping[str, Any] | None = None) -> str:
    """One line of :func:`psnr_gap_closed`'s shares, for the table's markdown and the report; with ``gains`` (the
    paired gains it was computed from) an unmeasured share names the oracle's gain."""
    a, b = gain
    parts = []
    for k, v in gap.items():
        if np.isfinite(v):
            parts.append(f"{k} {100 * v:.0f} %")
            continue
        sfx = "-refined" if k == "refined" else ""
        ob = (gains or {}).get(f"oracle{sfx} - {b}{sfx}")
        why = (f"the oracle's gain, {gain_text(ob['psnr'])}, is not above zero by its interval" if ob else
               "the oracle does not gain")
        parts.append(f"{k} not measured ({why})")
    return (f"Gap to the oracle closed in PSNR by `{a}` from `{b}` (({a} − {b}) / (oracle − {b}) of the mean "
            "gains): " + ", ".join(parts) + ".")


def _table2_documents(results: Mapping[str, dict], gains: Mapping[str, dict]) -> tuple[dict, dict]:
    """The ``evaluation`` artifact's document (per-image numbers) and the JSON-able summary per method."""
    from .results import to_document

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
    return doc, summary


def reconstruction_evaluation(predictions: Iterable[Prediction], shard: Mapping[str, np.ndarray],
                              select: np.ndarray, *, encoding: str, region: str = "face", lpips=None,
                              lpips_name: str = "off", released_batch: int = 32, ci: str = "t",
                              figure_images: int = 3, gain: Sequence[str] = ("finetuned", "initial"),
                              more_gains: Sequence[Sequence[str]] = ()) -> dict[str, Any]:
    """Table 2 of the ``predictions`` (one per row, in table order; e.g. the stage's
    :func:`reflectmm_cli.stages.evaluation_inputs.reconstruction_predictions`) on the images ``select`` of the
    wild-shard arrays ``shard`` (``image``, ``face_mask``, ``skin_mask``, ``names``, ``pix_offset``,
    ``vert_ids``, optional ``truth_vertex_albedo`` / ``truth_vertex_weights``), all encoded as ``encoding``.

    Each row: :func:`.reconstruction_eval.evaluate_reconstruction`. The gain A − B is reported per measure as the
    mean of the per-image differences with its confidence interval (:func:`paired_gains`), for ``gain`` = (A, B)
    and, when present, their ``-refined`` rows; A − B mean PSNR stands beside the paper's +0.95 dB (ours over
    ours w/o finetuning). ``more_gains``: further (A, B) pairs reported the same way when both are present (e.g.
    the oracle over the control: the ceiling of the finetuning gain). The figure: for each of the first
    ``figure_images`` images one row per prediction that has figure layers, with :data:`.figures.PANELS`.
    """
    from .figures import grid
    from .reconstruction_eval import evaluate_reconstruction, markdown_table, table_row
    from .results import evaluation_arrays, to_document

    idx = np.asarray(select)
    nfig = min(int(figure_images), len(idx))
    fig_rows: list[list[np.ndarray]] = [[] for _ in range(nfig)]
    labels: list[list[str]] = [[] for _ in range(nfig)]
    rows, results, per_method = [], {}, {}
    for p in predictions:
        out = evaluate_reconstruction(p.pred, shard, encoding=encoding, select=idx, region=region, lpips=lpips,
                                      method=ci, batch_size=released_batch)
        results[p.name] = out
        rows.append(table_row(p.name, out["image"], out["reflectance"]))
        per_method[p.name] = {"psnr": out["image"]["per_image"].summary["psnr"]["mean"],
                              "ssim": out["image"]["per_image"].summary["ssim"]["mean"]}
        if p.figure is not None:
            _figure_panels(fig_rows, labels, p, shard, idx, encoding)
        del p
    paper, gains = _table2_gains(per_method, results, gain, ci, more_gains)
    flat_rows = [r for rr in fig_rows for r in rr]
    doc, summary = _table2_documents(results, gains)
    return {"arrays": evaluation_arrays(doc), "table": markdown_table(rows), "summary": summary,
            "paper_numbers": paper, "gains": {k: {m: to_document(g["summary"]) for m, g in v.items()}
                                              for k, v in gains.items()},
            "gains_table": gains_table(gains) if gains else "",
            "ceiling": "ceiling" in results, "figure": grid(flat_rows) if flat_rows else None,
            "figure_rows": [lab for ll in labels for lab in ll], "n_images": int(len(idx)),
            "images": [str(shard["names"][i]) for i in idx], "encoding": encoding, "lpips": lpips_name,
            "protocol": RECONSTRUCTION_PROTOCOL}


# --------------------------------------------------------------------------- relighting (Fig. 7)

@dataclass
class Reflectance:
    """One method's reflectance for Fig. 7: ``space`` ``"vertex"`` (``albedo`` (3,V), ``weights`` (K,V)) or
    ``"uv"`` (UV maps (3,S,S), (K,S,S)), its lobe ``exponents`` (K,), how the coefficients were obtained
    (``path``, shown in the table) and the coefficients ``beta``."""
    name: str
    space: str
    albedo: np.ndarray
    weights: np.ndarray
    exponents: np.ndarray
    path: str
    beta: np.ndarray


def _names(a) -> list[str]:
    return [str(x) for x in np.asarray(a).reshape(-1)]


def relighting_selection(capture: Mapping[str, np.ndarray], geometry: Mapping[str, np.ndarray], *,
                         view: str = "05_1", input_light: str = "room", holdout: Sequence[str] | None = None,
                         source=None) -> dict[str, Any]:
    """Fig. 7's images, checked against the capture's and the geometry's arrays: the view (``c``: its index in
    the capture, ``g``: in the geometry), the held-out flashes ``held`` (default: every flash but the input's)
    and the linear ``input`` image (``input_light`` ``"room"`` — the room-light shot — or a flash id — the flash
    shot, room + OLAT). ``source``: the capture's path, named in the errors."""
    cap, geo = capture, geometry
    cv, cf = _names(cap["view_names"]), _names(cap["flash_ids"])
    gv = _names(geo["view_names"] if "view_names" in geo else geo["camera_names"])
    gf = _names(geo["flash_ids"])
    if view not in cv or view not in gv:
        raise ReflectmmError(f"relighting: view '{view}' not in the capture ({', '.join(cv)}) and the geometry "
                             f"({', '.join(gv)})", source)
    c, g = cv.index(view), gv.index(view)
    flashes = [f for f in cf if f in gf]
    if input_light != "room" and input_light not in flashes:
        raise ReflectmmError(f"relighting: input '{input_light}' is neither 'room' nor a flash of the capture "
                             f"({', '.join(flashes)})", source)
    held = [f for f in flashes if f != input_light] if not holdout else [str(f) for f in holdout]
    for f in held:
        if f not in flashes:
            raise ReflectmmError(f"relighting: held-out flash '{f}' is not a flash of the capture and the geometry "
                                 f"({', '.join(flashes)})", source)
        if f == input_light:
            raise ReflectmmError(f"relighting: flash '{f}' is the input image and cannot be held out")
    if not held:
        raise ReflectmmError("relighting: no held-out flash left")
    if input_light == "room":
        if "room" not in cap:
            raise ReflectmmError("relighting: the capture has no room-light image ('room' array)", source)
        inp_lin = np.asarray(cap["room"][c], np.float64)
    else:
        inp_lin = np.asarray(cap["olat"][c, cf.index(input_light)], np.float64)
        if "room" in cap:
            inp_lin = inp_lin + np.asarray(cap["room"][c], np.float64)
    return {"c": c, "g": g, "held": held, "input": inp_lin}


def relighting_evaluation(reflectances: Iterable[Reflectance], capture: Mapping[str, np.ndarray],
                          geometry: Mapping[str, np.ndarray], face_model, selection: Mapping[str, Any], *,
                          view: str = "05_1", input_light: str = "room", scale: str = "global",
                          log: Callable[[str], Any] | None = None) -> dict[str, Any]:
    """Fig. 7 for one held-out identity: each method's reflectance (from ONE image of ``view``; e.g. the stage's
    :func:`reflectmm_cli.stages.evaluation_inputs.relighting_reflectances`) re-rendered under the held-out
    flashes of ``selection`` (:func:`relighting_selection`) on the fitted geometry and compared with the captured
    OLAT images. Returns the module's result dict (``summary[name]`` = scale, PSNR, SSIM, per flash)."""
    from .figures import grid
    from .metrics import encode_for_metrics
    from .reconstruction_eval import markdown_table
    from .relighting import capture_targets, relight, relighting_metrics, relighting_rows, scene_from_artifacts
    from .results import evaluation_arrays, to_document

    say = log or (lambda s: None)
    cap, geo, held, inp_lin = capture, geometry, selection["held"], selection["input"]
    targets = capture_targets(cap, view, held)
    scene_v = scene_from_artifacts(cap, geo, face_model.triangles, view)
    scene_uv = None
    renders, metrics, used = {}, {}, {}
    for r in reflectances:
        if r.space == "uv" and scene_uv is None:
            scene_uv = scene_from_artifacts(cap, geo, face_model.triangles, view, uv=face_model.uv)
        scene = scene_uv if r.space == "uv" else scene_v
        renders[r.name] = relight(scene, r.albedo, r.weights, r.exponents, held)
        metrics[r.name] = relighting_metrics(scene, renders[r.name], targets, scale=scale)
        used[r.name] = {"path": r.path, "beta": r.beta}
        say(f"relighting: {r.name}: PSNR {metrics[r.name]['psnr']:.2f} dB, SSIM {metrics[r.name]['ssim']:.4f} "
            f"({used[r.name]['path']})")
    rows = [{"method": n, "coefficients from": used[n]["path"], "PSNR (dB)": f"{v['psnr']:.2f}",
             "SSIM": f"{v['ssim']:.4f}", "scale": f"{v['scale']:.3f}"} for n, v in metrics.items()]
    fid = held[0]
    fig = relighting_rows(scene_v, encode_for_metrics(inp_lin), renders, targets, fid,
                          scales={n: metrics[n]["scale"] for n in metrics})
    doc = {n: {"scale": v["scale"], "psnr": v["psnr"], "ssim": v["ssim"], "per_flash": v["per_flash"],
               "beta": used[n]["beta"]} for n, v in metrics.items()}
    return {"arrays": evaluation_arrays(doc), "table": markdown_table(rows),
            "summary": to_document({n: {k: v for k, v in d.items() if k != "beta"} for n, d in doc.items()}),
            "paper_numbers": {}, "figure": grid(fig),
            "figure_rows": [f"input ({input_light}) | captured OLAT of flash {fid}"] + list(metrics),
            "holdout": held, "view": view, "input": input_light,
            "paths": {n: used[n]["path"] for n in used}, "protocol": RELIGHTING_PROTOCOL}
