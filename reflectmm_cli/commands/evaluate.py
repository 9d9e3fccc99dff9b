"""``reflectmm evaluate``: errors against ground truth, the representation comparison and the closing report
(DESIGN.md §1 step 8). Thin layer over :mod:`reflectmm_cli.evaluation`.
"""

from __future__ import annotations

import json
from pathlib import Path

import click
import numpy as np

from reflectmm_cli.artifacts import atomic_write_text, read_artifact, write_artifact, write_png
from reflectmm_cli.commands._common import emit, json_option, output_option, parse_ids, run_stage_cli, workspace_option
from reflectmm_cli.errors import ReflectmmError
from reflectmm_cli.progress import log, progress
from reflectmm_cli.stages import StageContext, default_workspace, register_stage

EVAL_KIND = "evaluation"

# --------------------------------------------------------------------------- evaluate truth


def _flatten(prefix: str, obj, out: dict) -> dict:
    if isinstance(obj, dict):
        for k, v in obj.items():
            _flatten(f"{prefix}.{k}" if prefix else str(k), v, out)
    elif isinstance(obj, (int, float, np.floating, np.integer)):
        out[prefix] = float(obj)
    return out


def _is_vertex_reflectance(path: Path) -> bool:
    """A plain NPZ (no artifact meta) with per-vertex ``albedo (V, 3)`` (reflectmm_cli.evaluation.external)."""
    try:
        with np.load(path, allow_pickle=False) as z:
            return "__meta__" not in z.files and "albedo" in z.files and z["albedo"].ndim == 2
    except (OSError, ValueError):
        return False


def evaluate_truth(maps_path: Path | None, truth_path: Path, geometry_path: Path | None = None,
                   face_model_path: Path | None = None) -> dict:
    """Library entry: the error document of fitted maps (and geometry) against a synth-truth file, or against
    per-vertex reflectance (plain NPZ, docs/artifacts.md) laid out in UV with the face model ``face_model_path``."""
    from reflectmm_cli.evaluation.truth import geometry_errors, reflectance_errors

    doc: dict = {}
    if _is_vertex_reflectance(Path(truth_path)):
        from reflectmm_cli.evaluation.external import read_vertex_reflectance, vertex_reflectance_to_uv
        from reflectmm_cli.geometry import load_face_model

        if maps_path is None:
            raise ReflectmmError("per-vertex reflectance truth: give --maps", truth_path)
        if face_model_path is None:
            raise ReflectmmError("per-vertex reflectance truth needs the face model of its vertices: pass "
                                 "--face-model", truth_path)
        fm = load_face_model(face_model_path)
        maps = read_artifact(maps_path, "reflectance-maps")
        S = int(np.asarray(maps["albedo"]).shape[-1])
        t_uv = vertex_reflectance_to_uv(read_vertex_reflectance(truth_path, fm.n_vertices), fm.uv, fm.triangles, S)
        doc["reflectance"] = reflectance_errors(maps.arrays, t_uv)
        doc["truth_format"] = "per-vertex reflectance"
        return doc
    truth = read_artifact(truth_path)
    if truth.kind not in ("synth-truth", "reflectance-maps"):
        raise ReflectmmError(f"is a '{truth.kind}' artifact, expected a 'synth-truth' artifact", truth_path)
    if maps_path is not None:
        maps = read_artifact(maps_path, "reflectance-maps")
        doc["reflectance"] = reflectance_errors(maps.arrays, truth.arrays)
    if geometry_path is not None:
        geo = read_artifact(geometry_path, "geometry")
        doc["geometry"] = geometry_errors(geo.arrays, truth.arrays)
    if not doc:
        raise ReflectmmError("evaluate truth: give --maps and/or --geometry")
    return doc


def _truth_outputs(ctx: StageContext) -> list[Path]:
    return [ctx.output_path()]


# version 2: spec_ratio_median
@register_stage("evaluate-truth", version=3, per_identity=True, outputs=_truth_outputs,
                help="errors of fitted maps / geometry against ground truth")
def run_evaluate_truth(ctx: StageContext) -> list[Path]:
    maps = ctx.input_list("maps", required=False)
    geo = ctx.input_list("geometry", required=False)
    fms = ctx.input_list("face_model", required=False)
    doc = evaluate_truth(maps[0] if maps else None, ctx.input("truth"), geo[0] if geo else None,
                         fms[0] if fms else None)
    flat = _flatten("", doc, {})
    names = sorted(flat)
    out = ctx.output_path()
    write_artifact(out, EVAL_KIND, {"names": np.array(names, dtype=str),
                                    "values": np.array([flat[n] for n in names], np.float64)},
                   params=ctx.resolved_params(), inputs=ctx.input_refs(out.parent), producer=ctx.producer(),
                   cache_key=ctx.cache_key, extra_meta={"evaluation": "truth", "identity": ctx.identity,
                                                        "errors": doc})
    return [out]


