"""The two-phase finetuning loop (docs/design.md §7): phase 1 trains the encoder with the model frozen, phase 2 trains
the encoder and the model's mean and bases jointly. Adam; deterministic on CPU for a seed; atomic checkpoints
(one safetensors file with the JSON state in its header) every N steps and at each epoch end; ``resume``.

Call: ``result = finetune(shards, model, light, config, workdir)`` → :class:`FinetuneResult`; then
:func:`reflectmm_cli.finetune.outputs.write_finetune_outputs` writes the artifacts.
"""
from __future__ import annotations

import json
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

import numpy as np

from reflectmm_cli.errors import ReflectmmError

from .config import FinetuneConfig
from .shards import ShardSet

__all__ = ["FinetuneResult", "finetune", "check_inputs", "check_checkpoint", "load_models", "Trainer",
           "CHECKPOINT_NAME", "LOG_NAME", "PARTIAL_LOG_NAME"]

CHECKPOINT_NAME = "checkpoint.safetensors"
#: the JSONL log of the last run that finished training
LOG_NAME = "log.jsonl"
#: the JSONL log of the run in progress (or interrupted: ``--resume`` continues it); it replaces :data:`LOG_NAME`
#: when that run finishes training, so an interrupted rerun leaves the previous run's log as it was
PARTIAL_LOG_NAME = "log.partial.jsonl"
CHECKPOINT_SCHEMA = "reflectmm.finetune-checkpoint/1"

#: Memory (MiB) for the per-image SH bases of the G-buffer pixels kept across steps (648 B per pixel at order 8,
#: float32: ≈ 15 MiB per 224² image); an execution detail, never part of a result.
BASIS_CACHE_MB = 2048.0


@dataclass
class FinetuneResult:
    """What training produced.

    Attributes:
        params: final :class:`~reflectmm_cli.finetune.render.ModelParams` (the effective per-vertex model).
        encoder: the trained encoder (eval mode).
        initial: the initial per-vertex arrays (``vertex_*`` numpy).
        history: step and validation records (as in the JSONL log).
        config: the config used; perceptual: "off" or the identity network's name; z0: the head's z at start.
        steps: global steps done; stopped_early: True when ``stop_after`` ended the run.
    """

    params: object
    encoder: object
    initial: dict
    history: list
    config: FinetuneConfig
    perceptual: str
    z0: float
    steps: int
    stopped_early: bool = False
    n_train: int = 0
    n_val: int = 0
    stats: dict = field(default_factory=dict)
    phase1_encoder: Path | None = None
    image_size: int | None = None  # the side S of the training images (recorded in the encoder's meta)


#: A step loss this many times the run's first is taken as divergence (the run stops, nothing is written).
DIVERGED_FACTOR = 1e4


def load_models(model_path, light_path):
    """(ReflectanceModel, LightModel) from a ``reflectance-model`` and a ``light-model`` artifact."""
    from reflectmm_cli.artifacts import read_artifact
    from reflectmm_cli.model.light import LIGHT_MODEL_KIND, light_model_from_arrays
    from reflectmm_cli.model.pca import MODEL_KIND, model_from_arrays

    art = read_artifact(model_path, MODEL_KIND)
    _check_finite(art.arrays, model_path)
    model = model_from_arrays(art.arrays, art.meta.get("stats"), path=model_path)
    if model.vertex_albedo_mean is None:
        raise ReflectmmError("the reflectance model has no per-vertex part (build it with build-pca --face-model); "
                             "finetuning and reconstruction shade per vertex", model_path)
    lart = read_artifact(light_path, LIGHT_MODEL_KIND)
    _check_finite(lart.arrays, light_path)
    light = light_model_from_arrays(lart.arrays)
    return model, light


def _check_finite(arrays, path) -> None:
    """One line naming the file and the first array holding NaN or inf (a model that would poison training)."""
    for k in sorted(arrays):
        a = np.asarray(arrays[k])
        if a.dtype.kind == "f" and not np.isfinite(a).all():
            raise ReflectmmError(f"array '{k}' contains NaN or inf ({int((~np.isfinite(a)).sum())} values)", path)


def _shard_face_model_vertices(shards) -> int | None:
    """The vertex count of the face model the shards' meta records, when that file is a readable face-model
    artifact (None otherwise: the vertex-id bound above is then the only check)."""
    from reflectmm_cli.artifacts import read_artifact

    ref = getattr(shards, "face_model", None) or {}
    path = ref.get("resolved")
    if not path or not str(path).endswith(".npz") or not Path(path).is_file():
        return None
    try:
        return int(read_artifact(path, "face-model", members=("mean_shape",))["mean_shape"].shape[0])
    except ReflectmmError:
        return None


