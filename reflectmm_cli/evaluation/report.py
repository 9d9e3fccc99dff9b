"""The closing report of a run (``reflectmm evaluate report``): per-identity and mean errors against ground truth
for every stage that has outputs in a workspace, with the PNG previews linked.

Sections (each only when its outputs exist):

* geometry (``fit-geometry/<id>.npz``): landmark RMSE (px, as stored by the fit), vertex error (mm, raw and
  rigidly aligned) and camera-centre error (mm) against ``truth/<id>.npz``;
* the detector's chain (optional): fits from a landmark detector's points where it found a face and from the
  images elsewhere, against reference fits of the same identities with landmarks on every view (the main fits
  when no reference set is given);
* reflectance (``fit-reflectance/<id>.npz``): diffuse albedo and specular albedo errors, observable and flagged
  texels, raw and after the global scale (:mod:`.truth`);
* PCA model (``build-pca/*.npz``): explained variance, reconstruction error of the held-in maps (the training
  identities' fitted maps, projected on the first k diffuse components; specular by the same β);
* representation comparison (``evaluate-representation/*.npz``): its table;
* Table 2 (``evaluate-reconstruction/*.npz``), Table 3 (``evaluate-albedo/*.npz``) and relighting
  (``evaluate-relighting/<id>.npz``): their tables and figures, each with the command that made it;
* model samples before / after finetuning (the ``<stem>_samples_{before,after}.png`` that ``finetune`` writes
  beside its model, ``finetune/*.npz``);
* "paper vs reflectmm": the paper's checked numbers (:mod:`.paper_numbers`) beside ours, with the commands.
"""
from __future__ import annotations

import os
from pathlib import Path
from typing import Any, Callable, Iterable, Mapping, Sequence

import numpy as np

from .truth import camera_errors_by_view, geometry_errors, reflectance_errors

__all__ = ["build_report", "pca_reconstruction", "Read"]

#: One artifact the stage read: (its path, the :class:`~reflectmm_cli.artifacts.Artifact`).  The report reads no
#: file itself: the evaluate-report stage passes each role's artifacts, read one at a time as the report iterates
#: them (``stages/evaluate_report.py``), and the truth as a mapping identity → arrays read when looked up.
Read = tuple[Path, Any]


def pca_reconstruction(model_arrays, maps_list: Sequence[dict], ks: Sequence[int] = (1, 3, 10)) -> dict[str, Any]:
    """RMSE of the held-in maps reconstructed with the first k components (albedo over the model domain, linear
    RGB; Σw with the same β). Returns {k: {albedo_rmse, spec_rmse}} plus 'all'."""
    from reflectmm_cli.model import model_from_arrays, project_maps, sample_model

    m = model_from_arrays(model_arrays)
    d = m.mask
    out: dict[str, Any] = {}
    kk = sorted({min(k, m.n_components) for k in ks} | {m.n_components})
    for k in kk:
        ea, es = [], []
        for mp in maps_list:
            beta = project_maps(m, mp["albedo"], k)
            alb, wts = sample_model(m, beta)
            ea.append(np.mean((alb[:, d] - mp["albedo"][:, d]) ** 2))
            es.append(np.mean((wts.sum(0)[d] - np.asarray(mp["weights"]).sum(0)[d]) ** 2))
        key = "all" if k == m.n_components else str(k)
        out[key] = {"k": int(k), "albedo_rmse": float(np.sqrt(np.mean(ea))), "spec_rmse": float(np.sqrt(np.mean(es)))}
    return out


def _link_path(p: Path, base: Path) -> str:
    """``p`` relative to the report's folder ``base``, with forward slashes (a Markdown link target)."""
    return os.path.relpath(p, base).replace(os.sep, "/")


def _f(x, fmt="{:.4f}") -> str:
    return "–" if x is None or (isinstance(x, float) and not np.isfinite(x)) else fmt.format(x)


def _ident(art, path: Path) -> str:
    return str(art.meta.get("identity") or Path(path).stem)


def _fit_errors(fits: Sequence[Read], truth_by_id: Mapping[str, Any], progress: Callable, desc: str):
    """(identity, artifact, its truth or None, :func:`.truth.geometry_errors`) for each geometry artifact of
    ``fits``, in order."""
    for g, art in progress(fits, desc=desc):
        ident = _ident(art, g)
        tr = truth_by_id.get(ident)
        yield ident, art, tr, geometry_errors(art.arrays, tr if tr is not None else {})