@click.group("evaluate")
def evaluate_group():
    """Evaluate fitted maps, representations and a whole run (PSNR/SSIM/LPIPS, errors against ground truth)."""


@evaluate_group.command("truth")
@click.option("--id", "identity", required=True, help="Identity (names the output).")
@click.option("--maps", type=click.Path(dir_okay=False, path_type=Path), default=None,
              help="reflectance-maps artifact (default <ws>/fit-reflectance/<id>.npz if present).")
@click.option("--truth", "truth", type=click.Path(dir_okay=False, path_type=Path), default=None,
              help="synth-truth artifact (default <ws>/truth/<id>.npz or <ws>/synth/truth/<id>.npz).")
@click.option("--geometry", type=click.Path(dir_okay=False, path_type=Path), default=None,
              help="geometry artifact to evaluate too.")
@click.option("--face-model", type=click.Path(dir_okay=False, path_type=Path), default=None,
              help="face model whose vertices a per-vertex reflectance truth (plain NPZ) refers to.")
@workspace_option
@output_option
def evaluate_truth_cmd(identity, maps, truth, geometry, face_model, workspace, output):
    """Errors of one identity's fitted maps (and geometry) against the ground truth; JSON on stdout.

    Diffuse albedo RMSE / relative error in linear RGB, specular albedo Σw against spec_albedo, separately for
    observable and flagged texels, raw and after one global least-squares scale. Writes an `evaluation`
    artifact (<ws>/evaluate-truth/<id>.npz or --output).
    """
    ws = (workspace or default_workspace()).resolve()
    if maps is None and (ws / "fit-reflectance" / f"{identity}.npz").is_file():
        maps = ws / "fit-reflectance" / f"{identity}.npz"
    if truth is None:
        from reflectmm_cli.evaluation.report import find_truth_dir

        td = find_truth_dir(ws)
        if td is None:
            raise ReflectmmError(f"no --truth given and no truth folder in {ws} (looked for truth/, synth/truth/)")
        truth = td / f"{identity}.npz"
    inputs = {"truth": [truth]}
    if maps is not None:
        inputs["maps"] = [maps]
    if geometry is not None:
        inputs["geometry"] = [geometry]
    if face_model is not None:
        inputs["face_model"] = [face_model]
    paths = run_stage_cli("evaluate-truth", workspace=workspace, identity=identity, inputs=inputs, output=output)
    art = read_artifact(paths[0], EVAL_KIND)
    click.echo(json.dumps({"outputs": [str(p) for p in paths], "identity": identity,
                           "errors": art.meta["errors"]}, indent=2, sort_keys=True))


# --------------------------------------------------------------------------- evaluate representation

REP_DEFAULTS = {"exponents_sets": "8;16;32;64;1,8,64", "holdout": "05,09", "baselines": True, "solver": "fast",
                "symmetry": 1.0, "symmetry_mode": "adaptive", "loss": "l1", "prior": 1e-4, "prior_tail": 100.0,
                "lpips_net": "alex",
                "space": "auto",
                "max_identities": 0}


def _by_identity(paths: list[Path], kind: str) -> dict[str, Path]:
    from reflectmm_cli.artifacts import read_meta

    out = {}
    for p in paths:
        meta = read_meta(p)
        out[str(meta.get("identity") or Path(p).stem)] = Path(p)
    return out