def check_inputs(shards: ShardSet, model, light, verb: str = "finetune") -> None:
    """One-line errors (prefixed with ``verb``) for a model/light-model/shard mismatch (vertex count, SH order,
    per-vertex part)."""
    if getattr(model, "vertex_albedo_mean", None) is None:
        raise ReflectmmError(f"{verb}: the reflectance model has no per-vertex part (build it with --face-model)")
    V = int(model.vertex_albedo_mean.shape[0])
    vmax = int(shards.vert_ids.max()) if shards.vert_ids.size else -1
    if vmax >= V:
        raise ReflectmmError(f"{verb}: the shards reference vertex {vmax} but the reflectance model has {V} "
                             f"vertices (shards made with another face model?)")
    n_fm = _shard_face_model_vertices(shards)
    if n_fm is not None and n_fm != V:  # a smaller mesh's ids all lie below V: only its face model tells
        raise ReflectmmError(f"{verb}: the shards were made with a face model of {n_fm} vertices "
                             f"({shards.face_model.get('resolved')}), the reflectance model has {V}",
                             shards.sources[0] if getattr(shards, "sources", None) else None)
    if int(light.order) != int(shards.sh_order):
        raise ReflectmmError(f"{verb}: the light model has SH order {light.order} but the shards were prepared "
                             f"for order {shards.sh_order}")
    if model.vertex_weights_mean.shape[-1] != len(model.exponents):
        raise ReflectmmError(f"{verb}: the model's lobe weights and exponents disagree in count")


def _np(t):
    return t.detach().cpu().numpy()


