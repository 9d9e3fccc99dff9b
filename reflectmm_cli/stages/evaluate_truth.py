"""Stage ``evaluate-truth``: errors of one identity's fitted maps (and geometry) against ground truth."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from reflectmm_cli.artifacts import read_artifact, write_artifact
from reflectmm_cli.errors import ReflectmmError
from reflectmm_cli.evaluation.documents import EVAL_KIND, flatten
from reflectmm_cli.stages.base import Stage, StageContext

VERB = "evaluate-truth"

PARAMS = ()


def evaluate_truth(maps_path: Path | None, truth_path: Path, geometry_path: Path | None = None) -> dict:
    """Library entry: the error document of fitted maps (and geometry) against a synth-truth file."""
    from reflectmm_cli.evaluation.truth import geometry_errors, reflectance_errors

    truth = read_artifact(truth_path)
    if truth.kind not in ("synth-truth", "reflectance-maps"):
        raise ReflectmmError(f"is a '{truth.kind}' artifact, expected a 'synth-truth' artifact", truth_path)
    doc: dict = {}
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


def run(ctx: StageContext) -> list[Path]:
    maps = ctx.input_list("maps", required=False)
    geo = ctx.input_list("geometry", required=False)
    doc = evaluate_truth(maps[0] if maps else None, ctx.input("truth"), geo[0] if geo else None)
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
              help="errors of fitted maps / geometry against ground truth")