def _image_space_renderers(ctx: StageContext, ids: list[str], space: str):
    """Per identity an ImageSpaceRenderer when captures, geometries and a face model are given (space image/auto);
    None for UV space."""
    caps = ctx.input_list("capture", required=False)
    geos = ctx.input_list("geometry", required=False)
    fms = ctx.input_list("face_model", required=False)
    if space == "uv":
        return None
    have = bool(caps and geos and fms)
    if have:
        cap_by, geo_by = _by_identity(caps, "capture"), _by_identity(geos, "geometry")
        missing = [i for i in ids if i not in cap_by or i not in geo_by]
        have = not missing
    if not have:
        if space == "image":
            raise ReflectmmError("evaluate representation --space image needs a capture, a geometry and a face model "
                                 "for every identity (inputs capture, geometry, face_model)"
                                 + (f"; missing for {', '.join(missing)}" if caps and geos and fms else ""))
        log.info("evaluate representation: no captures/geometry/face model for every identity: UV-space "
                 "re-rendering")
        return None
    from reflectmm_cli.evaluation.image_space import ImageSpaceRenderer
    from reflectmm_cli.geometry.face_model import load_face_model

    try:
        from reflectmm_cli.geometry import has_embree
        if not has_embree():
            raise ImportError
    except ImportError:
        if space == "image":
            raise ReflectmmError("evaluate representation --space image needs Embree (embreex)") from None
        log.warning("evaluate representation: Embree unavailable: UV-space re-rendering")
        return None
    fm = load_face_model(fms[0])
    return [ImageSpaceRenderer(read_artifact(cap_by[i], "capture").arrays, read_artifact(geo_by[i], "geometry").arrays,
                               fm.triangles, fm.uv, name=i) for i in ids]


def _rep_outputs(ctx: StageContext) -> list[Path]:
    out = ctx.output_path()
    return [out, out.with_suffix(".md"), out.with_suffix(".png")]


# version 2: image-space region inside the maps' domain; symmetry_mode. version 3: prior_tail. version 4: adaptive
@register_stage("evaluate-representation", version=4, per_identity=False, outputs=_rep_outputs,
                help="the paper's Table 1: global exponents vs multi-lobe on held-out flashes")
def run_evaluate_representation(ctx: StageContext) -> list[Path]:
    from reflectmm_cli.evaluation.metrics import load_lpips
    from reflectmm_cli.evaluation.representation import (comparison_figure, compare_representations,
                                                         default_representations, margin_of_multilobe,
                                                         markdown_table)

    p = {**REP_DEFAULTS, **{k: v for k, v in ctx.params.items() if v is not None}}
    files = ctx.input_list("observations")
    if int(p["max_identities"]) > 0 and len(files) > int(p["max_identities"]):
        log.info(f"evaluate representation: using the first {int(p['max_identities'])} of {len(files)} identities "
                 "(max_identities)")
        files = files[: int(p["max_identities"])]
    lp_files = ctx.input_list("lpips_weights", required=False)
    lp = load_lpips(lp_files[0] if lp_files else None, str(p["lpips_net"]))
    reps = default_representations(str(p["exponents_sets"]), bool(p["baselines"]))
    holdout = [h.strip() for h in str(p["holdout"]).split(",") if h.strip()]
    obs, ids = [], []
    for f in files:
        art = read_artifact(f, "uv-observations")
        obs.append(art.arrays)
        ids.append(str(art.meta.get("identity") or Path(f).stem))
    kw = {k: p[k] for k in ("solver", "symmetry", "symmetry_mode", "loss", "prior", "prior_tail")}
    space = str(p["space"])
    if space not in ("auto", "uv", "image"):
        raise ReflectmmError(f"evaluate representation: space must be auto, uv or image, got {space!r}")
    isr = _image_space_renderers(ctx, ids, space)
    res = compare_representations(obs, ids, reps, holdout, lp, fit_kwargs=kw,
                                  progress=lambda it, **k: progress(it, unit="id", **k), image_space=isr)
    out = ctx.output_path()
    table = markdown_table(res)
    margin = margin_of_multilobe(res)
    arrays = {"representations": np.array([r.name for r in reps], dtype=str), "ids": np.array(ids, dtype=str),
              "psnr": res.psnr, "ssim": res.ssim, "psnr_pairs": res.psnr_pairs, "ssim_pairs": res.ssim_pairs,
              "train_psnr": res.train_psnr, "fit_seconds": res.fit_seconds,
              "outside_domain": np.asarray(res.outside_domain, np.float64),
              "holdout_flashes": np.array(holdout, dtype=str)}
    if res.lpips is not None:
        arrays["lpips"] = res.lpips
    exps = {r.name: list(r.exponents) for r in reps}
    write_artifact(out, EVAL_KIND, arrays, params={**{k: p[k] for k in REP_DEFAULTS}},
                   inputs=ctx.input_refs(out.parent), producer=ctx.producer(), cache_key=ctx.cache_key,
                   extra_meta={"evaluation": "representation", "space": res.space, "exponents": exps,
                               "protocol": "held-out flashes (all views); same training pairs for every "
                                           "representation; metrics on clip(x,0,1)^(1/1.2), peak 1",
                               "lpips": "on" if lp is not None else "off (no weights given)",
                               "figure": {"identity": res.figure.get("identity"), "view": res.figure.get("view"),
                                          "flash": res.figure.get("flash")},
                               "margin": margin, "table": table})
    head = ("# Representation comparison\n\nFigure: `" + out.with_suffix(".png").name + "` — identity "
            f"{res.figure.get('identity')}, view {res.figure.get('view')}, flash {res.figure.get('flash')}: "
            "truth | " + " | ".join(r.name for r in reps) + " (top), absolute error of the display encoding ×20, inferno colormap (bottom).\n\n")
    md = head + table
    if margin:
        md += (f"\n{margin['multilobe']} vs the best global exponent ({margin['best_global']}): "
               f"{margin['psnr_margin_db']:+.2f} dB PSNR, {margin['ssim_margin']:+.4f} SSIM; beats every global "
               f"exponent: PSNR {'yes' if margin['beats_every_global_psnr'] else 'NO'}, SSIM "
               f"{'yes' if margin['beats_every_global_ssim'] else 'NO'}.\n")
    atomic_write_text(out.with_suffix(".md"), md)
    write_png(out.with_suffix(".png"), comparison_figure(res, labels=[r.name for r in reps]))
    log.info(table)
    return [out, out.with_suffix(".md"), out.with_suffix(".png")]


