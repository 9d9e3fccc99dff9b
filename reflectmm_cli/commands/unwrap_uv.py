"""``reflectmm unwrap-uv``: capture + fitted geometry → per-texel observations (``uv-observations`` artifact)."""

from __future__ import annotations

import logging
import time
from pathlib import Path

import click

from reflectmm_cli.artifacts import atomic_write_bytes, read_artifact, write_artifact
from reflectmm_cli.commands._common import emit, json_option, output_option, run_stage_cli, workspace_option
from reflectmm_cli.errors import ReflectmmError
from reflectmm_cli.stages import StageContext, default_workspace, register_stage

log = logging.getLogger("reflectmm")

VERB = "unwrap-uv"


def _outputs(ctx: StageContext) -> list[Path]:
    out = ctx.output_path()
    return [out, out.with_name(out.stem + "_preview.png")]


def face_model_from_geometry(geometry_path: Path) -> Path | None:
    """The face model a geometry artifact was fitted with (its meta inputs), if recorded and present."""
    art_meta = read_artifact(geometry_path, "geometry").meta
    for ref in art_meta.get("inputs", []):
        role = str(ref.get("role", "")).replace("-", "_")
        if role in ("face_model", "model") or "face" in role:
            p = (Path(geometry_path).parent / ref.get("path", "")).resolve()
            if p.is_file():
                return p
    return None


def default_face_model(capture: Path, geometry: Path, workspace: Path) -> Path | None:
    """--face-model default: the geometry's recorded face model, else face_model.npz of the capture's dataset
    folder, else ``<workspace>/face_model.npz`` (the same rule as fit-geometry)."""
    from reflectmm_cli.artifacts import Artifact, read_meta
    from reflectmm_cli.commands.fit_geometry import default_face_model_for

    found = face_model_from_geometry(geometry)
    if found is not None:
        return found
    cap = Artifact("capture", {}, read_meta(capture), Path(capture))
    return default_face_model_for(cap, workspace)


def _resolved_inputs(ctx: StageContext) -> dict[str, list[Path]]:
    """ctx.inputs plus the default face model when the recipe leaves it out (so it keys the cache too)."""
    files = {k: [Path(p) for p in v] for k, v in ctx.inputs.items()}
    if not files.get("face_model"):
        cap, geo = files.get("capture") or [], files.get("geometry") or []
        if len(cap) == 1 and len(geo) == 1 and cap[0].is_file() and geo[0].is_file():
            try:
                fm = default_face_model(cap[0], geo[0], ctx.workspace)
            except ReflectmmError:
                fm = None
            if fm is not None:
                files["face_model"] = [fm]
    return files


def reflectance_views(capture, views=None) -> list[str]:
    """The capture views whose images enter the reflectance fit: ``views`` if given ("all" = every view), else
    every view but the raised cameras 08_1 / 19_1 (the paper uses them only to place flashes 14 / 18)."""
    from reflectmm_cli.rig import RAISED_CAMERAS

    have = [str(v) for v in capture["view_names"]]
    if views is not None:
        vs = [str(v) for v in (views.split(",") if isinstance(views, str) else views) if str(v).strip()]
        return have if vs == ["all"] else vs
    keep = [v for v in have if v not in RAISED_CAMERAS]
    if not keep:
        log.warning("unwrap-uv: the capture has only raised cameras (%s): unwrapping them", ", ".join(have))
        return have
    if len(keep) < len(have):
        log.info("unwrap-uv: leaving out the raised camera(s) %s (geometry / flash placement only; --views all "
                 "keeps them)", ", ".join(v for v in have if v in RAISED_CAMERAS))
    return keep


# version 2: the raised cameras 08_1 / 19_1 are left out by default (issue 13)
@register_stage(VERB, version=2, per_identity=True, outputs=_outputs, input_files=_resolved_inputs,
                help="capture + geometry -> per-texel OLAT observations in UV space")
