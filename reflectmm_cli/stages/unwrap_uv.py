"""Stage ``unwrap-uv``: capture + fitted geometry → per-texel observations (``uv-observations`` artifact)."""

from __future__ import annotations

import logging
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

from reflectmm_cli.artifacts import atomic_write_bytes, check_identity, read_artifact, write_artifact
from reflectmm_cli.errors import ReflectmmError
from reflectmm_cli.observations.unwrap import TRUST_CENTER_SIGMA_MM, TRUST_RESIDUAL_RATIO
from reflectmm_cli.params import Param
from reflectmm_cli.stages.base import Default, Input, Stage, StageContext
from reflectmm_cli.stages.fit_reflectance import EXPONENTS
from reflectmm_cli.workspace import find_face_model

log = logging.getLogger("reflectmm")

VERB = "unwrap-uv"

#: Largest UV map: 4096² texels × (views × flashes) observations is already tens of GB.
MAX_UV_SIZE = 4096

PARAMS = (
    Param("uv_size", "int", 256, range=(8, MAX_UV_SIZE), unit="texels", help="UV map size S."),
    Param("grazing_deg", "float", 80.0, range=(0.0, 90.0), low_open=True, unit="degrees",
          help="A view sees a texel only if the angle between normal and view direction is below this."),
    Param("edge_margin", "int", 1, range=(0, 64), unit="px",
          help="Pixels a view's sample keeps from the mesh's border, silhouette and occluding edges, so that a "
               "registration error of that size does not sample the background, hair or another surface."),
    replace(EXPONENTS, help="Lobe exponents used for the conditioning map."),
    Param("views", "strs", None,
          help="Capture views to unwrap, comma separated, 'all', 'landmarked': the views whose camera landmarks "
               "placed, or 'trusted': those, plus the views without landmarks whose registration by their images "
               "checks out (--trust-center-sigma, --trust-residual-ratio) (default: every view but the raised "
               "08_1 / 19_1, which only place flashes 14 / 18; 'landmarked' and 'trusted' leave them out too)."),
    Param("flashes", "strs", None,
          help="Capture flashes to unwrap, comma separated, 'all' (the default), 'landmarked': only the flashes "
               "carried by cameras that landmarks placed (a camera placed by the rig or by its flash images puts "
               "its flash where it was guessed), or 'trusted': those, plus the flashes of cameras without "
               "landmarks whose registration by their images checks out (--trust-center-sigma, "
               "--trust-residual-ratio)."),
    Param("trust_center_sigma", "float", TRUST_CENTER_SIGMA_MM, range=(0.0, None), low_open=True, unit="mm",
          help="--views / --flashes trusted: largest 1-sigma of a registered camera's centre (fit-geometry's "
               "center_sigma_mm) whose view and flash are kept."),
    Param("trust_residual_ratio", "float", TRUST_RESIDUAL_RATIO, range=(0.0, None), low_open=True,
          help="--views / --flashes trusted: largest flash residual of a registered camera, as a multiple of the "
               "median flash residual of the views that landmarks placed, whose view and flash are kept."),
)

#: The stage's input roles (checked in recipes and on the command line; shown in --help).
INPUTS = (
    Input('capture', 'capture', upstream='preprocess-multipie', default=Default(
        check_given=True, missing='{path}: capture artifact not found (run preprocess-multipie first or pass --capture)')),
    Input('geometry', 'geometry', upstream='fit-geometry', default=Default(
        check_given=True, missing='{path}: geometry artifact not found (run fit-geometry first or pass --geometry)')),
    Input('face_model', 'face-model artifact or BFM .mat', upstream='synth-multipie', help='the mesh and its UVs',
          default=Default('face-model', capture='capture', geometry='geometry', missing=(
              '{geometry}: no face model: the geometry does not record one, and there is no face_model.npz beside '
              "the capture's dataset or in the workspace; pass --face-model"))),
)


def _outputs(ctx: StageContext) -> list[Path]:
    out = ctx.output_path()
    return [out, out.with_name(out.stem + "_preview.png")]


def _resolved_inputs(ctx: StageContext) -> dict[str, list[Path]]:
    """ctx.inputs plus the default face model when the recipe leaves it out (so it keys the cache too)."""
    files = {k: [Path(p) for p in v] for k, v in ctx.inputs.items()}
    if not files.get("face_model"):
        cap, geo = files.get("capture") or [], files.get("geometry") or []
        if len(cap) == 1 and len(geo) == 1 and cap[0].is_file() and geo[0].is_file():
            try:
                fm = find_face_model(ctx.workspace, capture=cap[0], geometry=geo[0])
            except ReflectmmError:
                fm = None
            if fm is not None:
                files["face_model"] = [fm]
    return files


#: How far (mm) a face model may put a geometry's vertices, from the geometry's own coefficients, from where the
#: geometry has them: the same model gives them to the bit on the CPU, a float32 fit on a GPU to about 1e-3 mm;
#: another model or vertex order puts them millimetres to centimetres off.
MODEL_MISMATCH_MM = 0.1