@evaluate_group.command("representation")
@click.option("--ids", default=None, help="Identities: reads <ws>/unwrap-uv/<id>.npz (uv-observations).")
@click.option("--input", "-i", "inputs", multiple=True, type=click.Path(dir_okay=False, path_type=Path),
              help="A uv-observations artifact (repeatable).")
@click.option("--exponents-sets", default=REP_DEFAULTS["exponents_sets"], show_default=True,
              help="Representations separated by ';' (a single exponent = global exponent, K = 1).")
@click.option("--holdout", default=REP_DEFAULTS["holdout"], show_default=True,
              help="Flash ids held out for re-rendering (all views).")
@click.option("--no-baselines", is_flag=True, help="Skip 'diffuse only' and 'spec albedo + shininess 20'.")
@click.option("--solver", type=click.Choice(["fast", "adam"]), default="fast", show_default=True)
@click.option("--symmetry", type=click.FloatRange(0, 1), default=1.0, show_default=True)
@click.option("--symmetry-mode", type=click.Choice(["adaptive", "ill-posed", "all"]), default="adaptive", show_default=True,
              help="Mirror pooling: adaptive (ill-posed texels, and well-posed ones as far as the measured "
                   "asymmetry allows), only where a texel's own data are ill-posed, or everywhere (the paper's flip).")
@click.option("--loss", type=click.Choice(["l1", "l2"]), default="l1", show_default=True)
@click.option("--prior", type=click.FloatRange(0, None), default=1e-4, show_default=True)
@click.option("--prior-tail", type=click.FloatRange(0, None), default=100.0, show_default=True,
              help="Tail prior of fit-reflectance (× prior, for lobes seen only in their tail).")
@click.option("--lpips-weights", type=click.Path(dir_okay=False, path_type=Path), default=None,
              help="A torch state dict of LPIPS (trunk + lin layers). Without it LPIPS is off.")
@click.option("--lpips-net", type=click.Choice(["alex", "vgg"]), default="alex", show_default=True)
@click.option("--space", type=click.Choice(["auto", "image", "uv"]), default="auto", show_default=True,
              help="Re-render in image space against the captured OLAT images (needs <ws>/preprocess-multipie/<id>.npz, "
                   "<ws>/fit-geometry/<id>.npz and a face model) or in UV space; auto = image when available.")
@click.option("--face-model", type=click.Path(dir_okay=False, path_type=Path), default=None,
              help="Face model for image space (default: as build-pca).")
@click.option("--max-identities", type=click.IntRange(0, None), default=0, show_default=True,
              help="Evaluate only the first N identities (0 = all); ~45 s per identity at UV 256 on 2 cores.")