def run_unwrap(ctx: StageContext) -> list[Path]:
    from reflectmm_cli.geometry.face_model import load_face_model
    from reflectmm_cli.observations.unwrap import previews, unwrap_observations
    from reflectmm_cli.capture.preprocess import encode_png

    t0 = time.perf_counter()
    cap_path = ctx.input("capture")
    geo_path = ctx.input("geometry")
    files = _resolved_inputs(ctx)  # recipes may leave face_model out: the same default as the command line
    if not files.get("face_model"):
        raise ReflectmmError(f"stage '{ctx.stage_name}': no face_model input, and neither the geometry nor "
                             "the capture's dataset folder nor the workspace provides one", geo_path)
    fm_path = files["face_model"][0]
    cap = read_artifact(cap_path, "capture")
    geo = read_artifact(geo_path, "geometry")
    model = load_face_model(fm_path)
    exps = tuple(float(e) for e in ctx.param("exponents", (1.0, 8.0, 64.0)))
    arrays, report = unwrap_observations(cap.arrays, geo.arrays, model.triangles, model.uv,
                                         select_views=reflectance_views(cap, ctx.param("views")),
                                         uv_size=int(ctx.param("uv_size", 256)),
                                         grazing_deg=float(ctx.param("grazing_deg", 80.0)), exponents=exps,
                                         geometry_path=geo_path, capture_path=cap_path)
    out, prev = _outputs(ctx)
    write_artifact(out, "uv-observations", arrays, params=ctx.resolved_params(),
                   inputs=ctx.input_refs(out.parent, files),
                   producer=ctx.producer(), cache_key=ctx.cache_key, extra_meta={"report": report})
    atomic_write_bytes(prev, encode_png(previews(arrays)))
    log.info("unwrap-uv %s: %d texels, %d views x %d flashes, %d observed texel-pairs; rays: %d view, %d shadow "
             "(skipped %d back-facing, %d unseen); %d texels unseen by every view; %.2f s", ctx.identity,
             report["texels"], report["views"], report["flashes"], report["observed_pairs"], report["rays_view"],
             report["rays_shadow"], report["skipped_backfacing_light"], report["skipped_unseen"],
             report["texels_unseen"], time.perf_counter() - t0)
    return [out, prev]


@click.command(VERB)
@click.option("--id", "identity", required=True, help="Identity (e.g. 042).")
@click.option("--uv-size", type=click.IntRange(8, 4096), default=256, show_default=True, help="UV map size S.")
@click.option("--capture", "capture", type=click.Path(dir_okay=False, path_type=Path), default=None,
              help="capture artifact (default <ws>/preprocess-multipie/<id>.npz).")
@click.option("--geometry", type=click.Path(dir_okay=False, path_type=Path), default=None,
              help="geometry artifact (default <ws>/fit-geometry/<id>.npz).")
@click.option("--face-model", type=click.Path(dir_okay=False, path_type=Path), default=None,
              help="face model (face-model artifact or BFM .mat; default: the one the geometry records, else "
                   "face_model.npz of the capture's dataset folder, else <ws>/face_model.npz).")
@click.option("--grazing-deg", type=float, default=80.0, show_default=True,
              help="A view sees a texel only if the angle between normal and view direction is below this.")
@click.option("--exponents", default="1,8,64", show_default=True,
              help="Lobe exponents used for the conditioning map.")
@click.option("--views", default=None,
              help="Capture views to unwrap, comma separated, or 'all' (default: every view but the raised 08_1 / "
                   "19_1, which only place flashes 14 / 18).")
@workspace_option
@output_option
@json_option
def unwrap_uv_cmd(identity, uv_size, capture, geometry, face_model, grazing_deg, exponents, views, workspace, output,
                  as_json):
    """Unwrap one identity's OLAT images into UV space with visibility, shadow and saturation masks."""
    ws = (workspace or default_workspace()).resolve()
    capture = capture or ws / "preprocess-multipie" / f"{identity}.npz"
    geometry = geometry or ws / "fit-geometry" / f"{identity}.npz"
    for role, p, verb in (("capture", capture, "preprocess-multipie"), ("geometry", geometry, "fit-geometry")):
        if not Path(p).exists():
            raise ReflectmmError(f"{role} artifact not found (run {verb} first or pass --{role})", p)
    if face_model is None:
        face_model = default_face_model(capture, geometry, ws)
        if face_model is None:
            raise ReflectmmError("no face model: the geometry does not record one, and there is no face_model.npz "
                                 "beside the capture's dataset or in the workspace; pass --face-model", geometry)
    try:
        exps = [float(e) for e in exponents.replace(" ", "").split(",") if e]
    except ValueError:
        raise click.BadParameter(f"not a comma-separated list of numbers: {exponents!r}", param_hint="--exponents")
    if not exps or min(exps) <= 0:
        raise click.BadParameter("exponents must be > 0", param_hint="--exponents")
    params = {"uv_size": uv_size, "grazing_deg": grazing_deg, "exponents": exps}
    if views is not None:
        params["views"] = views
    paths = run_stage_cli(VERB, workspace=ws, identity=identity, params=params,
                          inputs={"capture": [capture], "geometry": [geometry], "face_model": [face_model]},
                          output=output)
    emit(paths, as_json)


COMMANDS = [unwrap_uv_cmd]
