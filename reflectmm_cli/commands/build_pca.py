"""``reflectmm build-pca``: the initial reflectance model from N identities' fitted maps (DESIGN.md §1 step 5).

Thin layer over :mod:`reflectmm_cli.model`: read ``reflectance-maps`` artifacts → PCA with specular transfer →
per-vertex model on the face model → ``reflectance-model`` artifact + PNG previews beside it.
"""

from __future__ import annotations

from pathlib import Path

import click
import numpy as np

from reflectmm_cli.artifacts import read_artifact, write_artifact, write_png
from reflectmm_cli.commands._common import emit, json_option, output_option, parse_ids, run_stage_cli, workspace_option
from reflectmm_cli.errors import ReflectmmError
from reflectmm_cli.model import MODEL_KIND, add_vertex_model, fit_reflectance_pca, model_arrays
from reflectmm_cli.progress import log, progress
from reflectmm_cli.stages import StageContext, default_workspace, register_stage

DEFAULTS = {"components": 80, "samples": 30, "seed": 0, "spread": 2.0, "preview": True}

#: Where a face model is looked for in a workspace when none is given (the synthetic world writes one).
FACE_MODEL_CANDIDATES = ("face_model.npz", "synth/face_model.npz", "synth-multipie/face_model.npz")


def find_face_model(workspace: Path) -> Path | None:
    for c in FACE_MODEL_CANDIDATES:
        p = Path(workspace) / c
        if p.is_file():
            return p
    return None


def _outputs(ctx: StageContext) -> list[Path]:
    out = ctx.output_path()
    outs = [out]
    if ctx.param("preview", True):
        outs.append(out.with_name(out.stem + "_components.png"))
        if ctx.inputs.get("face_model"):
            outs.append(out.with_name(out.stem + "_samples.png"))
    return outs


def load_maps(paths: list[Path]):
    """Read reflectance-maps artifacts; all must share exponents and UV size. Returns (ids, arrays, exponents)."""
    ids, albedos, weights, masks, flagged = [], [], [], [], []
    exps = None
    for p in progress(paths, desc="maps", unit="map"):
        art = read_artifact(p, "reflectance-maps")
        e = np.asarray(art["exponents"], np.float64).reshape(-1)
        if exps is None:
            exps, first = e, p
        elif e.shape != exps.shape or not np.allclose(e, exps):
            raise ReflectmmError(f"lobe exponents {e.tolist()} differ from {exps.tolist()} of {first}; a model "
                                 "needs one set of exponents", p)
        ids.append(str(art.meta.get("identity") or art.meta.get("params", {}).get("id") or Path(p).stem))
        albedos.append(art["albedo"])
        weights.append(art["weights"])
        masks.append(art["mask"] if "mask" in art.arrays else np.ones(art["albedo"].shape[1:], bool))
        flagged.append(art["flagged"] if "flagged" in art.arrays else np.zeros(art["albedo"].shape[1:], bool))
    return ids, albedos, weights, masks, flagged, exps


def build_model(map_paths: list[Path], components: int = 80, face_model: Path | None = None):
    """Library entry: (model, face model or None) from reflectance-maps files."""
    ids, A, W, M, F, exps = load_maps(map_paths)
    if len(set(ids)) != len(ids):
        ids = [Path(p).stem for p in map_paths]
    model = fit_reflectance_pca(A, W, exps, masks=M, flagged=F, components=components, ids=ids, log=log.warning)
    fm = None
    if face_model is not None:
        from reflectmm_cli.geometry.face_model import load_face_model

        fm = load_face_model(face_model)
        add_vertex_model(model, fm.uv)
    return model, fm


@register_stage("build-pca", version=1, per_identity=False, outputs=_outputs,
                help="PCA reflectance model (diffuse albedo + transferred lobe weights)")
