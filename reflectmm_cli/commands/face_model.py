"""``reflectmm face-model``: create, import and export face models (docs/geometry.md).

* ``face-model create --out FILE`` — the built-in procedural model as a ``face-model`` artifact + PNG preview
  (stage ``face-model-create``);
* ``face-model import BFM.mat --out FILE`` — BFM09 ``01_MorphableModel.mat`` (+ ``Exp_Pca.bin``) or
  Deep3DFaceRecon ``BFM_model_front.mat`` → ``face-model`` artifact, computing a symmetric UV layout if the model
  has none and reporting its distortion (stage ``face-model-import``);
* ``face-model embed-landmarks --face-model FM --capture C… --geometry G… --out FILE`` — the landmark vertices
  moved to where a detector puts the points, measured on views of known geometry (stage ``face-model-embed``);
* ``face-model export FILE --out mesh.obj|.ply`` — a mesh with UVs through trimesh (optionally for given
  shape/expression coefficients);
* ``face-model info FILE`` — sizes and provenance.
"""
from __future__ import annotations

import json
from pathlib import Path

import click
import numpy as np

from reflectmm_cli.commands._common import (emit, given_params, json_option, param_options, run_stage_cli,
                                            workspace_option)
from reflectmm_cli.errors import ReflectmmError
from reflectmm_cli.geometry.face_model_tools import export_mesh
from reflectmm_cli.geometry.render_face import parse_coeffs
from reflectmm_cli.stages import face_model_create, face_model_embed, face_model_import


@click.group("face-model")
def face_model_group():
    """Create, import, export and inspect face models (the `face-model` artifact)."""


@face_model_group.command("create")
@click.option("--out", "-o", "out", type=click.Path(dir_okay=False, path_type=Path), default=None,
              help="Output artifact (default <workspace>/face-model-create/face-model-create.npz).")
@param_options(face_model_create.PARAMS)
@workspace_option
@json_option
def create_cmd(out, workspace, as_json, **kw):
    """Write the built-in procedural face model (+ a PNG preview beside it)."""
    paths = run_stage_cli(face_model_create.VERB, workspace=workspace, output=out,
                          params=given_params(kw, face_model_create.PARAMS))
    emit(paths, as_json)


@face_model_group.command("import")
@click.argument("source", type=click.Path(path_type=Path))
@click.option("--out", "-o", "out", type=click.Path(dir_okay=False, path_type=Path), required=True)
@click.option("--exp", "exp", type=click.Path(path_type=Path), default=None,
              help="BFM09 only: Exp_Pca.bin expression basis (Guo et al.).")
@click.option("--exp-std", type=click.Path(path_type=Path), default=None,
              help="std_exp.txt: standard deviations of the expression coefficients.")
@click.option("--exp-index", type=click.Path(path_type=Path), default=None,
              help="BFM_exp_idx.mat ('trimIndex'): BFM09 vertices of the Exp_Pca.bin basis, if it has fewer.")
@click.option("--landmarks", type=click.Path(path_type=Path), default=None,
              help="68 landmark vertex indices (text/.anl/.npy), e.g. for BFM09 which has none.")
@param_options(face_model_import.PARAMS)
@workspace_option
@json_option
def import_cmd(source, out, exp, exp_std, exp_index, landmarks, workspace, as_json, **kw):
    """Convert a BFM09 01_MorphableModel.mat or Deep3DFaceRecon BFM_model_front.mat to a face-model artifact."""
    inputs = {"model": [source]}
    for role, p in (("exp", exp), ("exp_std", exp_std), ("exp_index", exp_index), ("landmarks", landmarks)):
        if p is not None:
            inputs[role] = [p]
    paths = run_stage_cli(face_model_import.VERB, workspace=workspace, output=out, inputs=inputs,
                          params=given_params(kw, face_model_import.PARAMS))
    emit(paths, as_json)


@face_model_group.command("embed-landmarks")
@click.option("--face-model", "face_model", type=click.Path(dir_okay=False, path_type=Path), required=True,
              help="The face model whose landmark vertices move (artifact or BFM .mat).")
