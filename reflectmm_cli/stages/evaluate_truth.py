"""Stage ``evaluate-truth``: errors of one identity's fitted maps (and geometry) against ground truth."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from reflectmm_cli.artifacts import check_identity, read_artifact, write_artifact
from reflectmm_cli.errors import ReflectmmError
from reflectmm_cli.evaluation.documents import EVAL_KIND, flatten
from reflectmm_cli.stages.base import Default, Input, Stage, StageContext

VERB = "evaluate-truth"

PARAMS = ()

#: The stage's input roles (checked in recipes and on the command line; shown in --help).
INPUTS = (
    Input('maps', 'reflectance-maps', upstream='fit-reflectance', default=Default(optional=True)),
    Input('geometry', 'geometry', upstream='fit-geometry'),
    Input('truth', 'ground-truth NPZ', upstream='synth-multipie', default=Default('truth', checked=False)),
    Input('face_model', 'face-model artifact or BFM .mat', upstream='synth-multipie', help='the mesh and its UVs'),
)


def _is_vertex_reflectance(path: Path) -> bool:
    """A plain NPZ (no artifact meta) with per-vertex ``albedo (V, 3)`` (reflectmm_cli.evaluation.external)."""
    import zipfile

    try:
        with np.load(path, allow_pickle=False) as z:
            return "__meta__" not in z.files and "albedo" in z.files and z["albedo"].ndim == 2
    except (OSError, ValueError, EOFError, zipfile.BadZipFile):
        return False  # not that format: the artifact reader names the problem


def _checked(art, keys, path, identity) -> None:
    """Refuse an input of another identity than the task's, without an array the errors read, with NaN or inf in
    one, or with lobe weights that do not match its exponents (each would give a wrong or NaN table, exit 0)."""
    check_identity(art, identity)
    missing = [k for k in keys if k not in art.arrays]
    if missing:
        raise ReflectmmError(f"{art.kind} artifact has no array {', '.join(repr(k) for k in missing)} (has: "
                             f"{', '.join(sorted(art.arrays))})", path)
    for k in keys:
        a = np.asarray(art[k])
        if a.dtype.kind == "f" and not np.isfinite(a).all():
            raise ReflectmmError(f"{art.kind} array '{k}' has {int((~np.isfinite(a)).sum())} NaN or inf values",
                                 path)
    if "weights" in keys and "exponents" in art.arrays:
        K, E = np.asarray(art["weights"]).shape[0], np.asarray(art["exponents"]).size
        if K != E:
            raise ReflectmmError(f"{art.kind} has {K} lobe-weight channels but {E} exponents", path)


def evaluate_truth(maps_path: Path | None, truth_path: Path, geometry_path: Path | None = None,
                   face_model_path: Path | None = None, identity: str | None = None) -> dict:
    """Library entry: the error document of fitted maps (and geometry) against a synth-truth file, or against
    per-vertex reflectance (plain NPZ, docs/artifacts.md) laid out in UV with the face model ``face_model_path``.
    ``identity``: the task's; every input that records another is refused."""
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
        _checked(maps, ("albedo", "weights"), maps_path, identity)
        _checked(truth, ("albedo",), truth_path, identity)
        got, want = np.shape(truth["albedo"]), np.shape(maps["albedo"])
        if got != want:  # the library's message names neither file
            raise ReflectmmError(f"evaluate truth: albedo has shape {got}, the maps {maps_path} {want}: the UV sizes "
                                 "must agree", truth_path)
        doc["reflectance"] = reflectance_errors(maps.arrays, truth.arrays)
    if geometry_path is not None:
        geo = read_artifact(geometry_path, "geometry")
        _checked(geo, ("vertices",), geometry_path, identity)
        _checked(truth, ("vertices",), truth_path, identity)
        doc["geometry"] = geometry_errors(geo.arrays, truth.arrays)
    if not doc:
        raise ReflectmmError("evaluate truth: give --maps and/or --geometry")
    return doc


def _truth_outputs(ctx: StageContext) -> list[Path]:
    return [ctx.output_path()]


def run(ctx: StageContext) -> list[Path]:
    maps = ctx.input_list("maps", required=False)
    geo = ctx.input_list("geometry", required=False)
    fms = ctx.input_list("face_model", required=False)
    doc = evaluate_truth(maps[0] if maps else None, ctx.input("truth"), geo[0] if geo else None,
                         fms[0] if fms else None, identity=ctx.identity)
    flat = flatten("", doc, {})
    names = sorted(flat)
    out = ctx.output_path()
    write_artifact(out, EVAL_KIND, {"names": np.array(names, dtype=str),
                                    "values": np.array([flat[n] for n in names], np.float64)},
                   params=ctx.resolved_params(), inputs=ctx.input_refs(out.parent), producer=ctx.producer(),
                   cache_key=ctx.cache_key, extra_meta={"evaluation": "truth", "identity": ctx.identity,
                                                        "errors": doc})
    return [out]


# version 2: spec_ratio_median
STAGE = Stage(VERB, version=3, run=run, per_identity=True, outputs=_truth_outputs, params=PARAMS,
              help="errors of fitted maps / geometry against ground truth", inputs=INPUTS)