def _geometry_section(geometry: Sequence[Read], truth_by_id: Mapping[str, Any], progress: Callable,
                      doc: dict[str, Any]) -> list[str]:
    """The "Geometry" section: each fit's landmark, vertex and camera errors and their mean."""
    lines: list[str] = []
    if not geometry:
        return lines
    rows, vals = [], []
    for ident, _, _, e in _fit_errors(geometry, truth_by_id, progress, "geometry"):
        vals.append(e)
        doc.setdefault("geometry", {})[ident] = e
        rows.append(f"| {ident} | {_f(e.get('landmark_rmse_px'), '{:.2f}')} | "
                    f"{_f(e.get('vertex_mean_mm'), '{:.2f}')} | {_f(e.get('vertex_rms_mm'), '{:.2f}')} | "
                    f"{_f(e.get('vertex_aligned_mean_mm'), '{:.2f}')} | {_f(e.get('camera_mean_mm'), '{:.2f}')} |")
    mean = {k: float(np.mean([v[k] for v in vals if k in v])) for k in
            ("landmark_rmse_px", "vertex_mean_mm", "vertex_rms_mm", "vertex_aligned_mean_mm", "camera_mean_mm")
            if any(k in v for v in vals)}
    doc.setdefault("geometry_mean", mean)
    lines += ["## Geometry", "",
              "| identity | landmark RMSE (px) | vertex error, mean (mm) | vertex error, RMS (mm) | "
              "vertex error, rigidly aligned (mm) | camera centre error (mm) |", "|---|---:|---:|---:|---:|---:|",
              *rows,
              f"| **mean** | {_f(mean.get('landmark_rmse_px'), '{:.2f}')} | {_f(mean.get('vertex_mean_mm'), '{:.2f}')}"
              f" | {_f(mean.get('vertex_rms_mm'), '{:.2f}')} | {_f(mean.get('vertex_aligned_mean_mm'), '{:.2f}')}"
              f" | {_f(mean.get('camera_mean_mm'), '{:.2f}')} |", "",
              "Vertex errors are per-vertex distances to the true mesh (same topology) in model space; "
              "without a truth file the errors fit-geometry stored (run with --truth) are shown.", ""]
    return lines


def _taken(observations: Sequence[Read], doc: dict[str, Any]) -> list[str]:
    """The lines that list the views and flashes of each identity's observations (unwrap-uv): which images each
    reflectance fit took (``unwrap-uv --views`` / ``--flashes`` may leave some out); their counts go to ``doc``."""
    taken: dict[str, tuple[list[str], list[str]]] = {}
    for op, art in observations:
        if "view_names" in art.arrays and "flash_ids" in art.arrays:
            taken[_ident(art, op)] = ([str(v) for v in np.asarray(art["view_names"]).reshape(-1)],
                                      [str(f) for f in np.asarray(art["flash_ids"]).reshape(-1)])
    if not taken:
        return []
    doc["observations"] = {i: {"views": len(v), "flashes": len(f)} for i, (v, f) in taken.items()}
    lines = ["The views and flashes each fit took (unwrap-uv; with `--views` / `--flashes` `landmarked` or `trusted` "
             "it leaves out those of cameras that were not placed well; docs/capture.md, \"unwrap-uv\"):", ""]
    lines += [f"- {i}: {len(v)} views ({', '.join(v)}); {len(f)} flashes ({', '.join(f)})"
              for i, (v, f) in sorted(taken.items())]
    return lines + [""]


