"""Stage ``view``: a reflectance model (optionally beside a second one) → one self-contained interactive HTML page
(docs/viewer.md). Library: :mod:`reflectmm_cli.viewer`.

Inputs: ``model`` (a ``reflectance-model`` with a per-vertex part), optional ``compare`` (a second model shown side
by side under the same β and light), ``face_model`` (default: the one the model records among its inputs, else
the workspace's, :func:`reflectmm_cli.workspace.find_face_model`),
optional ``light_model`` and ``envmap`` (any number of equirectangular maps, projected to SH).
"""
from __future__ import annotations

from pathlib import Path

from reflectmm_cli.errors import ReflectmmError
from reflectmm_cli.params import Param
from reflectmm_cli.progress import log
from reflectmm_cli.stages.base import Input, Stage, StageContext

VERB = "view"

#: Document kind of the page (its meta is embedded in the HTML head).
VIEW_KIND = "viewer"

PARAMS = (
    Param("components", "int", 10, range=(0, 512), help="Reflectance components per model in the page (β sliders)."),
    Param("light_components", "int", 10, range=(0, 512), help="Light-model components in the page (γ sliders)."),
    Param("sh_order", "int", 8, range=(0, 12), help="SH order of the --envmap projection."),
    Param("encoding", "str", "f2", choices=("f2", "u8"),
          help="Basis encoding: float16 (f2) or 8-bit with a scale per component and channel (u8)."),
    Param("title", "str", "", help="Page title (default: the model's file name)."),
    Param("names", "str", "", metavar="A[,B]", help="Display names of the model(s) (default: their file names)."),
)

#: The stage's input roles (checked in recipes and on the command line; shown in --help).
INPUTS = (
    Input('model', 'reflectance-model', upstream='finetune'),
    Input('compare', 'reflectance-model', upstream='build-pca', help='shown beside the first'),
    Input('face_model', 'face-model artifact or BFM .mat', upstream='synth-multipie', help='the mesh and its UVs'),
    Input('light_model', 'light-model', upstream='build-light-pca'),
    Input('envmap', 'EXR/HDR maps', upstream='synth-envmaps', many=True),
)


def _out(ctx: StageContext) -> Path:
    out = Path(ctx.output) if ctx.output is not None else ctx.output_path(name="model", suffix=".html")
    if out.suffix.lower() not in (".html", ".htm"):
        raise ReflectmmError("view output must be an .html file", out)
    return out


def _outputs(ctx: StageContext) -> list[Path]:
    return [_out(ctx)]


def _face_model(ctx: StageContext) -> Path:
    given = ctx.input_list("face_model", required=False)
    if given:
        return given[0]
    from reflectmm_cli.workspace import face_model_recorded_by, find_face_model

    found = face_model_recorded_by(ctx.input("model")) or find_face_model(ctx.workspace)
    if found is None:
        raise ReflectmmError("view: the model records no face model that exists here and the workspace has none; "
                             "give --face-model", ctx.input("model"))
    return found


def _input_files(ctx: StageContext) -> dict[str, list[Path]]:
    files = {role: [Path(p) for p in paths] for role, paths in ctx.inputs.items()}
    files["face_model"] = [_face_model(ctx)]
    return files


def run(ctx: StageContext) -> list[Path]:
    import numpy as np

    from reflectmm_cli.artifacts import atomic_write_text, make_meta, read_artifact
    from reflectmm_cli.geometry import load_face_model, vertex_normals
    from reflectmm_cli.viewer import (
        LightData,
        ViewerOptions,
        build_bundle,
        bundle_size,
        envmap_data,
        light_model_data,
        model_data,
        render_page,
    )

    p = ctx.params
    out = _out(ctx)
    opts = ViewerOptions(components=p["components"], light_components=p["light_components"],
                         sh_order=p["sh_order"], encoding=p["encoding"])
    paths = [ctx.input("model")] + ctx.input_list("compare", required=False)[:1]
    names = [s.strip() for s in (p.get("names") or "").split(",") if s.strip()]
    if names and len(names) != len(paths):
        raise ReflectmmError(f"view: --names gives {len(names)} names for {len(paths)} model(s)")
    models = []
    for i, mp in enumerate(paths):
        art = read_artifact(mp, "reflectance-model")
        models.append(model_data(art.arrays, opts.components, names[i] if names else Path(mp).stem, mp))
    fm_path = _face_model(ctx)
    fm = load_face_model(fm_path)
    verts = np.asarray(fm.mean_shape, np.float64)
    light = LightData()
    lm = ctx.input_list("light_model", required=False)
    if lm:
        light = light_model_data(read_artifact(lm[0], "light-model").arrays, opts.light_components, light)
    light = envmap_data(ctx.input_list("envmap", required=False), opts.sh_order, light)
    doc = build_bundle(verts, fm.triangles, vertex_normals(verts, fm.triangles, dtype=np.float64), models, light,
                       opts, title=p.get("title") or Path(paths[0]).stem)
    sizes = bundle_size(doc)
    files = dict(ctx.inputs)
    files["face_model"] = [fm_path]
    meta = make_meta(VIEW_KIND, params=ctx.resolved_params(), inputs=ctx.input_refs(out.parent, files=files),
                     producer=ctx.producer(), cache_key=ctx.cache_key,
                     extra={"bytes": sizes, "n_vertices": int(verts.shape[0]),
                            "models": [m.name for m in models], "sh_order": doc["shading"]["order"]})
    html = render_page(doc, meta)
    atomic_write_text(out, html)
    log.info("view: %s (%.2f MB: %s); open it in a browser", out, len(html.encode()) / 1e6,
             ", ".join(f"{k} {v / 1e6:.2f} MB" for k, v in sizes.items()))
    return [out]


STAGE = Stage(VERB, version=1, run=run, per_identity=False, outputs=_outputs, input_files=_input_files,
              params=PARAMS, help="write a self-contained interactive HTML viewer of a reflectance model", inputs=INPUTS)
