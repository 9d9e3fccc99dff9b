"""Stage ``finetune``: update-by-reconstruction of the reflectance model on in-the-wild shards (docs/design.md §7,
docs/finetune.md).

Inputs (roles): ``model`` the initial ``reflectance-model`` (build-pca, with its per-vertex part), ``light_model``
(build-light-pca), ``data`` the ``wild-shard`` files (or folders of them), optional ``face_model`` (previews and
the UV-map update; default: the one the shards record, :func:`reflectmm_cli.workspace.find_face_model`),
optional ``identity_weights`` (ArcFace safetensors; L_per is off without it), ``init_weights`` (an ImageNet
trunk for the encoder) and ``phase1_encoder`` (another run's phase-1 encoder: start at phase 2).

Reads → :func:`reflectmm_cli.finetune.train.finetune` → :func:`reflectmm_cli.finetune.outputs.
write_finetune_outputs`.  The parameters are generated from the fields of
:class:`reflectmm_cli.finetune.config.FinetuneConfig` (name, type, default, range, choices and help from the field
metadata): every weight, epoch count and learning rate is declared there once.  The fields whose default the
released-code variant changes (:data:`~reflectmm_cli.finetune.config.RELEASED`) are declared without a default
here and completed from ``variant`` (:func:`complete_params`) before the cache key is computed.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path
from typing import Any

from reflectmm_cli.errors import ReflectmmError
from reflectmm_cli.finetune.config import RELEASED, FinetuneConfig
from reflectmm_cli.params import Param
from reflectmm_cli.progress import log
from reflectmm_cli.stages.base import Default, Input, Stage, StageContext

VERB = "finetune"

#: FinetuneConfig annotation → Param kind.
_KINDS = {"int": "int", "float": "float", "str": "str", "int | None": "int", "tuple[float, float]": "floats"}

#: The stage's input roles (checked in recipes and on the command line; shown in --help).
INPUTS = (
    Input('model', 'reflectance-model', upstream='build-pca', default=Default()),
    Input('light_model', 'light-model', upstream='build-light-pca', default=Default()),
    Input('data', 'wild-shard', upstream='prepare-wild', many=True,
          default=Default('all', missing='--data: not given and no shards in {folder}')),
    Input('face_model', 'face-model artifact or BFM .mat', upstream='synth-multipie', help='the mesh and its UVs',
          default=Default('face-model', geometry='data', optional=True)),
    Input('init_weights', 'encoder weights (safetensors)', help='ImageNet-style initial weights'),
    Input('identity_weights', 'face-recognition weights (safetensors)'),
    Input('phase1_encoder', 'finetune-encoder', upstream='finetune', help='take phase 1 from this encoder instead of training it'),
)


def _two(v: list) -> None:
    """Adam's betas: two numbers, each in [0, 1) (at 1 its moment estimates never forget and its bias correction
    divides by zero)."""
    if len(v) != 2:
        raise ValueError(f"expected two numbers, got {len(v)}")
    for b in v:
        if not b < 1.0:
            raise ValueError(f"{b:g} is not below 1 (Adam's betas lie in [0, 1))")


def config_params() -> tuple[Param, ...]:
    """One :class:`Param` per :class:`FinetuneConfig` field (``extra`` excepted), from the field metadata."""
    out = []
    for f in dataclasses.fields(FinetuneConfig):
        if f.name == "extra":
            continue
        md = f.metadata
        kind = _KINDS[str(f.type)]
        rng = md.get("range")
        if rng is None and kind == "float":
            rng = (0.0, None)
        default = list(f.default) if isinstance(f.default, tuple) else f.default
        help_ = md["help"]
        if f.name in RELEASED and f.name != "variant":
            fmt = lambda v: f"{v:g}" if isinstance(v, float) else str(v)  # noqa: E731
            help_ += f"  [default: {fmt(default)}; --variant released: {fmt(RELEASED[f.name])}]"
            default = None
        out.append(Param(f.name, kind, default, range=rng, choices=md.get("choices"), help=help_,
                         option=md.get("option"), check=_two if f.name == "betas" else None))
    return tuple(out)


_SOLVE_KINDS = {"int": "int", "float": "float", "str": "str"}
#: The constraints of the least-squares update: off unless given, and then not recorded (cache keys of runs made
#: before these options are unchanged).
_SOLVE_OFF_BY_DEFAULT = ("harmonics", "robust", "update_bases", "pull_scale", "shard_images")


def solver_params() -> tuple[Param, ...]:
    """``solver`` (the paper's joint SGD, or the least-squares model update) and one ``ls_<field>`` Param per
    :class:`~reflectmm_cli.finetune.model_solve.SolveConfig` field, from the field metadata."""
    from reflectmm_cli.finetune.model_solve import SolveConfig

    out = [Param("solver", "str", "sgd", choices=("sgd", "ls"),
                 help="Model update: sgd = the paper's joint training of encoder and model (phase 2); ls = rounds of "
                      "per-image refinement and a least-squares model solve, then the encoder trained on the final "
                      "model with the same schedule and the model frozen (docs/finetune.md).")]
    for f in dataclasses.fields(SolveConfig):
        md = f.metadata
        kind = _SOLVE_KINDS[str(f.type)]
        off = f.name in _SOLVE_OFF_BY_DEFAULT
        rng = None if kind == "str" else md.get("range") or (0.0, None)
        out.append(Param("ls_" + f.name, kind, None if off else f.default, range=rng, choices=md.get("choices"),
                         help=md["help"] + (f" [default: {f.default}]" if kind == "str" else
                                            " [default: off]" if off else "")))
    return tuple(out)


def solve_config(params: dict[str, Any]):
    """The :class:`~reflectmm_cli.finetune.model_solve.SolveConfig` of resolved params."""
    from reflectmm_cli.finetune.model_solve import SolveConfig

    return SolveConfig(**{f.name: params["ls_" + f.name] for f in dataclasses.fields(SolveConfig)
                          if params.get("ls_" + f.name) is not None})


CONFIG_KEYS = tuple(f.name for f in dataclasses.fields(FinetuneConfig) if f.name != "extra")

PARAMS = config_params() + (
    Param("samples", "int", 60, range=(0, 1000), help="Model samples in the before/after PNGs."),
    Param("resume", "bool", False, invalidates_cache=False,
          help="Continue from the checkpoint in <output stem>_work/ (refused if made with other settings)."),
    Param("threads", "int", None, range=(1, 256), invalidates_cache=False,
          help="torch CPU threads (default: torch's; 1 is fastest for tiny problems on a busy machine)."),
    Param("jobs", "int", 1, range=(1, 256), invalidates_cache=False,
          help="Worker processes of the sharded least-squares update (--solver ls --ls-shard-images N): a local "
               "process pool, or LocalCluster workers with --executor dask. The result does not depend on it."),
    Param("executor", "str", "auto", choices=("auto", "serial", "pool", "dask"), invalidates_cache=False,
          help="Where the sharded update's map runs: auto = dask with --scheduler, pool with --jobs > 1, else "
               "serial."),
    Param("scheduler", "str", None, invalidates_cache=False, metavar="tcp://HOST:PORT",
          help="Address of a running Dask scheduler for the sharded update's map (implies --executor dask)."),
    Param("tensorboard", "path", None, invalidates_cache=False, metavar="DIR",
          help="Also write TensorBoard events to DIR: the JSONL log's losses, images/s and validation "
               "reconstructions (needs the 'tensorboard' package: pip install 'reflectmm[tensorboard]')."),
) + solver_params()


def config_from_params(params: dict[str, Any]) -> FinetuneConfig:
    """The :class:`FinetuneConfig` of resolved params: ``variant`` chooses the preset, given values override it."""
    given = {k: params[k] for k in CONFIG_KEYS if params.get(k) is not None and k != "variant"}
    if "betas" in given:
        given["betas"] = tuple(given["betas"])
    if params.get("variant", "paper") == "released":
        return FinetuneConfig.released(**given)
    return FinetuneConfig(**given)


def complete_params(params: dict[str, Any]) -> dict[str, Any]:
    """Resolved params with every config field filled from the variant (what keys the cache and goes to meta)."""
    full = config_from_params(params).to_dict()
    full.pop("extra", None)
    out = dict(params)
    out.update({k: v for k, v in full.items() if v is not None})
    return out


def data_paths(paths: list[Path]) -> list[Path]:
    """Shard files: the files given, and the ``*.npz`` of the folders given (sorted)."""
    out: list[Path] = []
    for p in paths:
        p = Path(p)
        if p.is_dir():
            found = sorted(q for q in p.glob("*.npz") if not q.name.startswith("."))
            if not found:
                raise ReflectmmError("no wild-shard .npz files in folder", p)
            out += found
        else:
            out.append(p)
    return out


def _outputs(ctx: StageContext) -> list[Path]:
    from reflectmm_cli.finetune.outputs import output_paths

    p = output_paths(ctx.output_path())
    phase1 = [p["encoder_phase1"]] if ctx.params.get("epochs2", 0) > 0 else []
    return [p["model"], p["encoder"]] + phase1 + [p["loss_png"]]


def _side_files(ctx: StageContext) -> list[Path]:
    from reflectmm_cli.finetune.outputs import output_paths

    return [p for k, p in output_paths(ctx.output_path()).items() if k != "workdir"]


def _one(ctx: StageContext, role: str) -> Path | None:
    paths = ctx.input_list(role, required=False)
    if len(paths) > 1:
        raise ReflectmmError(f"stage '{ctx.stage_name}': input '{role}' given {len(paths)} times, expected once")
    return paths[0] if paths else None


def run(ctx: StageContext) -> list[Path]:
    """The stage's run.  Its checkpoints and log are written at once (a resume after a kill reads them); its outputs
    are committed together by :func:`~reflectmm_cli.finetune.outputs.write_finetune_outputs`, the model last."""
    from reflectmm_cli.artifacts import written_at_once

    with written_at_once():
        return _run(ctx)


def _run(ctx: StageContext) -> list[Path]:
    from reflectmm_cli.finetune.identity import load_identity_net
    from reflectmm_cli.finetune.outputs import output_paths, write_finetune_outputs
    from reflectmm_cli.finetune.shards import load_shards
    from reflectmm_cli.finetune.train import CHECKPOINT_NAME, check_checkpoint, finetune, load_models
    from reflectmm_cli.geometry.face_model import load_face_model
    from reflectmm_cli.workspace import find_face_model

    p = ctx.params
    if p.get("tensorboard") is not None:  # a missing package is refused before anything is read or written
        from reflectmm_cli.finetune.tensorboard_log import require_tensorboard

        require_tensorboard()
    cfg = config_from_params(p)
    _check_map_options(p)
    out = ctx.output_path()
    model, light = load_models(ctx.input("model"), ctx.input("light_model"))
    data = data_paths(ctx.input_list("data"))
    shards = load_shards(data)
    identity = None
    weights = _one(ctx, "identity_weights")
    if weights is not None:
        identity = load_identity_net(weights, ctx.device)
        log.info(f"finetune: perceptual loss on ({identity.name} from {weights.name})")
    else:
        log.info("finetune: perceptual loss off (no --identity-weights given)")
    fm_path = _one(ctx, "face_model") or find_face_model(ctx.workspace, geometry=data[0])
    face_model = load_face_model(fm_path) if fm_path is not None else None
    if face_model is not None and model.vertex_albedo_mean is not None \
            and len(face_model.uv) != len(model.vertex_albedo_mean):  # checked before hours of training, not after
        raise ReflectmmError(f"has {len(face_model.uv)} vertices, the reflectance model {ctx.input('model')} "
                             f"{len(model.vertex_albedo_mean)}: not the face model it was built on", fm_path)
    _check_solver_options(p, model, face_model, fm_path)
    solve_cfg = solve_config(p) if p["solver"] == "ls" else None
    if solve_cfg is not None:
        # the encoder is trained on the solved model, which stays fixed; the solve's settings go with the run's
        # config, so that --resume refuses a checkpoint trained on a model solved otherwise
        solve = {k: v for k, v in dataclasses.asdict(solve_cfg).items() if k != "shard_images"}  # sharding
        cfg = cfg.replace(model_lr=0.0, extra={**dict(cfg.extra), "model_solve": solve})  # gives the same solve
    if p.get("resume"):  # a checkpoint of other settings is refused before the model solve, not after it
        check_checkpoint(output_paths(out)["workdir"] / CHECKPOINT_NAME, cfg, len(shards.indices("train")))
    train_model, solve_report = model, None
    if solve_cfg is not None:
        mesh = (face_model.mean_shape, face_model.triangles) if face_model is not None else None
        train_model, solve_report = _least_squares_update(model, light, shards, solve_cfg, ctx, mesh)
    res = finetune(shards, train_model, light, cfg, output_paths(out)["workdir"], device=ctx.device,
                   identity=identity, init_weights=_one(ctx, "init_weights"), resume=bool(p.get("resume")),
                   phase1_encoder=_one(ctx, "phase1_encoder"), log=log.info, threads=p.get("threads"),
                   tensorboard=p.get("tensorboard"))
    if solve_report is not None:
        from reflectmm_cli.finetune.render import ModelParams

        # the update is measured from the initial model, not from the solved one the encoder was trained on
        res.initial = ModelParams(model, "cpu", n_components=res.params.n_components).vertex_arrays()
        res.stats["model_solve"] = {"rounds": solve_report.rounds, "best_round": solve_report.best_round}
    return write_finetune_outputs(res, model, out, face_model=face_model, inputs=ctx.input_refs(out.parent),
                                  params=ctx.resolved_params(), producer=ctx.producer(), cache_key=ctx.cache_key,
                                  samples=p["samples"], seed=cfg.seed, log=log.info)


def _check_solver_options(p: dict[str, Any], model, face_model, fm_path) -> None:
    """The ``--ls-*`` options against the solver and the models, before anything is solved or trained: with
    ``--solver sgd`` a warning that they are not used; with ``--solver ls`` a one-line error for more mesh harmonics
    than the face model allows, and a warning for more bases to update than the model has."""
    from reflectmm_cli.finetune.model_solve import SolveConfig

    if p["solver"] != "ls":
        unused = [f"--ls-{f.name.replace('_', '-')} {p['ls_' + f.name]}" for f in dataclasses.fields(SolveConfig)
                  if p.get("ls_" + f.name) is not None and p["ls_" + f.name] != f.default]
        if unused:
            log.warning(f"finetune: warning: {', '.join(unused)}: option(s) of --solver ls, not used by --solver "
                        f"{p['solver']}")
        return
    harmonics = p.get("ls_harmonics") or 0
    if harmonics and face_model is not None:
        from reflectmm_cli.geometry.harmonics import max_mesh_harmonics

        V = int(len(face_model.mean_shape))
        if harmonics > max_mesh_harmonics(V):
            raise ReflectmmError(f"--ls-harmonics {harmonics}: the face model {fm_path} has {V} vertices, which "
                                 f"give at most {max_mesh_harmonics(V)} mesh harmonics")
    bases = p.get("ls_update_bases")
    if bases is not None and bases > model.n_components:
        log.warning(f"finetune: warning: --ls-update-bases {bases} but the reflectance model has "
                    f"{model.n_components} components; using {model.n_components}")


def _check_map_options(p: dict[str, Any]) -> None:
    """--jobs / --executor / --scheduler choose where the sharded update's map runs: refused (one line, before
    anything is read) where there is no map to run."""
    from reflectmm_cli.recipes.executors import executor_kind

    asked = p.get("jobs", 1) > 1 or p.get("executor", "auto") != "auto" or p.get("scheduler")
    if asked and not (p["solver"] == "ls" and p.get("ls_shard_images")):
        raise ReflectmmError("finetune: --jobs, --executor and --scheduler run the sharded model update; "
                             "give --solver ls --ls-shard-images N")
    executor_kind(p.get("executor", "auto"), p.get("jobs", 1), p.get("scheduler"))  # e.g. --scheduler with pool


def _least_squares_update(model, light, shards, scfg, ctx, mesh):
    """(the model with its per-vertex part solved by :func:`~reflectmm_cli.finetune.model_solve.alternate`, or by
    its map-reduce :func:`~reflectmm_cli.finetune.model_mapreduce.alternate_sharded` with ``--ls-shard-images``,
    the report); ``mesh`` (vertices, triangles) of the face model, for ``--ls-harmonics``."""
    from reflectmm_cli.finetune.model_mapreduce import alternate_sharded
    from reflectmm_cli.finetune.model_solve import alternate, with_solved

    p = ctx.params
    if scfg.shard_images:
        if ctx.device not in ("cpu", None):
            raise ReflectmmError(f"finetune: the sharded model update runs on the CPU (--device {ctx.device} given)")
        arrays, report = alternate_sharded(model, light, shards, scfg, log=log.info, mesh=mesh,
                                           executor=p.get("executor", "auto"), jobs=p.get("jobs", 1),
                                           scheduler=p.get("scheduler"), threads=p.get("threads") or 1)
    else:
        arrays, report = alternate(model, light, shards, scfg, device=ctx.device, log=log.info, mesh=mesh)
    return with_solved(model, arrays), report


STAGE = Stage(VERB, version=1, run=run, per_identity=False, outputs=_outputs, side_files=_side_files,
              params=PARAMS, complete=complete_params,
              help="finetune the reflectance model on in-the-wild shards (update-by-reconstruction)", inputs=INPUTS)