def _reflectance_section(maps: Sequence[Read], truth_by_id: Mapping[str, Any], progress: Callable,
                        doc: dict[str, Any], base: Path, observations: Sequence[Read] = ()
                        ) -> tuple[list[str], list[tuple[Path, dict]]]:
    """The "Reflectance maps" section (errors against the truth, the views and flashes each fit took, previews)
    and each map's (path, arrays)."""
    lines: list[str] = []
    maps_arrays: list[tuple[Path, dict]] = []
    if not maps:
        return lines, maps_arrays
    taken_lines = _taken(observations, doc)
    rows, vals = [], []
    previews = []
    for mp, art in progress(maps, desc="reflectance"):
        ident = _ident(art, mp)
        maps_arrays.append((Path(mp), art.arrays))
        previews += [q for q in sorted(Path(mp).parent.glob(f"{Path(mp).stem}*.png"))]
        tr = truth_by_id.get(ident)
        if tr is None:
            continue
        e = reflectance_errors(art.arrays, tr)
        doc.setdefault("reflectance", {})[ident] = e
        vals.append(e)
        o, fl, so = e["raw"]["observable"], e["raw"]["flagged"], e["scaled"]["observable"]
        frac = e["texels"]["flagged"] / max(e["texels"]["all"], 1)
        rows.append(f"| {ident} | {_f(o['albedo_rmse'])} | {_f(o['albedo_rel'], '{:.2%}')} | "
                    f"{_f(o.get('spec_rmse'))} | {_f(o.get('spec_rel'), '{:.2%}')} | "
                    f"{_f(fl['albedo_rel'], '{:.2%}')} | {_f(fl.get('spec_rel'), '{:.2%}')} | "
                    f"{_f(e['scale'], '{:.3f}')} | {_f(so['albedo_rel'], '{:.2%}')} | "
                    f"{_f(so.get('spec_rel'), '{:.2%}')} | {frac:.1%} | "
                    f"{_f(o.get('albedo_rel_median'), '{:.2%}')} | {_f(o.get('spec_ratio_median'), '{:.2f}')} |")
    if vals:
        def mean_of(mode, reg, key):
            xs = [v[mode][reg].get(key) for v in vals]
            xs = [x for x in xs if x is not None and np.isfinite(x)]
            return float(np.mean(xs)) if xs else float("nan")

        mean = {f"{mode}.{reg}.{key}": mean_of(mode, reg, key) for mode in ("raw", "scaled")
                for reg in ("observable", "flagged", "all")
                for key in ("albedo_rmse", "albedo_rel", "spec_rmse", "spec_rel", "albedo_rel_median",
                            "spec_ratio_median")}
        doc["reflectance_mean"] = mean
        lines += ["## Reflectance maps", "",
                  "Diffuse albedo: RMSE over texels and linear RGB channels, relative = RMSE / RMS(truth). "
                  "Specular albedo: Σw against the truth's directional albedo at normal view. *Flagged* texels "
                  "were ill-conditioned and filled from the mirror/neighbourhood. *Scaled*: after one global "
                  "least-squares scale (flash intensity ↔ reflectance ambiguity). The RMS columns are dominated by a few "
                  "texels (sharp highlights the lobes cannot represent, grazing-only texels at the border); the last "
                  "two columns are the typical texel: the median per-texel relative albedo error and the median of "
                  "Σw / true specular albedo (1 = right).", "",
                  "| identity | albedo RMSE | albedo rel. | spec RMSE | spec rel. | albedo rel. (flagged) | "
                  "spec rel. (flagged) | scale | albedo rel. (scaled) | spec rel. (scaled) | flagged | "
                  "albedo rel. (median texel) | Σw / truth (median) |",
                  "|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|", *rows,
                  f"| **mean** | {_f(mean['raw.observable.albedo_rmse'])} | "
                  f"{_f(mean['raw.observable.albedo_rel'], '{:.2%}')} | {_f(mean['raw.observable.spec_rmse'])} | "
                  f"{_f(mean['raw.observable.spec_rel'], '{:.2%}')} | {_f(mean['raw.flagged.albedo_rel'], '{:.2%}')}"
                  f" | {_f(mean['raw.flagged.spec_rel'], '{:.2%}')} | | "
                  f"{_f(mean['scaled.observable.albedo_rel'], '{:.2%}')} | "
                  f"{_f(mean['scaled.observable.spec_rel'], '{:.2%}')} | | "
                  f"{_f(mean['raw.observable.albedo_rel_median'], '{:.2%}')} | "
                  f"{_f(mean['raw.observable.spec_ratio_median'], '{:.2f}')} |", ""]
    else:
        lines += ["## Reflectance maps", "", f"{len(maps)} fitted identities; no matching ground truth.", ""]
    lines += taken_lines
    if previews:
        lines += ["Previews: " + ", ".join(f"[{q.name}]({_link_path(q, base)})" for q in previews[:60]), ""]
    return lines, maps_arrays