@click.option("--capture", "-i", "captures", multiple=True, required=True,
              type=click.Path(dir_okay=False, path_type=Path),
              help="A capture artifact whose landmarks come from the detector (repeatable).")
@click.option("--geometry", "geometries", multiple=True, required=True,
              type=click.Path(dir_okay=False, path_type=Path),
              help="The geometry of a capture's identity: fitted from trusted landmarks, or the truth "
                   "(fit-geometry --from-truth) on synthetic data (repeatable; matched by identity).")
@click.option("--out", "-o", "out", type=click.Path(dir_okay=False, path_type=Path), required=True)
@param_options(face_model_embed.PARAMS)
@workspace_option
@json_option
def embed_cmd(face_model, captures, geometries, out, workspace, as_json, **kw):
    """Move a face model's landmark vertices to where a detector puts the 68 points, measured on views whose
    geometry is known; the jaw keeps its vertices by default."""
    inputs = {"face_model": [face_model], "capture": list(captures), "geometry": list(geometries)}
    paths = run_stage_cli(face_model_embed.VERB, workspace=workspace, output=out, inputs=inputs,
                          params=given_params(kw, face_model_embed.PARAMS))
    emit(paths, as_json)


@face_model_group.command("export")
@click.argument("model_path", metavar="FILE", type=click.Path(path_type=Path))
@click.option("--out", "-o", "out", type=click.Path(dir_okay=False, path_type=Path), required=True,
              help="Mesh file: .obj (with vt/vn), .ply (binary, UVs as s/t), .glb, .off or .stl.")
@click.option("--coeffs", "--shape", "shape", default=None,
              help="Shape coefficients (raw, prior std = shape_sigma): 'a,b,c' or a .npy/.txt/.json file.")
@click.option("--exp", "exp", default=None, help="Expression coefficients, same forms.")
@click.option("--sigma-units", is_flag=True, help="Coefficients are in units of sigma (multiplied by it).")
@click.option("--geometry", type=click.Path(path_type=Path), default=None,
              help="A geometry artifact: export its fitted vertices.")
@json_option
def export_cmd(model_path, out, shape, exp, sigma_units, geometry, as_json):
    """Export a face model (mean, given coefficients, or a fitted geometry) as a mesh with UVs."""
    from reflectmm_cli.geometry import load_face_model

    model = load_face_model(model_path)
    a, d = parse_coeffs(shape, "--coeffs"), parse_coeffs(exp, "--exp")
    if sigma_units:
        a = None if a is None else a * model.shape_sigma[: len(a)]
        d = None if d is None else d * model.exp_sigma[: len(d)]
    if geometry is not None:
        from reflectmm_cli.artifacts import read_artifact

        g = read_artifact(geometry, "geometry")
        verts = np.asarray(g["vertices"], dtype=np.float32)
        if verts.shape != model.mean_shape.shape:
            raise ReflectmmError(f"geometry has {verts.shape[0]} vertices, the face model {model.n_vertices}",
                                 geometry)
        model = type(model)(verts, None, None, None, None, model.triangles, model.uv, model.landmarks,
                            model.skin_mask, name=model.name)
        a = d = None
    emit([export_mesh(model, out, a, d)], as_json)


@face_model_group.command("info")
@click.argument("model_path", metavar="FILE", type=click.Path(path_type=Path))
@json_option
def info_cmd(model_path, as_json):
    """Print sizes, σ ranges and provenance of a face model (artifact or BFM .mat)."""
    from reflectmm_cli.geometry import load_face_model

    m = load_face_model(model_path)
    doc = {"name": m.name, "vertices": m.n_vertices, "triangles": int(len(m.triangles)), "shape": m.n_shape,
           "expression": m.n_exp, "landmarks": int(m.landmarks.size), "skin_vertices": int(m.skin_mask.sum()),
           "texture": m.mean_tex is not None, "info": m.info,
           "extent_mm": (m.mean_shape.max(0) - m.mean_shape.min(0)).round(2).tolist()}
    if as_json:
        click.echo(json.dumps(doc, indent=2, sort_keys=True, default=str))
    else:
        for k, v in doc.items():
            click.echo(f"{k}: {v}")


COMMANDS = [face_model_group]
