"""Stage ``build-baseline``: the paper's baseline reflectance models rebuilt from ground truth — BFM09's role
(``diffuse-only``) and AlbedoMM's role (``albedomm``), models (a) and (b) of Tables 2 and 3 — and the ``oracle``
of finetuning, the model of the same size built from the wild training identities' truth (the ceiling row of
Table 2; library: :mod:`reflectmm_cli.evaluation.baselines`, :mod:`reflectmm_cli.evaluation.expressive`;
docs/evaluation.md).

Inputs: ``truth`` (synth-truth ``<id>.npz`` files, or the folder holding them — the "scanned" identities; for
``oracle`` a ``synth wild`` folder, whose train split is used), ``face_model`` (for the per-vertex model that
finetune / reconstruct / evaluate read), ``like`` (``oracle`` only: the model whose size it takes). Output: a
``reflectance-model`` artifact ``<ws>/build-baseline/<kind>.npz`` (or ``--output``) and its component preview.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from reflectmm_cli.artifacts import read_artifact, write_png
from reflectmm_cli.errors import ReflectmmError
from reflectmm_cli.params import Param
from reflectmm_cli.progress import log
from reflectmm_cli.stages.base import Default, Input, Stage, StageContext
from reflectmm_cli.workspace import WORKSPACE_FACE_MODELS, check_given_once

VERB = "build-baseline"

#: The stage's input roles (checked in recipes and on the command line; shown in --help).
INPUTS = (
    Input('truth', 'ground-truth NPZ files or their folder', upstream='synth-multipie', many=True, help='identities to build the baseline from',
          default=Default('truth')),
    Input('face_model', 'face-model artifact or BFM .mat', upstream='synth-multipie', help='the mesh and its UVs',
          default=Default('face-model', wild='truth', missing=(
              "build-baseline: no --face-model given and none found (looked for face_model.npz in the --truth folder "
              "{truth}, and for " + ", ".join(WORKSPACE_FACE_MODELS) + " in {workspace}); pass --face-model"))),
    Input('like', 'reflectance-model', upstream='build-pca',
          help='kind oracle: a model of this size (its component count caps --components; its UV size and lobe '
               'exponents are used and checked)'),
)


def _check_ids(ids) -> None:
    if ids and len(set(ids)) != len(ids):
        raise ValueError("an identity is listed twice")


PARAMS = (
    Param("kind", "str", "diffuse-only", choices=("diffuse-only", "albedomm", "oracle"),
          help="diffuse-only = BFM09's role (Lambertian PCA); albedomm = AlbedoMM's role (diffuse + specular "
               "albedo PCA, one Blinn-Phong lobe); oracle = the model of the same size built from a synth wild "
               "folder's training identities' true per-vertex reflectance (the ceiling of finetuning)."),
    Param("components", "int", 80, range=(1, None), help="PCA components (capped by N − 1 with a message)."),
    Param("exponent", "float", 20.0, range=(0.0, 10000.0), low_open=True,
          help="Global Blinn-Phong exponent of the albedomm baseline (ignored for diffuse-only)."),
    Param("ids", "strs", None, check=_check_ids,
          help="Use only these truth identities (default: every file given); keep the held-out identities "
               "of Table 3 / relighting out."),
    Param("preview", "bool", True, option="--no-preview", help="Skip the component preview PNG."),
    Param("uv_size", "int", 256, range=(8, 8192),
          help="kind oracle without --like: size of its UV maps (with --like, that model's)."),
)


def _out(ctx: StageContext) -> Path:
    return Path(ctx.output) if ctx.output is not None else ctx.output_path(name=ctx.params["kind"])


def _outputs(ctx: StageContext) -> list[Path]:
    out = _out(ctx)
    return [out] + ([out.with_name(out.stem + "_components.png")] if ctx.params["preview"] else [])


def truth_files(paths: list[Path], ids: list[str] | None) -> list[Path]:
    """The synth-truth files of ``paths`` (files, or folders of ``<id>.npz``), restricted to ``ids`` (in that
    order; a missing one is an error)."""
    files: list[Path] = []
    for p in paths:
        p = Path(p)
        files += sorted(q for q in p.glob("*.npz") if not q.name.startswith(".")) if p.is_dir() else [p]
    if ids:
        by = {f.stem: f for f in files}
        missing = [i for i in ids if i not in by]
        if missing:
            raise ReflectmmError(f"build-baseline: no truth file for identity '{missing[0]}' "
                                 f"(have {', '.join(sorted(by)) or 'none'})")
        files = [by[i] for i in ids]
    check_given_once(files, "each identity counts once", "build-baseline: ")  # e.g. a folder and one of its files
    return files


def load_truths(paths: list[Path]) -> tuple[list[dict[str, np.ndarray]], list[str]]:
    """Read ``synth-truth`` artifacts → (list of {albedo, spec_albedo, uv_mask, …} dicts, identity ids), each
    checked by :func:`reflectmm_cli.evaluation.baselines.truth_maps` (the stage reads, the library builds)."""
    from reflectmm_cli.evaluation.baselines import truth_maps

    out, ids = [], []
    for p in paths:
        art = read_artifact(p, "synth-truth")
        arrs = {k: np.asarray(art.arrays[k]) for k in ("albedo", "spec_albedo", "uv_mask", "vertex_albedo",
                                                       "vertex_spec_albedo") if k in art.arrays}
        truth_maps(arrs, str(p))
        if out and np.shape(arrs["albedo"]) != np.shape(out[0]["albedo"]):  # the PCA would say "build-pca: <id>"
            raise ReflectmmError(f"build-baseline: albedo has shape {np.shape(arrs['albedo'])}, but "
                                 f"{np.shape(out[0]['albedo'])} in {paths[0]}: the truths must share one UV size", p)
        out.append(arrs)
        ids.append(str(art.meta.get("identity", Path(p).stem)))
    return out, ids


def _pca_components(requested: int, n: int, what: str, path: Path | None = None) -> int:
    """The component count of a PCA of ``n`` identities: at least 2 of them (else a one-line error naming ``what``
    they are), at most N − 1 components (said on stderr when fewer than ``requested``)."""
    if n < 2:
        raise ReflectmmError(f"build-baseline: a PCA needs at least 2 {what} identities, got {n}", path)
    if requested > n - 1:
        log.info(f"build-baseline: {requested} components requested, {n} identities: using {n - 1}")
    return min(int(requested), n - 1)


def _oracle(ctx: StageContext, fm):
    """The ``oracle`` kind: (model, number of training identities)."""
    from reflectmm_cli.artifacts import read_meta
    from reflectmm_cli.evaluation.expressive import oracle_reflectance_model
    from reflectmm_cli.stages.evaluate_expressive import load_wild_truth
    from reflectmm_cli.stages.evaluation_inputs import load_model

    p = ctx.params
    if p.get("ids"):
        raise ReflectmmError("build-baseline: --ids does not apply to kind oracle (it takes the synth wild "
                             "folder's train split)")
    truths = ctx.input_list("truth")
    if len(truths) != 1 or not Path(truths[0]).is_dir():
        raise ReflectmmError(f"build-baseline: kind oracle needs one synth wild folder as --truth, got "
                             f"{', '.join(map(str, truths)) or 'none'}")
    folder = Path(truths[0])
    tr = load_wild_truth(folder)
    train = tr["train"]
    _pca_components(1, len(train), "training", folder)  # too few identities: said before the model is read
    exps = read_meta(folder / "identities" / f"id{train[0]:05d}.npz").get("exponents")  # its arrays are read above
    if exps is None:
        raise ReflectmmError("the wild truth does not name its lobe exponents (meta 'exponents')",
                             folder / "identities" / f"id{train[0]:05d}.npz")
    comps, size = int(p["components"]), int(p["uv_size"])
    like = ctx.input_list("like", required=False)
    if like:
        ref = load_model(like[0])
        if not np.allclose(np.asarray(ref.exponents, np.float64), np.asarray(exps, np.float64)):
            raise ReflectmmError(f"build-baseline: the model's lobe exponents {list(map(float, ref.exponents))} "
                                 f"differ from the wild truth's {list(map(float, exps))}", like[0])
        V = int(np.shape(tr["albedo"][train[0]])[0])
        if ref.vertex_albedo_mean is not None and ref.vertex_albedo_mean.shape[0] != V:
            raise ReflectmmError(f"build-baseline: the model has {ref.vertex_albedo_mean.shape[0]} vertices, the wild "
                                 f"truth {V} (another face model?)", like[0])
        comps, size = min(comps, ref.n_components), ref.size
    comps = _pca_components(comps, len(train), "training", folder)
    model = oracle_reflectance_model(np.stack([tr["albedo"][i] for i in train]),
                                     np.stack([tr["weights"][i] for i in train]), exps, comps, fm.uv,
                                     fm.triangles, size, ids=[f"wild{i:05d}" for i in train])
    return model, len(train)


def run(ctx: StageContext) -> list[Path]:
    from reflectmm_cli.evaluation.baselines import build_baseline, write_baseline_model
    from reflectmm_cli.geometry.face_model import load_face_model

    p = ctx.params
    fm_path = ctx.input("face_model")
    if p["kind"] == "oracle":
        fm = load_face_model(fm_path)
        model, n = _oracle(ctx, fm)
    else:
        if ctx.input_list("like", required=False):
            raise ReflectmmError(f"build-baseline: --like applies to kind oracle only, not {p['kind']}")
        files = truth_files(ctx.input_list("truth"), p.get("ids"))
        comps = _pca_components(int(p["components"]), len(files), "truth")
        truths, ids = load_truths(files)
        fm = load_face_model(fm_path)
        nv = {int(np.asarray(t["vertex_albedo"]).shape[0]) for t in truths if t.get("vertex_albedo") is not None}
        if nv and nv != {int(fm.uv.shape[0])}:  # the truth's own mesh: the per-vertex part must be laid on it
            raise ReflectmmError(f"build-baseline: has {fm.uv.shape[0]} vertices, the truth's meshes "
                                 f"{', '.join(str(n) for n in sorted(nv))}: not the face model the truth was made "
                                 "with", fm_path)
        model = build_baseline(p["kind"], truths, components=comps, ids=ids, vertex_uv=fm.uv,
                               exponent=float(p["exponent"]), log=log.info)
        n = len(files)
    out = _out(ctx)
    written = []
    if p["preview"]:
        from reflectmm_cli.model.preview import component_grid

        written.append(write_png(out.with_name(out.stem + "_components.png"), component_grid(model, 3, 2.0)))
    write_baseline_model(model, out, params=ctx.resolved_params(), inputs=ctx.input_refs(out.parent),
                         producer=ctx.producer(), cache_key=ctx.cache_key,
                         face_model={"path": Path(fm_path).name, "n_vertices": int(fm.uv.shape[0])})
    log.info(f"build-baseline: {p['kind']} from {n} truth identities, {model.n_components} components")
    return [out] + written


STAGE = Stage(VERB, version=2, run=run, per_identity=False, outputs=_outputs, params=PARAMS, inputs=INPUTS,
              help="baseline reflectance model from ground truth (BFM09's or AlbedoMM's role, or the oracle)")