def _pca_sections(models: Iterable[Read], maps_arrays: Sequence[tuple[Path, dict]], doc: dict[str, Any],
                 base: Path) -> list[str]:
    """One "PCA reflectance model" section per (readable) model: explained variance, reconstruction of the
    held-in maps, previews."""
    lines: list[str] = []
    for mpath, art in models:
        ev = np.asarray(art["explained_variance_ratio"], np.float64)
        cum = np.cumsum(ev)
        ids = [str(x) for x in art["ids"]]
        entry: dict[str, Any] = {"n_components": int(ev.size), "n_identities": len(ids),
                                 "explained_variance_ratio": ev[:10].tolist()}
        lines += [f"## PCA reflectance model (`{_link_path(Path(mpath), base)}`)", "",
                  f"{len(ids)} identities, {ev.size} components. Explained variance of the diffuse albedo "
                  "(cumulative): " + ", ".join(f"k={k + 1}: {100 * cum[k]:.1f}%" for k in range(min(10, ev.size))),
                  ""]
        # held-in maps: those of the training ids among the reflectance maps
        held = [a for mp, a in maps_arrays if mp.stem in ids]
        if held:
            rec = pca_reconstruction(art.arrays, held)
            entry["reconstruction"] = rec
            lines += ["Reconstruction of the held-in maps from the first k components (RMSE, linear):", "",
                      "| k | albedo RMSE | spec albedo RMSE |", "|---:|---:|---:|"]
            lines += [f"| {v['k']} | {v['albedo_rmse']:.2e} | {v['spec_rmse']:.2e} |" for v in rec.values()]
            lines.append("")
        pngs = sorted(Path(mpath).parent.glob(f"{Path(mpath).stem}*.png"))
        if pngs:
            lines += ["Previews: " + ", ".join(f"[{q.name}]({_link_path(q, base)})" for q in pngs), ""]
        doc.setdefault("pca", {})[Path(mpath).stem] = entry
    return lines


def _representation_sections(representation: Iterable[Read], doc: dict[str, Any], base: Path) -> list[str]:
    """One "Representation comparison" section per evaluate-representation artifact."""
    lines: list[str] = []
    for rpath, art in representation:
        if art.meta.get("evaluation") != "representation":
            continue
        lines += [f"## Representation comparison (`{_link_path(Path(rpath), base)}`)", "", art.meta.get("table", ""),
                  ""]
        png = Path(rpath).with_suffix(".png")
        if png.is_file():
            lines += [f"![representations]({_link_path(png, base)})", ""]
        doc.setdefault("representation", {})[Path(rpath).stem] = art.meta.get("margin")
    return lines


def _detected_section(detected: Sequence[Read], truth_by_id: Mapping[str, Any], progress: Callable,
                      doc: dict[str, Any], reference: Sequence[Read] = ()) -> list[str]:
    """The "Landmarks from a detector" section: fits whose landmarks a detector gave (none where it found no
    face) against fits of the same identities with landmarks on every view: ``reference`` if given, else the
    run's main fits (``doc["geometry"]``)."""
    if not detected:
        return []
    main = doc.get("geometry", {})
    if reference:
        main = {ident: e for ident, _, _, e in _fit_errors(reference, truth_by_id, progress, "geometry (reference)")}
        doc["reference_geometry"] = main
    rows, ratios, out = [], [], {}
    for ident, art, tr, e in _fit_errors(detected, truth_by_id, progress, "geometry (detector)"):
        cams = camera_errors_by_view(art.arrays, tr) if tr is not None else {}
        names = [str(x) for x in np.asarray(art["view_names"])]
        evidence = art.get("view_evidence")  # (fits before views without landmarks: every view had them)
        marked = [True] * len(names) if evidence is None else [str(x).startswith("landmarks")
                                                               for x in np.asarray(evidence)]
        with_lm = [cams[n] for n, m in zip(names, marked) if m and n in cams]
        without = [cams[n] for n, m in zip(names, marked) if not m and n in cams]
        ref = main.get(ident, {}).get("vertex_rms_mm")
        ratio = e["vertex_rms_mm"] / ref if ref and "vertex_rms_mm" in e else float("nan")
        if np.isfinite(ratio):
            ratios.append(ratio)
        out[ident] = {**e, "views_with_landmarks": int(sum(marked)), "views": len(names),
                      "vertex_rms_all_landmarks_mm": ref, "ratio": ratio,
                      "camera_max_with_landmarks_mm": max(with_lm) if with_lm else None,
                      "camera_max_without_landmarks_mm": max(without) if without else None}
        rows.append(f"| {ident} | {sum(marked)} / {len(names)} | {_f(ref, '{:.2f}')} | "
                    f"{_f(e.get('vertex_rms_mm'), '{:.2f}')} | {_f(ratio, '{:.2f}')} | "
                    f"{_f(out[ident]['camera_max_with_landmarks_mm'], '{:.1f}')} | "
                    f"{_f(out[ident]['camera_max_without_landmarks_mm'], '{:.1f}')} |")
    med = float(np.median(ratios)) if ratios else float("nan")
    doc["detected"] = {"identities": out, "median_ratio": med}
    what = ("the annotated reference: the same captures with landmarks on every view (in the demo the synthetic "
            "ones, 1 px noise, in the role of hand-made ones; recipes/synthetic.toml, stages `preprocess-annotated` "
            "to `fit-geometry-annotated`)" if reference else "the fits above")
    return ["## Landmarks from a detector", "",
            "Fits from a detector's landmarks, which exist only on the views where it found a face; the other "
            f"views are placed by the rig and registered by their images. Set against {what}.", "",
            "| identity | views with landmarks | vertex RMS (mm), all landmarks | vertex RMS (mm), detector | × | "
            "camera centre error, max (mm): views with landmarks | views without |",
            "|---|---:|---:|---:|---:|---:|---:|", *rows, "",
            f"Median ratio {_f(med, '{:.2f}')} (the target is ≤ 1.3; docs/benchmarks.md, \"The demo on dlib's "
            f"landmarks\", \"The detector's per-camera offsets\", \"The flash rounds' optimisation budget\", "
            "\"The joint rounds\" and \"What holds the joint rounds back\", say where it stands and what limits it).",
            ""]


