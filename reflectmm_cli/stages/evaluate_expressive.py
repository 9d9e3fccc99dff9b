"""Stage ``evaluate-expressive``: how well each reflectance model can represent identities it has never seen,
measured against ground truth (synthetic world; library: :mod:`reflectmm_cli.evaluation.expressive`).

The held-out identities of a ``synth wild`` folder (its manifest's non-train split) have their true per-vertex
diffuse albedo and lobe weights projected onto each model (one free scale per identity, the model's prior). The
same projection onto the **oracle** (a model of the same size built from the training identities' truth by
``build-pca``'s own PCA and transfer) is the best a model of that size could do with that population. With
``gain = [A, B]`` the report gives the gap closed, ``(B − A) / (B − oracle)``, of both residuals.

Inputs: ``truth`` (a ``synth wild`` output folder: ``manifest.npz`` and ``identities/``), ``model_<name>`` per
method. Outputs: an ``evaluation`` artifact (``<ws>/evaluate-expressive/evaluate-expressive.npz``) and its
markdown table.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from reflectmm_cli.artifacts import atomic_write_text, write_artifact
from reflectmm_cli.errors import ReflectmmError
from reflectmm_cli.evaluation.documents import EVAL_KIND
from reflectmm_cli.evaluation.methods import check_method_names
from reflectmm_cli.params import Param
from reflectmm_cli.progress import log
from reflectmm_cli.stages.base import Default, Input, Stage, StageContext

VERB = "evaluate-expressive"

#: The stage's input roles (checked in recipes and on the command line; shown in --help).
INPUTS = (
    Input('truth', 'synth-wild folder or ground-truth files', upstream='synth-wild', many=True,
          default=Default('folder', checked=False)),
    Input('model', 'reflectance-model', prefix=True, help='one method each'),
)


def _check_gain(v) -> None:
    if len(v) != 2 or v[0] == v[1]:
        raise ValueError("give two different method names A,B (the gap closed from B to A)")
    check_method_names(v)


PARAMS = (
    Param("methods", "strs", None, check=check_method_names, option="",
          help="Method names in table order (inputs model_<name>); default: the model roles' names, sorted."),
    Param("prior", "float", 1e-3, range=(0.0, 1e6),
          help="λ of the projection's prior λ‖β‖² (the data term is relative to the truth's squared norm)."),
    Param("gain", "strs", ["finetuned", "initial"], check=_check_gain,
          help="A,B: the gap to the oracle that going from B to A closes."),
    Param("no_oracle", "bool", False, help="Do not build the oracle model from the training identities' truth."),
)

ROLE_OPTIONS = {"truth": "--truth"}


def _outputs(ctx: StageContext) -> list[Path]:
    out = ctx.output_path()
    return [out, out.with_suffix(".md")]


def load_wild_truth(folder: Path) -> dict:
    """Per identity of a ``synth wild`` folder: ``{"train": [ids], "heldout": [ids], "albedo": {id: (V,3)},
    "weights": {id: (V,K)}, "skin": {id: (V,)}}`` (an identity is held out when its images are not in the train
    split)."""
    from reflectmm_cli.artifacts import read_artifact

    folder = Path(folder)
    man_path = folder / "manifest.npz"
    if not man_path.is_file():
        raise ReflectmmError("not a synth wild folder (no manifest.npz)", folder)
    man = read_artifact(man_path)
    ident = np.asarray(man["identity"]).astype(int)
    split = np.asarray(man["split"]).astype(str)
    ids = sorted(set(int(i) for i in ident))
    train = [i for i in ids if (split[ident == i] == "train").all()]
    held = [i for i in ids if i not in train]
    out = {"train": train, "heldout": held, "albedo": {}, "weights": {}, "skin": {}}
    for i in ids:
        a = read_artifact(folder / "identities" / f"id{i:05d}.npz")
        for k, key in (("albedo", "vertex_albedo"), ("weights", "vertex_weights"), ("skin", "vertex_skin")):
            if key not in a.arrays:
                raise ReflectmmError(f"wild truth has no array '{key}'", a.path)
            out[k][i] = np.asarray(a[key])
    if not held:
        raise ReflectmmError("the manifest holds no held-out identity (every identity is in the train split)",
                             man_path)
    return out


def run(ctx: StageContext) -> list[Path]:
    from reflectmm_cli.evaluation.expressive import gap_closed, oracle_model, projection_residuals
    from reflectmm_cli.evaluation.face_metrics import format_ci, mean_ci
    from reflectmm_cli.evaluation.methods import command_line, methods_from_inputs
    from reflectmm_cli.evaluation.reconstruction_eval import markdown_table
    from reflectmm_cli.evaluation.results import evaluation_arrays
    from reflectmm_cli.stages.evaluation_inputs import load_model

    p = ctx.params
    methods = methods_from_inputs(ctx.inputs, p.get("methods"), stage=VERB)
    names = [m.name for m in methods]
    missing = [g for g in p["gain"] if g not in names]
    if missing and list(p["gain"]) != ["finetuned", "initial"]:
        raise ReflectmmError(f"{VERB}: --gain names {', '.join(missing)}, not among the methods ({', '.join(names)})")
    tr = load_wild_truth(ctx.input("truth"))
    held = tr["heldout"]
    ta = np.stack([tr["albedo"][i] for i in held]).astype(np.float64)
    tw = np.stack([tr["weights"][i] for i in held]).astype(np.float64)
    region = np.stack([tr["skin"][i] for i in held]).astype(bool)
    parts: dict[str, dict] = {}
    for m in methods:
        model = load_model(m.model)
        if getattr(model, "vertex_albedo_mean", None) is None:
            raise ReflectmmError(f"{VERB}: method '{m.name}': the model has no per-vertex part", m.model)
        if model.vertex_albedo_mean.shape != ta.shape[1:] or model.vertex_weights_mean.shape != tw.shape[1:]:
            raise ReflectmmError(f"{VERB}: method '{m.name}': the model has {model.vertex_albedo_mean.shape[0]} "
                                 f"vertices × {model.vertex_weights_mean.shape[1]} lobes, the truth "
                                 f"{ta.shape[1]} × {tw.shape[2]}", m.model)
        parts[m.name] = {"vertex_albedo_mean": model.vertex_albedo_mean, "vertex_albedo_basis":
                         model.vertex_albedo_basis, "vertex_weights_mean": model.vertex_weights_mean,
                         "vertex_weights_basis": model.vertex_weights_basis, "sigma": model.sigma,
                         "exponents": model.exponents}
    if not p["no_oracle"]:
        first = parts[names[0]]
        M = int(np.shape(first["sigma"])[0])
        parts["oracle"] = oracle_model(np.stack([tr["albedo"][i] for i in tr["train"]]),
                                       np.stack([tr["weights"][i] for i in tr["train"]]), first["exponents"], M)
    prior = float(p["prior"])
    doc, rows, means = {}, [], {}
    for name, mdl in parts.items():
        ra = projection_residuals(mdl["vertex_albedo_mean"], mdl["vertex_albedo_basis"], mdl["sigma"], ta, region,
                                  prior=prior)
        rw = projection_residuals(mdl["vertex_weights_mean"], mdl["vertex_weights_basis"], mdl["sigma"], tw, region,
                                  prior=prior)
        ca, cw = mean_ci(ra), mean_ci(rw)
        doc[name] = {"albedo_residual": ra, "weights_residual": rw}
        means[name] = (ca["mean"], cw["mean"])
        rows.append({"model": name, "components": str(int(np.shape(mdl["sigma"])[0])),
                     "albedo residual": format_ci(ca, 3), "lobe-weight residual": format_ci(cw, 3)})
    gap = {}
    a, b = p["gain"]
    if "oracle" in means and a in means and b in means:
        gap = {"albedo": gap_closed(means[b][0], means[a][0], means["oracle"][0]),
               "weights": gap_closed(means[b][1], means[a][1], means["oracle"][1])}
        doc["gap_closed"] = gap
    table = markdown_table(rows)
    out = ctx.output_path()
    cmd = command_line(["evaluate", "expressive"], p, ctx.inputs, workspace=ctx.workspace, output=out,
                       role_options=ROLE_OPTIONS, declared=PARAMS)
    protocol = (f"Relative residual ‖s·(μ + Σ β_k σ_k b_k) − t‖ / ‖t‖ of the true per-vertex diffuse albedo and lobe "
                f"weights t of the {len(held)} held-out wild identities over their skin vertices, after projection "
                f"onto each model (one free scale s per identity, prior λ = {prior:g} on β; mean ± 95 % CI over "
                f"identities). `oracle`: a model of the same size built from the {len(tr['train'])} training "
                f"identities' truth by build-pca's PCA and transfer.")
    md = f"# Expressive power on held-out identities\n\n{protocol}\n\n{table}\n"
    if gap:
        md += (f"\nGap to the oracle closed by going from `{b}` to `{a}`: diffuse albedo {100 * gap['albedo']:.0f} %, "
               f"lobe weights {100 * gap['weights']:.0f} % (negative: the model moved away from what it should "
               "learn).\n")
    md += f"\nCommand: `{cmd}`\n"
    write_artifact(out, EVAL_KIND, evaluation_arrays(doc), params=ctx.resolved_params(),
                   inputs=ctx.input_refs(out.parent), producer=ctx.producer(), cache_key=ctx.cache_key,
                   extra_meta={"evaluation": "expressive", "command": cmd, "table": table, "methods": names,
                               "identities": {"train": tr["train"], "heldout": held}, "gap_closed": gap,
                               "means": {k: {"albedo": v[0], "weights": v[1]} for k, v in means.items()},
                               "protocol": protocol})
    atomic_write_text(out.with_suffix(".md"), md)
    log.info(table)
    return [out, out.with_suffix(".md")]


STAGE = Stage(VERB, version=1, run=run, per_identity=False, outputs=_outputs, params=PARAMS,
              help="expressive power: held-out identities' true reflectance projected onto each model and an oracle", inputs=INPUTS)
