"""The explicit list of built-in stages: verb → module of :mod:`reflectmm_cli.stages`, and :func:`run_stage`.

Each module defines ``STAGE`` (a :class:`~reflectmm_cli.stages.base.Stage`).  Looking a verb up imports only
that module (no click, no scanning of packages), so the recipe planner and Dask workers find a stage without
loading the command line.  A new stage: write ``reflectmm_cli/stages/<verb>.py`` and add one line here.

:func:`run_stage` lives here, not in :mod:`.base`, because it looks a verb up: the dependency goes one way,
registry → base.
"""

from __future__ import annotations

import importlib
from pathlib import Path
from typing import Any, Callable, Iterable, Mapping

from reflectmm_cli.errors import ReflectmmError
from reflectmm_cli.stages.base import (Stage, StageContext, cache_key_doc, check_no_overwrite, key_of_doc,
                                       resolve_device, run_committed)
from reflectmm_cli.workspace import default_workspace

#: verb → module name under reflectmm_cli.stages (the built-in stages, in pipeline order).
STAGE_MODULES: dict[str, str] = {
    "synth-multipie": "synth_multipie",
    "synth-envmaps": "synth_envmaps",
    "synth-wild": "synth_wild",
    "detect-landmarks": "detect_landmarks",
    "prepare-wild": "prepare_wild",
    "face-model-create": "face_model_create",
    "face-model-import": "face_model_import",
    "face-model-embed": "face_model_embed",
    "preprocess-multipie": "preprocess_multipie",
    "calibrate-rig": "calibrate_rig",
    "fit-geometry": "fit_geometry",
    "unwrap-uv": "unwrap_uv",
    "fit-reflectance": "fit_reflectance",
    "build-pca": "build_pca",
    "build-light-pca": "build_light_pca",
    "render": "render",
    "finetune": "finetune",
    "reconstruct": "reconstruct",
    "evaluate-truth": "evaluate_truth",
    "evaluate-representation": "evaluate_representation",
    "build-baseline": "build_baseline",
    "evaluate-albedo": "evaluate_albedo",
    "evaluate-expressive": "evaluate_expressive",
    "evaluate-reconstruction": "evaluate_reconstruction",
    "evaluate-relighting": "evaluate_relighting",
    "evaluate-report": "evaluate_report",
    "checksum": "checksum",
    "view": "view",
}

#: verb → Stage: the built-in stages loaded so far and those registered with :func:`register_stage`.
_REGISTRY: dict[str, Stage] = {}


def _load(verb: str) -> Stage:
    if verb not in _REGISTRY:
        mod = importlib.import_module(f"reflectmm_cli.stages.{STAGE_MODULES[verb]}")
        stage = mod.STAGE
        if stage.verb != verb:  # pragma: no cover - a wrong registry line
            raise RuntimeError(f"stages.{STAGE_MODULES[verb]} defines '{stage.verb}', registered as '{verb}'")
        _REGISTRY[verb] = stage
    return _REGISTRY[verb]


def get_stage(verb: str) -> Stage:
    """The stage of ``verb``; a one-line error listing the known verbs otherwise."""
    if verb in _REGISTRY or verb in STAGE_MODULES:
        return _load(verb)
    from reflectmm_cli.params import closest_name

    known = sorted(set(STAGE_MODULES) | set(_REGISTRY))
    near = closest_name(verb, known)
    hint = f"did you mean '{near}'? " if near else ""
    raise ReflectmmError(f"unknown stage verb '{verb}' ({hint}known: {', '.join(known)})")


def all_stages() -> dict[str, Stage]:
    """Every stage (built-in and registered), by verb."""
    for v in STAGE_MODULES:
        _load(v)
    return dict(_REGISTRY)


def register_stage(verb: str, version: int = 1, per_identity: bool = False, **kwargs: Any
                   ) -> Callable[[Callable[[StageContext], list[Path]]], Callable[[StageContext], list[Path]]]:
    """Decorator registering ``run(ctx) -> list[Path]`` as an extra stage (tests, extensions); built-in stages
    are listed in :data:`STAGE_MODULES` instead."""

    def deco(fn: Callable[[StageContext], list[Path]]) -> Callable[[StageContext], list[Path]]:
        if verb in STAGE_MODULES or (verb in _REGISTRY and _REGISTRY[verb].run is not fn):
            raise RuntimeError(f"stage '{verb}' registered twice")
        _REGISTRY[verb] = Stage(verb=verb, version=version, run=fn, per_identity=per_identity, **kwargs)
        return fn

    return deco


def run_stage(stage: "Stage | str", *, workspace: Path | None = None, identity: str | None = None,
              params: Mapping[str, Any] | None = None, inputs: Mapping[str, Iterable[Path]] | None = None,
              output: Path | None = None, device: str = "cpu", stage_name: str | None = None) -> list[Path]:
    """Run a stage once (the command line's path, also the Python API), with the cache key a recipe computes.

    ``params`` are the given values (None = not given); they are validated and completed with the declared
    defaults before the cache key.  Every input path must exist.  Returns the paths written.
    """
    if isinstance(stage, str):
        stage = get_stage(stage)
    ctx = stage.context(workspace=Path(workspace or default_workspace()).resolve(),
                        stage_name=stage_name or stage.verb, identity=identity, params=dict(params or {}),
                        inputs={k: [Path(p) for p in v] for k, v in (inputs or {}).items()},
                        output=output, device=resolve_device(device) if device else "cpu")
    stage.check_roles(ctx.inputs)
    for role, paths in ctx.inputs.items():
        for p in paths:
            if not Path(p).exists():
                raise ReflectmmError(f"input '{role}' not found", p)
    check_no_overwrite(stage, ctx)
    used: dict[str, Any] = {}
    ctx = ctx.with_(cache_key=key_of_doc(cache_key_doc(stage, ctx, {}, used)))
    return run_committed(stage, ctx, used)