def build_report(workspace: Path, out_md: Path, geometry: Sequence[Read] = (), maps: Sequence[Read] = (),
                 models: Iterable[Read] = (), truth: Mapping[str, Any] | None = None,
                 representation: Iterable[Read] = (), progress: Callable = lambda it, **k: it,
                 reconstruction: Sequence[Read] = (), albedo: Sequence[Read] = (), relighting: Sequence[Read] = (),
                 finetune: Sequence[Path] = (), expressive: Sequence[Read] = (),
                 viewer: Sequence[Path] = (), detected: Sequence[Read] = (),
                 reference: Sequence[Read] = (), observations: Sequence[Read] = ()) -> tuple[str, dict[str, Any]]:
    """Markdown text and a document of numbers, from what the stage read (:data:`Read` pairs; nothing is read
    here).  ``geometry`` / ``maps``: geometry and reflectance-maps artifacts; ``truth``: identity → synth-truth
    arrays; ``models``: reflectance models; ``representation`` / ``reconstruction`` / ``albedo`` / ``relighting`` /
    ``expressive``: ``evaluation`` artifacts (each section takes those of its kind; "Paper vs reflectmm" is written
    when ``reconstruction`` or ``albedo`` is non-empty, i.e. when files were given, readable or not);
    ``finetune``: finetuned model paths (their sample PNGs are shown); ``viewer``: pages of ``reflectmm view``
    (linked); ``detected``: geometry artifacts fitted from a detector's landmarks, compared with ``reference``
    (fits of the same identities with landmarks on every view) or, without it, with ``geometry``;
    ``observations``: uv-observations artifacts (their ``view_names`` and ``flash_ids`` are listed under the
    reflectance maps)."""
    base = Path(out_md).parent
    truth_by_id = truth if truth is not None else {}
    doc: dict[str, Any] = {}
    lines = [f"# reflectmm report — `{Path(workspace).name}`", ""]
    if not truth_by_id:
        lines += ["No ground truth found: errors against truth are not available.", ""]
    lines += _geometry_section(geometry, truth_by_id, progress, doc)
    lines += _detected_section(detected, truth_by_id, progress, doc, reference)
    refl_lines, maps_arrays = _reflectance_section(maps, truth_by_id, progress, doc, base, observations)
    lines += refl_lines
    lines += _pca_sections(models, maps_arrays, doc, base)
    lines += _representation_sections(representation, doc, base)
    lines += paper_sections(base, reconstruction=reconstruction, albedo=albedo, relighting=relighting,
                            finetune=finetune, expressive=expressive, doc=doc)
    pages = [Path(v) for v in viewer if Path(v).is_file()]
    if pages:
        lines += ["## Look at the model", "",
                  "Interactive pages (one self-contained file each; open in a browser, docs/viewer.md): "
                  + ", ".join(f"[{_link_path(v, base)}]({_link_path(v, base)})" for v in pages) + ".", ""]
    return "\n".join(lines) + "\n", doc


