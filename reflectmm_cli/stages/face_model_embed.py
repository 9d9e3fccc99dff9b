"""Stage ``face-model-embed``: a face model + views of known geometry with a detector's landmarks → the same face
model with its landmark vertices where that detector puts the points (``reflectmm face-model embed-landmarks``).

Library: :func:`reflectmm_cli.geometry_fit.embedding.embed_landmarks` (docs/geometry.md, "A landmark embedding
for a detector").
"""
from __future__ import annotations

import dataclasses
import logging
from pathlib import Path

import numpy as np

from reflectmm_cli.artifacts import artifact_identity, read_artifact
from reflectmm_cli.errors import ReflectmmError
from reflectmm_cli.landmarks import GROUPS, SURFACE_GROUPS, group_mask
from reflectmm_cli.params import Param
from reflectmm_cli.stages.base import Input, Stage, StageContext

log = logging.getLogger("reflectmm")

VERB = "face-model-embed"

PARAMS = (
    Param("groups", "strs", list(SURFACE_GROUPS), choices=tuple(GROUPS),
          help="Landmark groups to move (default every group but the jaw, whose detected points follow the "
               "silhouette)."),
    Param("min_views", "int", 3, range=(1, None), help="A landmark seen by fewer views keeps its vertex."),
    Param("view_bias", "bool", True, option="--no-view-bias",
          help="Do not measure the detector's per-camera offsets from the embedded points (calibrate-rig and "
               "fit-geometry take them off the captures' points of those cameras)."),
)

#: The stage's input roles (checked in recipes and on the command line; shown in --help).
INPUTS = (
    Input('face_model', 'face-model artifact or BFM .mat', upstream='synth-multipie'),
    Input('capture', 'capture artifacts with the detector landmarks', upstream='preprocess-multipie', many=True),
    Input('geometry', 'geometry artifacts of the same identities (fitted or true)', upstream='fit-geometry',
          many=True),
)


def outputs(ctx: StageContext) -> list[Path]:
    """The face model and its preview: the old landmark vertices in cyan, the new ones in red."""
    out = ctx.output_path()
    return [out, out.with_suffix(".png")]


def _views(captures: list[Path], geometries: list[Path], n_vertices: int):
    """(camera name, vertices, K, R, t, points) of every view that a capture gives landmarks for and its
    identity's geometry has, captures and geometries matched by identity."""
    from reflectmm_cli.geometry_fit.calibrate import landmarks_from_captures

    geos = {}
    for g in geometries:
        art = read_artifact(g, "geometry")
        n = np.asarray(art["vertices"]).shape[0]
        if n != n_vertices:
            raise ReflectmmError(f"has {n} vertices but the face model has {n_vertices}: a geometry of another "
                                 "face model", g)
        ident = artifact_identity(art)
        if ident is None:
            raise ReflectmmError("records no identity: cannot match it to a capture", g)
        if ident in geos:
            raise ReflectmmError(f"a second geometry of identity {ident} (the first: {geos[ident].path})", g)
        geos[ident] = art
    # (N, C, 68, 2), NaN where a capture lacks a view
    lm, idents, cams, _ = landmarks_from_captures(captures, purpose="the embedding")
    views = []
    for c, ident, lm_i in zip(captures, idents, lm):
        if ident not in geos:
            raise ReflectmmError(f"no geometry of identity {ident} among the --geometry files", c)
        geo = geos[ident]
        names = [str(v) for v in geo["view_names"]]
        for k, v in enumerate(cams):
            if v not in names or not np.isfinite(lm_i[k]).all(-1).any():
                continue
            j = names.index(v)
            views.append((v, np.asarray(geo["vertices"]), geo["K"][j], geo["R"][j], geo["t"][j], lm_i[k]))
    if not views:
        raise ReflectmmError("no view has both detector landmarks (capture) and a geometry: nothing to embed from",
                             captures[0] if captures else None)
    return views


def run(ctx: StageContext) -> list[Path]:
    from reflectmm_cli.artifacts import write_png
    from reflectmm_cli.geometry.face_model import load_face_model, save_face_model
    from reflectmm_cli.geometry_fit.embedding import embed_landmarks, view_bias
    from reflectmm_cli.geometry.face_model_tools import preview_image

    fm_path = ctx.input("face_model")
    caps = [Path(p) for p in ctx.inputs.get("capture") or []]
    geos = [Path(p) for p in ctx.inputs.get("geometry") or []]
    if not caps or not geos:
        raise ReflectmmError("face-model embed-landmarks needs --capture and --geometry files (one geometry per "
                             "identity)")
    model = load_face_model(fm_path)
    if np.asarray(model.landmarks).size != 68:
        raise ReflectmmError("the face model has no 68 landmark vertices to move", fm_path)
    views = _views(caps, geos, int(np.asarray(model.mean_shape).shape[0]))
    p = ctx.params
    emb = embed_landmarks(model.mean_shape, model.triangles, model.landmarks, [v[1:] for v in views],
                          groups=tuple(p["groups"]), min_views=p["min_views"])
    out = ctx.output_path()
    info = dict(model.info)
    info["landmark_embedding"] = {"views": len(views), "groups": list(p["groups"]), "min_views": p["min_views"],
                                  "per_group": emb.summary(), "moved_mm": [round(float(x), 3) for x in emb.moved_mm],
                                  "spread_mm": [None if not np.isfinite(x) else round(float(x), 3)
                                                for x in emb.spread_mm]}
    if p["view_bias"]:
        bias = view_bias(emb.indices, views, groups=tuple(p["groups"]))
        info["landmark_view_bias"] = {"groups": list(p["groups"]), "cameras": {
            name: {"offset_iod": np.round(b["offset_iod"], 6).tolist(), "identities": b["identities"]}
            for name, b in bias.items()}}
        for name, b in bias.items():
            rms = float(np.sqrt(np.mean(b["offset_iod"][group_mask(p["groups"])] ** 2)))
            log.info("face-model embed-landmarks: camera %s: the detector's points sit %.4f inter-ocular distances "
                     "(RMS) from the embedded ones over %d identities", name, rms, b["identities"])
    else:
        info.pop("landmark_view_bias", None)
    new = dataclasses.replace(model, landmarks=emb.indices, info=info)
    save_face_model(new, out, params=ctx.resolved_params(), inputs=ctx.input_refs(out.parent),
                    producer=ctx.producer(), cache_key=ctx.cache_key)
    png = write_png(out.with_suffix(".png"), preview_image(
        new, yaws=(0.0, 30.0), marks=[(np.asarray(model.landmarks), (0.1, 0.9, 1.0)), (emb.indices, (1.0, 0.1, 0.1))]))
    for name, s in emb.summary().items():
        if s["moved"]:
            log.info("face-model embed-landmarks: %s: %d of %d moved, median %.1f mm (spread %.1f mm over %d views)",
                     name, s["moved"], s["of"], s["median_move_mm"], s["median_spread_mm"], s["median_views"])
    kept = np.flatnonzero(group_mask(p["groups"]) & ~emb.embedded)
    if kept.size:
        log.warning("face-model embed-landmarks: landmark(s) %s seen by fewer than %d views keep their vertices",
                    ", ".join(str(j) for j in kept), p["min_views"])
    return [out, png]


STAGE = Stage(VERB, version=2, run=run, per_identity=False, outputs=outputs, params=PARAMS,
              help="move a face model's landmark vertices to where a detector puts the points", inputs=INPUTS)