@workspace_option
@output_option
@json_option
def evaluate_representation_cmd(ids, inputs, exponents_sets, holdout, no_baselines, solver, symmetry, symmetry_mode,
                                loss, prior, prior_tail,
                                lpips_weights, lpips_net, space, face_model, max_identities, workspace, output,
                                as_json):
    """Global exponents vs multi-lobe (the paper's Table 1) on held-out flash images; markdown table on stdout.

    Writes an `evaluation` artifact (<ws>/evaluate-representation/evaluate-representation.npz or --output), the
    table (.md) and a figure (.png) beside it.
    """
    ws = (workspace or default_workspace()).resolve()
    files = [ws / "unwrap-uv" / f"{i}.npz" for i in parse_ids(ids)] + list(inputs)
    if not files:
        raise click.UsageError("give --ids or --input")
    params = {"exponents_sets": exponents_sets, "holdout": holdout, "baselines": not no_baselines,
              "solver": solver, "symmetry": symmetry, "symmetry_mode": symmetry_mode, "loss": loss, "prior": prior,
              "prior_tail": prior_tail, "lpips_net": lpips_net,
              "space": space, "max_identities": max_identities}
    inp = {"observations": files}
    if space != "uv" and ids:
        from reflectmm_cli.commands.build_pca import find_face_model

        caps = [ws / "preprocess-multipie" / f"{i}.npz" for i in parse_ids(ids)]
        geos = [ws / "fit-geometry" / f"{i}.npz" for i in parse_ids(ids)]
        fm = face_model or find_face_model(ws)
        if fm is not None and all(c.is_file() for c in caps) and all(g.is_file() for g in geos):
            inp.update(capture=caps, geometry=geos, face_model=[fm])
    if lpips_weights is not None:
        inp["lpips_weights"] = [lpips_weights]
    paths = run_stage_cli("evaluate-representation", workspace=workspace, params=params, inputs=inp,
                          output=output)
    if as_json:
        art = read_artifact(paths[0], EVAL_KIND)
        emit(paths, True, {"margin": art.meta.get("margin"), "lpips": art.meta.get("lpips")})
    else:
        click.echo(Path(paths[1]).read_text())
        emit(paths)


# --------------------------------------------------------------------------- evaluate report


def _report_outputs(ctx: StageContext) -> list[Path]:
    """[evaluation artifact (primary, carries the cache key), markdown report]."""
    if ctx.output is not None and Path(ctx.output).suffix.lower() != ".npz":
        md = Path(ctx.output)
        return [md.with_suffix(".npz"), md]
    npz = ctx.output_path()
    return [npz, npz.with_suffix(".md")]


@register_stage("evaluate-report", version=2, per_identity=False, outputs=_report_outputs,
                help="closing report of a run: errors of every stage against ground truth")
def run_evaluate_report(ctx: StageContext) -> list[Path]:
    from reflectmm_cli.evaluation.report import build_report

    out_npz, out_md = _report_outputs(ctx)
    text, doc = build_report(ctx.workspace, out_md,
                             geometry=ctx.input_list("geometry", required=False),
                             maps=ctx.input_list("maps", required=False),
                             models=ctx.input_list("model", required=False),
                             truth=ctx.input_list("truth", required=False),
                             representation=ctx.input_list("representation", required=False),
                             progress=lambda it, **k: progress(it, **k))
    flat = _flatten("", doc, {})
    names = sorted(flat)
    write_artifact(out_npz, EVAL_KIND, {"names": np.array(names, dtype=str),
                                        "values": np.array([flat[n] for n in names], np.float64)},
                   params=ctx.resolved_params(), inputs=ctx.input_refs(out_npz.parent), producer=ctx.producer(),
                   cache_key=ctx.cache_key, extra_meta={"evaluation": "report", "report": doc})
    atomic_write_text(out_md, text)
    return [out_md, out_npz]


@evaluate_group.command("report")
@click.option("--truth-dir", type=click.Path(file_okay=False, path_type=Path), default=None,
              help="Folder of synth-truth <id>.npz (default <ws>/truth or <ws>/synth/truth).")
@click.option("--out", "out", type=click.Path(dir_okay=False, path_type=Path), default=None,
              help="Markdown report path (default <ws>/evaluate-report/evaluate-report.md).")
@workspace_option
@json_option
def evaluate_report_cmd(truth_dir, out, workspace, as_json):
    """Closing report of a workspace: per-identity and mean errors against ground truth for every stage that has
    outputs (geometry, reflectance, PCA, representation comparison), with the PNG previews linked."""
    from reflectmm_cli.evaluation.report import discover_inputs

    ws = (workspace or default_workspace()).resolve()
    inputs = discover_inputs(ws, truth_dir)
    if not any(inputs.values()):
        raise ReflectmmError(f"evaluate report: nothing to report in {ws} (no fit-geometry/, fit-reflectance/, "
                             "build-pca/ or evaluate-representation/ outputs)")
    paths = run_stage_cli("evaluate-report", workspace=workspace, inputs={k: v for k, v in inputs.items() if v},
                          output=out)
    emit(paths, as_json)


COMMANDS = [evaluate_group]