def _evaluations(items: Iterable[Read], kind: str) -> list[Read]:
    return [(Path(p), art) for p, art in items if art.meta.get("evaluation") == kind]


def _command(art) -> list[str]:
    cmd = art.meta.get("command")
    return [f"Made by (from the workspace root): `{cmd}`", ""] if cmd else []


def _ceiling_text(summary: Mapping[str, Any]) -> str:
    """The oracle's gain of a :func:`~.face_metrics.mean_ci` summary, ``+0.12 ± 0.32 dB``, and whether its interval
    holds zero (then the ceiling itself is not measured at this sample size)."""
    from .tables import gain_text, interval_holds_zero

    text = gain_text(summary)
    if np.isfinite(float(summary.get("half_width", float("nan")))) and interval_holds_zero(summary):
        text += ", an interval that holds zero: at this number of test images no ceiling above zero is measured"
    return text


def paper_sections(base: Path, *, reconstruction: Sequence[Read] = (), albedo: Sequence[Read] = (),
                   relighting: Sequence[Read] = (), finetune: Sequence[Path] = (), expressive: Sequence[Read] = (),
                   doc: dict[str, Any] | None = None) -> list[str]:
    """Markdown lines of the Table 2, Table 3, relighting, model-sample and "paper vs reflectmm" sections (each
    only when its inputs are given); numbers go into ``doc``."""
    from .paper_numbers import paper_vs_ours_rows
    from .reconstruction_eval import markdown_table

    doc = {} if doc is None else doc
    lines: list[str] = []
    ours: dict[str, float] = {}
    commands: dict[str, str] = {}
    intervals: dict[str, float] = {}  # half widths of the 95 % intervals, where the number has one
    ceiling = None  # the oracle's encoder-only PSNR gain over the control (mean_ci summary), when Table 2 has it

    def take(art):
        for k, v in (art.meta.get("paper_numbers") or {}).items():
            if v is not None:
                ours[k] = float(v)
                commands[k] = art.meta.get("command", "")
        pair = (art.meta.get("params") or {}).get("gain") or ()
        if len(pair) == 2 and (art.meta.get("paper_numbers") or {}).get("table2.psnr_gain_finetune") is not None:
            # Table 2's gain, from this artifact: its paired interval
            g = ((art.meta.get("gains") or {}).get(f"{pair[0]} - {pair[1]}") or {}).get("psnr") or {}
            if g.get("half_width") is not None and np.isfinite(float(g["half_width"])):
                intervals["table2.psnr_gain_finetune"] = float(g["half_width"])

    for path, art in _evaluations(reconstruction, "reconstruction"):
        take(art)
        lines += [f"## Table 2: reconstruction of in-the-wild test images (`{_link_path(path, base)}`)", "",
                  art.meta.get("protocol", ""), "", art.meta.get("table", ""), "",
                  f"{len(art.meta.get('images', []))} images; LPIPS: {art.meta.get('lpips', 'off')}.", ""]
        png = path.with_suffix(".png")
        if png.is_file() and art.meta.get("figure_rows"):
            lines += [f"![Table 2 figure]({_link_path(png, base)})", "",
                      "Columns: input | reconstruction | diffuse | specular | error; rows: "
                      + "; ".join(art.meta["figure_rows"]) + ".", ""]
        if art.meta.get("gains_table"):
            lines += ["### The finetuning gain, per image (mean ± 95 % CI)", "",
                      "A − B of each test image, averaged (for the reflectance errors B − A, so that a positive "
                      "gain is an improvement). `initial` is the control run: the finetuned run's schedule with "
                      "the model frozen, so the gain measures the model update alone (docs/evaluation.md, "
                      "\"A fair Table 2\")."
                      + (" `oracle - initial`: the oracle (a model of the same size built from the training "
                         "identities' true reflectance) with the control's encoder schedule, over the control: what "
                         "the best model of this size for this population gives at this encoder budget (a finetuned "
                         "model can pass it in PSNR by taking up light and shadow; docs/evaluation.md, \"The oracle "
                         "row\")." if "oracle - initial" in (art.meta.get("gains") or {}) else ""),
                      "", art.meta["gains_table"], ""]
            lines += [f"**Not at equal encoder budget:** `{k}`: {'; '.join(v)}." for k, v in
                      (art.meta.get("unequal_budgets") or {}).items()] + (
                         [""] if art.meta.get("unequal_budgets") else [])
            if art.meta.get("psnr_gap_sentence"):
                lines += [art.meta["psnr_gap_sentence"], ""]
        lines += _command(art)
        doc.setdefault("table2", {})[path.stem] = art.meta.get("summary")
        if art.meta.get("gains"):
            doc.setdefault("table2_gains", {})[path.stem] = art.meta["gains"]
            if "oracle - initial" not in (art.meta.get("unequal_budgets") or {}):  # a ceiling at the same budget only
                ceiling = ((art.meta["gains"].get("oracle - initial") or {}).get("psnr") or None)
    for path, art in _evaluations(expressive, "expressive"):
        lines += [f"## Expressive power on held-out identities (`{_link_path(path, base)}`)", "",
                  art.meta.get("protocol", ""), "", art.meta.get("table", ""), ""]
        gap = art.meta.get("gap_closed") or {}
        if gap:
            lines += [f"Gap to the oracle closed by finetuning: diffuse albedo {100 * gap['albedo']:.0f} %, lobe "
                      f"weights {100 * gap['weights']:.0f} %.", ""]
        lines += _command(art)
        doc.setdefault("expressive", {})[path.stem] = {"means": art.meta.get("means"), "gap_closed": gap}
    for path, art in _evaluations(albedo, "albedo"):
        take(art)
        lines += [f"## Table 3: albedo of held-out identities (`{_link_path(path, base)}`)", "",
                  art.meta.get("protocol", ""), "", "Identities: " + ", ".join(art.meta.get("identities", [])) + ".",
                  "", art.meta.get("table", ""), ""] + _command(art)
        doc.setdefault("table3", {})[path.stem] = art.meta.get("summary")
    rel = _evaluations(relighting, "relighting")
    if rel:
        lines += ["## Relighting (Fig. 7)", "", rel[0][1].meta.get("protocol", ""), ""]
        for path, art in rel:
            ident = art.meta.get("identity", path.stem)
            lines += [f"### Identity {ident}: view {art.meta.get('view')}, input {art.meta.get('input')}, held-out "
                      f"flashes {', '.join(art.meta.get('holdout', []))} (`{_link_path(path, base)}`)", "",
                      art.meta.get("table", ""), ""]
            png = path.with_suffix(".png")
            if png.is_file():
                lines += [f"![relighting {ident}]({_link_path(png, base)})", ""]
            lines += _command(art)
            doc.setdefault("relighting", {})[str(ident)] = art.meta.get("summary")
    shown = []
    for mp in finetune:
        mp = Path(mp)
        pair = [mp.with_name(f"{mp.stem}_samples_{w}.png") for w in ("before", "after")]
        if any(q.is_file() for q in pair):
            shown.append((mp, pair))
    if shown:
        lines += ["## Model samples before and after finetuning", "",
                  "Random samples (β ~ N(0, 1)) of the initial and the finetuned per-vertex model under a white frontal "
                  "point light (the paper's supp. Figs 8–9), written by `reflectmm finetune`.", ""]
        for mp, (b, a) in shown:
            lines += [f"`{_link_path(mp, base)}`:", "", "| before | after |", "|---|---|",
                      "| " + " | ".join(f"![{w}]({_link_path(q, base)})" if q.is_file() else "missing"
                                        for w, q in (("before", b), ("after", a))) + " |", ""]
    if reconstruction or albedo:
        rows = paper_vs_ours_rows(ours, {k: f"`{v}`" if v else "" for k, v in commands.items()}, intervals)
        lines += ["## Paper vs reflectmm", "",
                  "The paper measures real photographs and Light Stage scans; reflectmm the synthetic world with exact "
                  "ground truth, so trends and magnitudes compare, not equal numbers. Table 3's reflectmm numbers are "
                  "the raw (unscaled) PSNR of the method the evaluation calls 'ours'; Table 2's gain is the mean PSNR "
                  "difference of the two methods of its `gain` param."
                  + (f" Its ceiling in this world, the oracle's gain over the control at the same encoder budget, is "
                     f"{_ceiling_text(ceiling)} (Table 2's gains table)." if ceiling is not None else ""),
                  "", markdown_table(rows), ""]
        doc["paper_vs_reflectmm"] = ours
    return lines