class Trainer:
    """State of one finetuning run (encoder, model parameters, optimiser, schedule position)."""

    def __init__(self, shards: ShardSet, model, light, config: FinetuneConfig, workdir: Path, *, device="cpu",
                 identity=None, init_weights=None, log: Callable[[str], None] | None = None, progress=True,
                 basis_cache_mb: float = BASIS_CACHE_MB):
        import torch

        from .encoder import build_encoder, load_trunk
        from .render import ModelParams

        check_inputs(shards, model, light)
        self.shards, self.model, self.light, self.cfg = shards, model, light, config
        self.workdir = Path(workdir)
        self.device = torch.device(device)
        self.identity = identity
        self.log = log or (lambda s: None)
        self.show_progress = progress
        self.train_idx = shards.indices("train")
        self.val_idx = shards.indices("val")
        if len(self.train_idx) == 0:
            raise ReflectmmError("finetune: the shards have no image in the 'train' split")
        M = model.n_components if config.n_reflectance is None else min(config.n_reflectance, model.n_components)
        NL = light.n_components if config.n_light is None else min(config.n_light, light.n_components)
        for opt, asked, got, what in (("--components", config.n_reflectance, M, "reflectance model"),
                                      ("--light-components", config.n_light, NL, "light model")):
            if asked is not None and asked > got:
                self.log(f"finetune: warning: {opt} {asked} but the {what} has {got} components; using {got}")
        given = ("the model given (solved by --solver ls before training)" if "model_solve" in config.extra
                 else "the initial one")
        if config.epochs1 == 0 and config.epochs2 == 0:
            self.log("finetune: warning: --epochs1 0 --epochs2 0: no training step; the encoder written is the "
                     f"untrained initialisation and the model is {given}")
        elif ((config.epochs1 == 0 or config.lr1 == 0) and (config.epochs2 == 0 or config.lr2 == 0)
              and (config.epochs2 == 0 or config.model_lr == 0)):
            self.log("finetune: warning: every learning rate of the phases that run is 0: the steps change nothing; "
                     f"the encoder written is the one the run starts from and the model is {given}")
        self.M, self.NL = M, NL
        dc = getattr(light, "dc", None)
        self.z0 = float(np.mean(dc)) if dc is not None and np.size(dc) and np.all(np.asarray(dc) > 0) else 1.0
        torch.manual_seed(config.seed)
        self.encoder = build_encoder(config.arch, M, NL, config.width, self.z0).to(self.device)
        if init_weights:
            load_trunk(self.encoder, init_weights)
        self.params = ModelParams(model, self.device, trainable=None, n_components=M)
        self.initial = {k: v.detach().clone() for k, v in
                        zip(("albedo_mean", "albedo_basis", "weights_mean", "weights_basis"), self.params.effective())}
        self.initial_np = self.params.vertex_arrays()
        self.B = int(config.batch_size)
        n = len(self.train_idx)
        if n < 2 or self.B < 2:
            raise ReflectmmError(f"finetune: BatchNorm needs batches of at least 2 images (train split: {n} "
                                 f"images, batch size {self.B})")
        self.steps_per_epoch = -(-n // self.B)
        self.plan = [(1, e) for e in range(config.epochs1)] + [(2, e) for e in range(config.epochs2)]
        self.phase = 1
        self.opt = self._optimizer(1)
        self.pos = (0, 0)  # (plan index, step within epoch)
        self.global_step = 0
        self._first_loss: float | None = None  # the run's first step loss, the divergence check's reference
        self.history: list[dict] = []
        self.feat_cache: dict[str, object] = {}
        # the G-buffer never changes, so each image's SH basis of n and r (2·81 floats per pixel at order 8) is
        # evaluated once and kept while the budget allows; images beyond it are evaluated per batch
        self.basis_cache: dict[int, object] = {}
        self.basis_budget = float(basis_cache_mb) * 2 ** 20
        self.basis_bytes = 0.0
        #: a :class:`~reflectmm_cli.finetune.tensorboard_log.TensorBoardLog` that mirrors the JSONL log, or None
        self.tensorboard = None

    # ------------------------------------------------------------------ optimiser / phases
    def _optimizer(self, phase):
        import torch

        cfg = self.cfg
        groups = [{"params": list(self.encoder.parameters()), "lr": cfg.lr1 if phase == 1 else cfg.lr2}]
        if phase == 2:
            groups.append({"params": self.params.parameters(), "lr": cfg.model_lr})
        return torch.optim.Adam(groups, betas=tuple(cfg.betas))

    def _enter_phase2(self):
        from .render import ModelParams

        if self.phase == 2:
            return
        self.params = ModelParams(self.model, self.device, trainable=self.cfg.trainable, n_components=self.M)
        self.phase = 2
        self.opt = self._optimizer(2)

    # ------------------------------------------------------------------ one batch
    def _bases(self, idx, gb, order: int) -> list:
        """One :class:`~reflectmm_cli.shading.EnvBasis` per image of the batch, from the cache when it has it."""
        from reflectmm_cli.shading import EnvBasis

        out = []
        for b, i in enumerate(int(j) for j in idx):
            basis = self.basis_cache.get(i)
            if basis is None:
                s0, s1 = int(gb.offsets[b]), int(gb.offsets[b + 1])
                basis = EnvBasis(gb.normal[s0:s1], gb.view[s0:s1], order, dtype=gb.normal.dtype,
                                 device=gb.normal.device)
                size = float(basis.Yn.numel() + basis.Yr.numel()) * basis.Yr.element_size()
                if self.basis_bytes + size <= self.basis_budget:
                    self.basis_cache[i] = basis
                    self.basis_bytes += size
            out.append(basis)
        return out

    def _forward(self, idx):
        import torch

        from . import losses as L
        from .render import batch_gbuffer, scatter_pixels

        t0 = time.perf_counter()
        b = self.shards.batch(idx)
        gb = batch_gbuffer(b, self.device)
        x = torch.as_tensor(b["images"], device=self.device).permute(0, 3, 1, 2).float() / 255.0
        t1 = time.perf_counter()
        beta, gamma, sh, pred = self._predict(idx, x, gb)
        cfg = self.cfg
        terms = {"photo": L.photometric(pred, gb.target, gb.skin, cfg.photometric),
                 "coef": L.coefficient_prior(beta, gamma), "light": L.light_monochrome(sh)}
        weights = {"photo": cfg.w_photo, "coef": cfg.w_coef, "light": cfg.w_light}
        if self.identity is not None and cfg.w_per > 0:
            lin = torch.as_tensor(b["linear"], device=self.device)
            img = scatter_pixels(pred, gb, background=lin)
            lms = self.shards_landmarks(idx)
            tf = self._target_features(idx, lin, lms)
            terms["per"] = L.perceptual(self.identity.features(img, lms), tf)
            weights["per"] = cfg.w_per
        if self.phase == 2:
            if cfg.model_reg == "l1":
                cur = dict(zip(("albedo_mean", "albedo_basis", "weights_mean", "weights_basis"),
                               self.params.effective()))
                terms["upd"] = L.model_update_l1(cur, self.initial)
                weights["upd"] = cfg.w_upd
            else:
                _, ab, _, wb = self.params.effective()
                nrm, orth = L.basis_norm_ortho(ab, self.initial["albedo_basis"], wb, self.initial["weights_basis"],
                                               self.params.sigma)
                terms["norm"], terms["ortho"] = nrm, orth
                weights["norm"], weights["ortho"] = cfg.w_upd, cfg.w_ortho
        total = sum(weights[k] * v for k, v in terms.items())
        return total, terms, t1 - t0

    def _predict(self, idx, x, gb):
        """(β, γ, SH lighting, per-pixel prediction (P, 3)) of the images ``idx``: ``x`` (B,3,S,S) in [0, 1],
        ``gb`` their G-buffer."""
        from reflectmm_cli.shading import sh_order

        from .render import lighting, shade_gbuffer

        beta, gamma, z = self.encoder(x)
        sh = lighting(self.light, gamma[:, :self.NL] if self.NL else gamma, z)
        order = sh_order(sh.shape[-1])
        # no NaN scans of the shading inputs: the step refuses a non-finite loss
        d, s, _, _ = shade_gbuffer(self.params, beta, sh, gb, bases=self._bases(idx, gb, order), check_finite=False)
        return beta, gamma, sh, d + s

    def preview(self, n: int):
        """(targets, reconstructions), each (n, S, S, 3) linear float32, of the first ``n`` validation images (the
        reconstruction over the target outside the face); None without a "val" split.  Eval mode, no gradient:
        training is not changed by it."""
        import torch

        from .render import batch_gbuffer, scatter_pixels

        idx = self.val_idx[:n]
        if len(idx) == 0:
            return None
        was_training = self.encoder.training
        self.encoder.eval()
        with torch.no_grad():
            b = self.shards.batch(idx)
            gb = batch_gbuffer(b, self.device)
            x = torch.as_tensor(b["images"], device=self.device).permute(0, 3, 1, 2).float() / 255.0
            pred = self._predict(idx, x, gb)[3]
            lin = torch.as_tensor(b["linear"], device=self.device)
            img = scatter_pixels(pred, gb, background=lin)
        self.encoder.train(was_training)
        return b["linear"], _np(img).astype(np.float32)

    def shards_landmarks(self, idx):
        lm = getattr(self.shards, "landmarks", None)
        if lm is None:
            return np.full((len(idx), 68, 2), np.nan)
        return lm[np.asarray(idx)]

    def _target_features(self, idx, lin, lms):
        import torch

        missing = [j for j, i in enumerate(idx) if str(self.shards.names[i]) not in self.feat_cache]
        if missing:
            with torch.no_grad():
                f = self.identity.features(lin[missing], lms[missing])
            for j, row in zip(missing, f):
                self.feat_cache[str(self.shards.names[idx[j]])] = row
        return torch.stack([self.feat_cache[str(self.shards.names[i])] for i in idx])

    def _validate(self):
        import torch

        if len(self.val_idx) == 0:
            return None
        self.encoder.eval()
        sums, n = {}, 0
        with torch.no_grad():
            for s0 in range(0, len(self.val_idx), self.B):
                idx = self.val_idx[s0:s0 + self.B]
                total, terms, _ = self._forward(idx)
                for k, v in {"total": total, **terms}.items():
                    sums[k] = sums.get(k, 0.0) + float(v) * len(idx)
                n += len(idx)
        self.encoder.train()
        return {k: v / n for k, v in sums.items()}

    # ------------------------------------------------------------------ checkpoints
    @property
    def phase1_encoder_path(self) -> Path:
        return self.workdir / "encoder_phase1.safetensors"

    def save_phase1_encoder(self) -> Path:
        """The encoder as phase 1 left it (model frozen): the "without finetuning" method of Table 2 is the initial
        model with exactly this encoder, so it needs no second phase-1 training. Written atomically before phase 2
        starts; a resumed phase 2 finds it in the work folder."""
        from .encoder import save_encoder

        return save_encoder(self.encoder, self.phase1_encoder_path,
                            {"config": self.cfg.to_dict(), "phase": 1, "steps": self.global_step,
                             "image_size": int(self.shards.size)})

    #: The config fields that decide what phase 1 computes (given the same data and initial model).
    PHASE1_FIELDS = ("arch", "width", "photometric", "w_photo", "w_per", "w_coef", "w_light", "epochs1", "lr1",
                     "batch_size", "betas", "seed", "n_reflectance", "n_light", "variant")

    def start_phase2_from(self, encoder_path) -> None:
        """Skip phase 1 by taking the encoder another run's phase 1 left (its ``*_encoder_phase1.safetensors``).

        Phase 1 is deterministic and phase 2 starts with a fresh optimiser, so the result equals a run that trains
        phase 1 itself (tested). Refused unless the file was written by phase 1 with the same phase-1 settings
        (:data:`PHASE1_FIELDS`), the same number of steps and the same image size."""
        import json

        from safetensors import safe_open
        from safetensors.torch import load_file

        path = Path(encoder_path)
        if self.cfg.epochs2 == 0:
            raise ReflectmmError("finetune: a phase-1 encoder was given but --epochs2 is 0 (nothing left to train)",
                                 path)
        try:
            with safe_open(str(path), "pt") as f:
                meta = json.loads((f.metadata() or {}).get("__meta__", "{}"))
            sd = load_file(str(path))
        except Exception as e:  # safetensors raises several types for a bad header
            raise ReflectmmError(f"not a readable encoder safetensors file ({type(e).__name__}: {e})", path) \
                from None
        if meta.get("phase") != 1:
            raise ReflectmmError("not a phase-1 encoder (finetune's *_encoder_phase1.safetensors)", path)
        mine, theirs = self.cfg.to_dict(), meta.get("config") or {}
        diff = [k for k in self.PHASE1_FIELDS if theirs.get(k) != mine.get(k)]
        steps = self.cfg.epochs1 * self.steps_per_epoch
        if diff or int(meta.get("steps", -1)) != steps or meta.get("image_size") not in (None, int(self.shards.size)):
            why = (f"phase-1 settings differ ({', '.join(diff)})" if diff else
                   f"{meta.get('steps')} steps, this run's phase 1 has {steps}" if int(meta.get("steps", -1)) != steps
                   else f"trained on {meta.get('image_size')}² images")
            raise ReflectmmError(f"this phase-1 encoder does not belong to this run: {why}", path)
        try:
            self.encoder.load_state_dict(sd)
        except RuntimeError as e:
            raise ReflectmmError(f"phase-1 encoder weights do not fit ({str(e).splitlines()[0]})", path) from None
        self.pos = (self.cfg.epochs1, 0)
        self.global_step = steps
        self._enter_phase2()
        self.save_phase1_encoder()

    @property
    def ckpt_path(self) -> Path:
        return self.workdir / CHECKPOINT_NAME

    @property
    def log_path(self) -> Path:
        """The log this run appends to (:data:`PARTIAL_LOG_NAME`), :data:`LOG_NAME` once it has finished."""
        return self.workdir / PARTIAL_LOG_NAME

    @property
    def finished_log_path(self) -> Path:
        return self.workdir / LOG_NAME

    def save_checkpoint(self):
        import torch
        from safetensors.torch import save

        from reflectmm_cli.artifacts import atomic_write_bytes, canonical_json

        tensors = {f"encoder/{k}": v.detach().cpu().contiguous() for k, v in self.encoder.state_dict().items()}
        if self.phase == 2:
            tensors.update({f"model/{k}": v.detach().cpu().contiguous()
                            for k, v in self.params.named_parameters().items()})
        sd = self.opt.state_dict()
        for pi, st in sd["state"].items():
            for k, v in st.items():
                tensors[f"opt/{pi}/{k}"] = (v if torch.is_tensor(v) else torch.tensor(v)).detach().cpu()
        meta = {"schema": CHECKPOINT_SCHEMA, "phase": self.phase, "plan_index": self.pos[0], "step": self.pos[1],
                "global_step": self.global_step, "config": self.cfg.to_dict(),
                "param_groups": [{k: v for k, v in g.items() if k != "params"} | {"params": g["params"]}
                                 for g in sd["param_groups"]],
                "data": [str(p) for p in self.shards.sources], "n_train": int(len(self.train_idx))}
        self.workdir.mkdir(parents=True, exist_ok=True)
        atomic_write_bytes(self.ckpt_path, save(tensors, metadata={"__meta__": canonical_json(meta)}))

    def load_checkpoint(self) -> bool:
        """Restore the last checkpoint if there is one (returns False if none). Refuses a different config/data."""
        import torch
        from safetensors import safe_open

        p = self.ckpt_path
        meta = check_checkpoint(p, self.cfg, len(self.train_idx))
        if meta is None:
            return False
        try:
            with safe_open(str(p), "pt") as f:
                tensors = {k: f.get_tensor(k) for k in f.keys()}
        except Exception as e:
            raise ReflectmmError(f"unreadable checkpoint ({type(e).__name__}: {e}); delete it to start over", p) \
                from None
        if meta["phase"] == 2:
            self._enter_phase2()
            for k, v in self.params.named_parameters().items():
                with torch.no_grad():
                    v.copy_(tensors[f"model/{k}"])
        enc = {k[len("encoder/"):]: v for k, v in tensors.items() if k.startswith("encoder/")}
        self.encoder.load_state_dict(enc)
        state = {}
        for k, v in tensors.items():
            if k.startswith("opt/"):
                _, pi, name = k.split("/", 2)
                state.setdefault(int(pi), {})[name] = v
        sd = self.opt.state_dict()
        sd["state"] = state
        sd["param_groups"] = [dict(g) for g in meta["param_groups"]]
        for g in sd["param_groups"]:
            if "betas" in g:
                g["betas"] = tuple(g["betas"])
        self.opt.load_state_dict(sd)
        self.pos = (int(meta["plan_index"]), int(meta["step"]))
        self.global_step = int(meta["global_step"])
        # the log keeps what happened up to the checkpoint: the interrupted run's, or (a checkpoint of a run that
        # finished, or of a reflectmm that wrote no partial log) the finished log, copied to go on from
        src = self.log_path if self.log_path.is_file() else self.finished_log_path
        if src.is_file():
            lines = [ln for ln in src.read_text().splitlines() if ln.strip()]
            kept = [ln for ln in lines if json.loads(ln)["global_step"] <= self.global_step]
            self.history = [json.loads(ln) for ln in kept]
            from reflectmm_cli.artifacts import atomic_write_text

            atomic_write_text(self.log_path, "".join(ln + "\n" for ln in kept))
        return True

    def _append_log(self, rec):
        self.history.append(rec)
        with open(self.log_path, "a") as f:
            f.write(json.dumps(rec, sort_keys=True) + "\n")
        if self.tensorboard is not None:
            self.tensorboard.record(rec)

    def _preview_to_tensorboard(self):
        """The first validation images, target | reconstruction, at the current global step."""
        from .tensorboard_log import N_PREVIEW, preview_grid

        pv = self.preview(N_PREVIEW)
        if pv is not None:
            self.tensorboard.image("val_reconstructions", preview_grid(*pv), self.global_step)
        self.tensorboard.flush()

    # ------------------------------------------------------------------ the loop
    def run(self, stop_after: int | None = None) -> bool:
        """Train from the current position to the end; ``stop_after`` global steps ends early (returns True)."""
        self._start_log()
        self.encoder.train()
        progress = _Progress.for_run(self.show_progress, self.steps_per_epoch, len(self.plan) * self.steps_per_epoch)
        while self.pos[0] < len(self.plan):
            pi, k0 = self.pos
            phase, ep = self.plan[pi]
            if phase == 2:
                self._enter_phase2()
            t_epoch = time.perf_counter()
            n_img = self._train_epoch(k0, progress, stop_after)
            if n_img is None:
                return True
            val = self._log_validation(phase, ep)
            progress.end_epoch()
            el = time.perf_counter() - t_epoch
            self.log(f"finetune: phase {phase} epoch {ep + 1}: {n_img / max(el, 1e-9):.1f} images/s"
                     + ("" if val is None else f", validation loss {val['total']:.4g} (photometric "
                                               f"{val['photo']:.4g})"))
            self._end_epoch_checkpoint()
            if stop_after is not None and self.global_step >= stop_after:
                return True
        self._finish_log()
        return False

    def _start_log(self) -> None:
        """A run from the very start begins a new JSONL log (a resumed one appends to the kept part). The
        previous run's finished log stays until this run finishes (:meth:`_finish_log`)."""
        self.workdir.mkdir(parents=True, exist_ok=True)
        if self.global_step == 0 and self.pos == (0, 0) and self.log_path.exists():
            self.log_path.unlink()

    def _finish_log(self) -> None:
        """Training has finished: this run's log replaces the previous run's (one rename)."""
        import os

        if not self.log_path.exists():  # no step at all (0 epochs): an empty log, as before
            self.log_path.write_text("")
        os.replace(self.log_path, self.finished_log_path)

    def _epoch_order(self, phase: int, ep: int) -> np.ndarray:
        """The training images of epoch ``ep`` of ``phase`` in their shuffled order (a function of seed, phase and
        epoch only, so a resumed run sees the same batches)."""
        rng = np.random.default_rng([self.cfg.seed, phase, ep])
        return self.train_idx[rng.permutation(len(self.train_idx))]

    def _batch(self, perm: np.ndarray, k: int) -> np.ndarray:
        """Step ``k``'s images of the epoch order ``perm``; a last batch of one image gets the epoch's first too
        (BatchNorm needs 2)."""
        idx = perm[k * self.B:(k + 1) * self.B]
        if len(idx) < 2:
            idx = np.concatenate([idx, perm[:1]])
        return idx

    def _train_epoch(self, k0: int, progress: "_Progress", stop_after: int | None) -> int | None:
        """Steps ``k0``.. of the epoch at ``self.pos``: one optimiser step, its log record, progress and the
        periodic checkpoint each. Returns the number of images trained on, or None when ``stop_after`` ended the
        run inside the epoch."""
        pi = self.pos[0]
        phase, ep = self.plan[pi]
        perm = self._epoch_order(phase, ep)
        n_img = 0
        for k in range(k0, self.steps_per_epoch):
            idx = self._batch(perm, k)
            ts = time.perf_counter()
            total, terms = self._train_step(idx, phase, ep)
            self.pos = (pi, k + 1)
            n_img += len(idx)
            rec = self._log_step(phase, ep, k, total, terms)
            ips = len(idx) / max(time.perf_counter() - ts, 1e-9)
            if self.tensorboard is not None:
                self.tensorboard.scalar("images_per_s", ips, self.global_step)
            progress.step(phase, ep, k, self.global_step, rec, terms, ips)
            last = k + 1 == self.steps_per_epoch
            if not last:
                self._checkpoint_step()
                if stop_after is not None and self.global_step >= stop_after:
                    return None
        return n_img

    def _train_step(self, idx, phase: int, ep: int):
        """One Adam step on the images ``idx``: (total loss, loss terms); refuses a non-finite loss."""
        import torch

        total, terms, _ = self._forward(idx)
        if not torch.isfinite(total):
            raise ReflectmmError(f"finetune: the loss became {float(total)} at step {self.global_step} "
                                 f"(phase {phase}, epoch {ep}); lower the learning rate")
        first = self._first_loss
        if first is None:
            self._first_loss = first = max(float(total.detach()), 1e-12)
        elif float(total.detach()) > DIVERGED_FACTOR * first:
            raise ReflectmmError(f"finetune: the loss grew from {first:.3g} to {float(total):.3g} at step "
                                 f"{self.global_step} (phase {phase}, epoch {ep}): training diverged; lower the "
                                 "learning rate")
        self.opt.zero_grad(set_to_none=True)
        total.backward()
        self.opt.step()
        self.global_step += 1
        return total, terms

    def _log_step(self, phase: int, ep: int, k: int, total, terms: dict) -> dict:
        """The step record (loss and every term) appended to the history, the JSONL log and TensorBoard."""
        rec = {"type": "step", "phase": phase, "epoch": ep, "step": k, "global_step": self.global_step,
               "loss": float(total.detach()), **{k_: float(v.detach()) for k_, v in terms.items()}}
        self._append_log(rec)
        return rec

    def _checkpoint_step(self) -> None:
        """The periodic checkpoint inside an epoch: every ``checkpoint_every`` global steps."""
        if self.global_step % self.cfg.checkpoint_every == 0:
            self.save_checkpoint()

    def _log_validation(self, phase: int, ep: int) -> dict | None:
        """The epoch-end validation: its record (``val_*`` losses; none without a "val" split) appended to the
        logs, and the reconstructions to TensorBoard. Returns the validation losses or None."""
        val = self._validate()
        rec = {"type": "val", "phase": phase, "epoch": ep, "global_step": self.global_step,
               **({} if val is None else {f"val_{k_}": v for k_, v in val.items()})}
        self._append_log(rec)
        if self.tensorboard is not None:
            self._preview_to_tensorboard()
        return val

    def _end_epoch_checkpoint(self) -> None:
        """The epoch is done: move to the next one, checkpoint, and keep phase 1's encoder where phase 2 starts."""
        pi = self.pos[0]
        phase = self.plan[pi][0]
        self.pos = (pi + 1, 0)
        self.save_checkpoint()
        if phase == 1 and self.pos[0] < len(self.plan) and self.plan[self.pos[0]][0] == 2:
            self.save_phase1_encoder()


class _Progress:
    """Progress lines of the training loop on stderr: a terminal gets one line redrawn in place; a log file or a
    captured stderr gets plain lines, one per ~10 % of an epoch, and never a carriage return."""

    def __init__(self, show: bool, tty: bool, steps_per_epoch: int, total_steps: int):
        self.show, self.tty = show, tty
        self.steps_per_epoch, self.total_steps = steps_per_epoch, total_steps
        self.every = max(1, steps_per_epoch // 10)

    @classmethod
    def for_run(cls, wanted: bool, steps_per_epoch: int, total_steps: int) -> "_Progress":
        """Shown when ``wanted`` and the reflectmm logger shows INFO; redrawn when stderr is a terminal."""
        import logging
        import sys

        from reflectmm_cli.progress import log as plog

        show = wanted and plog.getEffectiveLevel() <= logging.INFO
        tty = show and bool(getattr(sys.stderr, "isatty", lambda: False)())
        return cls(show, tty, steps_per_epoch, total_steps)

    def step(self, phase: int, ep: int, k: int, global_step: int, rec: dict, terms, ips: float) -> None:
        """The line of step ``k`` of epoch ``ep`` (every step on a terminal)."""
        import sys

        if not (self.show and (self.tty or (k + 1) % self.every == 0 or k + 1 == self.steps_per_epoch)):
            return
        sys.stderr.write(("\r" if self.tty else "")
                         + f"finetune phase {phase} epoch {ep + 1} step {k + 1}/{self.steps_per_epoch} "
                         f"[{global_step}/{self.total_steps}] loss {rec['loss']:.4g} "
                         + " ".join(f"{k_} {rec[k_]:.3g}" for k_ in terms)
                         + f" {ips:.1f} img/s" + (" " if self.tty else "\n"))
        sys.stderr.flush()

    def end_epoch(self) -> None:
        """A terminal's redrawn line is ended."""
        import sys

        if self.tty:
            sys.stderr.write("\n")


def _settings_diff(old: dict, new: dict) -> list[str]:
    """The names of the settings in which two :meth:`FinetuneConfig.to_dict` differ, the solver first: a run of
    ``--solver ls`` records its model solve (``extra["model_solve"]``, its ``ls_*`` options) and trains with
    ``model_lr`` 0, so a switch of solver is named as such, not as the ``model_lr`` it implies."""
    old_s = (old.get("extra") or {}).get("model_solve")
    new_s = (new.get("extra") or {}).get("model_solve")
    diff = sorted(k for k in set(old) | set(new) if old.get(k) != new.get(k) and k != "extra")
    if (old_s is None) != (new_s is None):
        return ["solver"] + [k for k in diff if k != "model_lr"]
    old_s, new_s = old_s or {}, new_s or {}
    diff += sorted(f"ls_{k}" for k in set(old_s) | set(new_s) if old_s.get(k) != new_s.get(k))
    return diff or ["extra"]


def check_checkpoint(path: str | Path, config: FinetuneConfig, n_train: int) -> dict | None:
    """The meta of the checkpoint ``path`` if it was made with ``config`` on ``n_train`` training images; None when
    there is no checkpoint. Otherwise a one-line error naming the settings that differ: ``--resume`` checks it
    before the least-squares model solve (``--solver ls``), which runs before training, not only at training."""
    from safetensors import safe_open

    p = Path(path)
    if not p.is_file():
        return None
    try:
        with safe_open(str(p), "pt") as f:
            meta = json.loads(f.metadata()["__meta__"])
    except Exception as e:
        raise ReflectmmError(f"unreadable checkpoint ({type(e).__name__}: {e}); delete it to start over", p) \
            from None
    if meta.get("schema") != CHECKPOINT_SCHEMA:
        raise ReflectmmError(f"not a finetune checkpoint (schema {meta.get('schema')!r})", p)
    mine = config.to_dict()
    if meta["config"] != mine:
        diff = _settings_diff(meta["config"], mine)
        raise ReflectmmError(f"checkpoint was made with other settings ({', '.join(diff)}); use the same options or "
                             "delete it", p)
    if int(meta.get("n_train", -1)) != int(n_train):
        raise ReflectmmError("checkpoint was made with other data (train split size differs)", p)
    return meta


def finetune(shards: ShardSet, model, light, config: FinetuneConfig, workdir: str | Path, *, device="cpu",
             identity=None, init_weights=None, resume: bool = False, stop_after: int | None = None,
             phase1_encoder=None,
             log: Callable[[str], None] | None = None, progress: bool = True,
             threads: int | None = None, basis_cache_mb: float = BASIS_CACHE_MB,
             tensorboard: str | Path | None = None) -> FinetuneResult:
    """Library entry of ``finetune``.

    Args:
        shards: the data (:func:`reflectmm_cli.finetune.shards.load_shards`); "train" split trains, "val" validates.
        model: initial :class:`~reflectmm_cli.model.pca.ReflectanceModel` with its per-vertex part.
        light: :class:`~reflectmm_cli.shading.LightModel` (order = the shards' ``sh_order``).
        config: :class:`FinetuneConfig`.
        workdir: folder of the checkpoint and the JSONL log.
        identity: an :class:`~reflectmm_cli.finetune.identity.IdentityNet` (L_per on) or None (L_per off).
        init_weights: optional safetensors ImageNet trunk (torchvision key names).
        resume: continue from ``workdir``'s checkpoint (an error if it was made with other settings);
            without it an existing checkpoint is ignored and overwritten.
        stop_after: stop after this many global steps (tests; simulates an interruption).
        phase1_encoder: start at phase 2 from another run's phase-1 encoder (:meth:`Trainer.start_phase2_from`):
            the control run of Table 2 shares phase 1 with the finetuned run instead of training it twice.
        basis_cache_mb: memory for the per-image SH bases kept across steps (0: evaluate them every step; the
            result is the same either way).
        threads: torch CPU threads for the run (None: unchanged). Small images on a busy machine run fastest
            with 1 (thread spin-waiting in tiny BatchNorm/conv calls costs more than it gains).
        tensorboard: folder for TensorBoard events mirroring the JSONL log, plus images/s and validation
            reconstructions (:mod:`reflectmm_cli.finetune.tensorboard_log`; needs the ``tensorboard`` package, a
            one-line error before anything is done without it). None: nothing is written and nothing imported.
    Returns:
        :class:`FinetuneResult`.
    """
    from reflectmm_cli.threads import torch_threads

    if tensorboard is not None:
        from .tensorboard_log import TensorBoardLog, require_tensorboard

        require_tensorboard()
    with torch_threads(threads):
        tr = Trainer(shards, model, light, config, workdir, device=device, identity=identity,
                     init_weights=init_weights, log=log, progress=progress, basis_cache_mb=basis_cache_mb)
        resumed = bool(resume) and tr.load_checkpoint()
        if resumed:
            (log or (lambda s: None))(f"finetune: resumed at global step {tr.global_step}")
        elif phase1_encoder is not None:
            tr.start_phase2_from(phase1_encoder)
            (log or (lambda s: None))(f"finetune: phase 1 taken from {phase1_encoder}")
        if tensorboard is not None:
            tr.tensorboard = TensorBoardLog(tensorboard, purge_step=tr.global_step + 1)
        try:
            stopped = tr.run(stop_after)
        finally:
            if tr.tensorboard is not None:
                tr.tensorboard.close()
    tr.encoder.eval()
    return FinetuneResult(params=tr.params, encoder=tr.encoder, initial=tr.initial_np, history=tr.history,
                          config=config, perceptual="off" if identity is None or config.w_per == 0 else
                          f"{identity.name} ({identity.path.name})", z0=tr.z0, steps=tr.global_step,
                          stopped_early=stopped, n_train=int(len(tr.train_idx)), n_val=int(len(tr.val_idx)),
                          phase1_encoder=tr.phase1_encoder_path if tr.phase1_encoder_path.is_file() else None,
                          image_size=int(shards.size),
                          stats={"basis_cache_images": len(tr.basis_cache),
                                 "basis_cache_mib": round(tr.basis_bytes / 2 ** 20, 3)})