def run_build_pca(ctx: StageContext) -> list[Path]:
    p = {**DEFAULTS, **{k: v for k, v in ctx.params.items() if v is not None}}
    maps = ctx.input_list("maps")
    if len(maps) < 2:
        raise ReflectmmError(f"build-pca: a PCA needs at least 2 reflectance-maps files, got {len(maps)}")
    fm_paths = ctx.input_list("face_model", required=False)
    fm_path = fm_paths[0] if fm_paths else None
    model, fm = build_model(maps, int(p["components"]), fm_path)
    out = ctx.output_path()
    resolved = {"components": int(p["components"])}
    extra = {"n_identities": len(maps), "n_components": model.n_components, "stats": model.stats,
             "ids": model.ids,
             "method": "PCA of the centred diffuse albedo (N x N Gram eigendecomposition + one Lowdin "
                       "re-orthonormalisation); specular bases = the same combination of training samples "
                       "(AlbedoMM); beta in units of sigma (ddof=1)",
             "face_model": None if fm_path is None else {"path": Path(fm_path).name,
                                                         "n_vertices": int(fm.uv.shape[0])}}
    written = [out]
    renderer = None
    if p["preview"]:
        from reflectmm_cli.model.preview import component_grid, render_samples

        written.append(write_png(out.with_name(out.stem + "_components.png"),
                                 component_grid(model, 3, float(p["spread"]))))
        if fm is not None:
            img, renderer = render_samples(model, fm.mean_shape, fm.triangles, n=int(p["samples"]),
                                           seed=int(p["seed"]), uv=fm.uv)
            log.info(f"build-pca: samples rendered with {renderer}")
            written.append(write_png(out.with_name(out.stem + "_samples.png"), img))
        else:
            log.warning("build-pca: no face model given: no per-vertex model and no rendered samples "
                        "(give --face-model)")
    extra["preview_renderer"] = renderer
    # the artifact last: it is the primary output whose cache key says the whole set is up to date
    write_artifact(out, MODEL_KIND, model_arrays(model), params=resolved, inputs=ctx.input_refs(out.parent),
                   producer=ctx.producer(), cache_key=ctx.cache_key, extra_meta=extra)
    ev = model.explained_variance_ratio
    log.info(f"build-pca: {len(maps)} identities -> {model.n_components} components; first 3 explain "
             f"{100 * float(ev[:3].sum()):.1f}% of the diffuse variance")
    return written


@click.command("build-pca")
@click.option("--ids", default=None, help="Identities (001,002 or 001-010): reads <ws>/fit-reflectance/<id>.npz.")
@click.option("--input", "-i", "inputs", multiple=True, type=click.Path(path_type=Path),
              help="A reflectance-maps artifact (repeatable; instead of or in addition to --ids).")
@click.option("--components", type=click.IntRange(1, None), default=80, show_default=True,
              help="PCA components (capped by N − 1 with a message).")
@click.option("--face-model", type=click.Path(dir_okay=False, path_type=Path), default=None,
              help="face-model artifact / BFM .mat for the per-vertex model (default: <ws>/face_model.npz or "
                   "<ws>/synth/face_model.npz if present).")
@click.option("--no-preview", is_flag=True, help="Skip the PNG previews.")
@workspace_option
@output_option
@json_option
def build_pca_cmd(ids, inputs, components, face_model, no_preview, workspace, output, as_json):
    """Build the PCA reflectance model from N identities' reflectance maps.

    Writes a `reflectance-model` artifact (<ws>/build-pca/build-pca.npz or --output), a PNG of the first 3
    components ±2σ and (with a face model) 30 random samples under a white frontal point light.
    """
    ws = (workspace or default_workspace()).resolve()
    paths = [ws / "fit-reflectance" / f"{i}.npz" for i in parse_ids(ids)] + list(inputs)
    if not paths:
        raise click.UsageError("give --ids or at least two --input files")
    if face_model is None:
        face_model = find_face_model(ws)
    inp = {"maps": paths}
    if face_model is not None:
        inp["face_model"] = [face_model]
    out = run_stage_cli("build-pca", workspace=workspace, params={"components": components,
                                                                  "preview": not no_preview},
                        inputs=inp, output=output)
    emit(out, as_json)


COMMANDS = [build_pca_cmd]