def check_model_of_geometry(model, geometry, fm_path, geo_path) -> None:
    """Refuse a face model that is not the one the geometry was fitted with: from the geometry's shape and
    expression coefficients it must give the geometry's vertices (:data:`MODEL_MISMATCH_MM`).  A model with
    the same vertex count but another vertex order, mean or basis would otherwise unwrap a scrambled face.  A model
    that differs only in its landmark vertices (``face-model embed-landmarks``) gives the same mesh and passes.
    Geometries without coefficients, or whose vertex count differs (the library names that), are left alone."""
    g = geometry
    if "shape_coeffs" not in g or "vertices" not in g:
        return
    verts = np.asarray(g["vertices"], np.float64)
    if verts.shape != np.asarray(model.mean_shape).shape:
        return
    try:
        v = model.vertices(np.asarray(g["shape_coeffs"]).reshape(-1),
                           np.asarray(g["exp_coeffs"]).reshape(-1) if "exp_coeffs" in g else None)
    except ReflectmmError as e:
        raise ReflectmmError(f"cannot give the geometry's vertices from its coefficients ({e}): not the face model "
                             f"{geo_path} was fitted with", fm_path) from None
    off = float(np.abs(v - verts).max())
    if not off <= MODEL_MISMATCH_MM:
        raise ReflectmmError(f"gives the geometry's vertices, from its coefficients, up to {off:.3g} mm from where "
                             f"{geo_path} has them: not the face model it was fitted with (another model, or its "
                             "vertices in another order)", fm_path)


def run(ctx: StageContext) -> list[Path]:
    from reflectmm_cli.capture.preprocess import encode_png
    from reflectmm_cli.geometry.face_model import load_face_model
    from reflectmm_cli.observations.unwrap import (previews, reflectance_flashes, reflectance_views,
                                                   unwrap_observations, warn_rig_placed)

    t0 = time.perf_counter()
    cap_path = ctx.input("capture")
    geo_path = ctx.input("geometry")
    files = _resolved_inputs(ctx)  # recipes may leave face_model out: the same default as the command line
    if not files.get("face_model"):
        raise ReflectmmError(f"stage '{ctx.stage_name}': no face_model input, and neither the geometry nor "
                             "the capture's dataset folder nor the workspace provides one", geo_path)
    fm_path = files["face_model"][0]
    cap = check_identity(read_artifact(cap_path, "capture"), ctx.identity)
    geo = check_identity(read_artifact(geo_path, "geometry"), ctx.identity)
    model = load_face_model(fm_path)
    check_model_of_geometry(model, geo.arrays, fm_path, geo_path)
    p = ctx.params
    views = reflectance_views(cap.arrays, p.get("views"), geo.arrays, geo_path,
                              max_center_sigma_mm=p["trust_center_sigma"], max_residual_ratio=p["trust_residual_ratio"])
    flashes = reflectance_flashes(cap.arrays, geo.arrays, p.get("flashes"), geo_path,
                                  max_center_sigma_mm=p["trust_center_sigma"],
                                  max_residual_ratio=p["trust_residual_ratio"])
    warn_rig_placed(geo.arrays, views, flashes, ctx.identity)
    arrays, report = unwrap_observations(cap.arrays, geo.arrays, model.triangles, model.uv,
                                         select_views=views,
                                         select_flashes=flashes,
                                         uv_size=p["uv_size"], grazing_deg=p["grazing_deg"],
                                         edge_margin=p["edge_margin"],
                                         exponents=tuple(p["exponents"]),
                                         geometry_path=geo_path, capture_path=cap_path)
    out, prev = _outputs(ctx)
    write_artifact(out, "uv-observations", arrays, params=ctx.resolved_params(),
                   inputs=ctx.input_refs(out.parent, files),
                   producer=ctx.producer(), cache_key=ctx.cache_key,
                   extra_meta={"report": report, **({"identity": str(ctx.identity)} if ctx.identity else {})})
    atomic_write_bytes(prev, encode_png(previews(arrays)))
    log.info("unwrap-uv %s: %d texels, %d views x %d flashes, %d observed texel-pairs; rays: %d view, %d shadow "
             "(skipped %d back-facing, %d unseen); %d texels unseen by every view; %.2f s", ctx.identity,
             report["texels"], report["views"], report["flashes"], report["observed_pairs"], report["rays_view"],
             report["rays_shadow"], report["skipped_backfacing_light"], report["skipped_unseen"],
             report["texels_unseen"], time.perf_counter() - t0)
    return [out, prev]


# version 2: the raised cameras 08_1 / 19_1 are left out by default (issue 13)
# version 3: samples keep 1 px from the mesh's border, silhouette and occluding edges (--edge-margin)
STAGE = Stage(VERB, version=3, run=run, per_identity=True, outputs=_outputs, input_files=_resolved_inputs,
              params=PARAMS, help="capture + geometry -> per-texel OLAT observations in UV space", inputs=INPUTS)
