"""Every weight, epoch count, learning rate, batch size, seed and architecture choice of finetuning, declared once.

Defaults are the paper's (CVPR 2023 §3.3, §4.1, supp. A.2). ``FinetuneConfig.released()`` returns the variant of the
authors' released training code (yxuhan/ReflectanceMM); the differences are listed in docs/finetune.md.
"""
from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from typing import Any, Mapping

from reflectmm_cli.errors import ReflectmmError
from reflectmm_cli.params import SEED_RANGE

__all__ = ["FinetuneConfig", "ARCHS", "PHOTOMETRIC", "MODEL_REG", "TRAINABLE", "VARIANTS", "RELEASED"]

ARCHS = ("resnet18", "resnet34", "resnet50")
PHOTOMETRIC = ("l1", "l2norm")  # L1 over RGB (paper) | per-pixel Euclidean norm over RGB (released code)
MODEL_REG = ("l1", "norm_ortho")  # L1 to the initial model (paper) | basis norm + orthogonality (released code)
TRAINABLE = ("all", "albedo")  # mean + bases of diffuse and lobe weights | see docs (released code)
VARIANTS = ("paper", "released")


#: The released training code's values where they differ from the paper's (:meth:`FinetuneConfig.released`).
RELEASED = dict(photometric="l2norm", w_photo=1.92, trainable="albedo", epochs2=5, lr2=1e-4, model_lr=1e-5,
                model_reg="norm_ortho", w_upd=10.0, w_ortho=10.0, variant="released")


def _f(default, help: str, *, range=None, choices=None, option=None):
    """A config field with its declaration in the metadata (help, range, choices, command-line option).  The
    stage's parameter declaration (reflectmm_cli/stages/finetune.py) is generated from these fields."""
    return field(default=default, metadata={"help": help, "range": range, "choices": choices, "option": option})


@dataclass(frozen=True)
class FinetuneConfig:
    """Finetuning hyper-parameters (all configurable; each loss term is logged separately).

    Loss weights: ``w_photo`` photometric term (paper L1 weight 2), ``w_per`` identity-feature term (0.1),
    ``w_coef`` coefficient prior (0.001), ``w_upd`` model-update term (10, phase 2 only), ``w_light``
    monochromatic-lighting term (10). ``w_ortho`` is used only with ``model_reg="norm_ortho"``.
    Schedule: phase 1 trains the encoder (``epochs1`` at ``lr1``); phase 2 trains encoder and model
    (``epochs2``; encoder at ``lr2``, model mean and bases at ``model_lr``). Adam with ``betas``.
    """

    # architecture
    arch: str = _f("resnet50", "Encoder architecture.", choices=ARCHS)
    width: int = _f(64, "Channels of the first ResNet stage (64 = the standard networks).", range=(1, 1024))
    # losses
    photometric: str = _f("l1", "Photometric term: L1 over RGB (paper) or the per-pixel RGB norm (released code).",
                          choices=PHOTOMETRIC)
    w_photo: float = _f(2.0, "Photometric weight.")
    w_per: float = _f(0.1, "Perceptual (identity-feature) weight; the term is off without --identity-weights.")
    w_coef: float = _f(0.001, "Coefficient-prior weight.")
    w_upd: float = _f(10.0, "Model-update weight (phase 2).")
    w_light: float = _f(10.0, "Monochrome-light weight.")
    w_ortho: float = _f(10.0, "Diffuse-orthogonality weight (model_reg norm_ortho only).")
    model_reg: str = _f("l1", "Model regulariser: L1 to the initial model (paper) or basis norm + orthogonality "
                        "(released code).", choices=MODEL_REG)
    trainable: str = _f("all", "Trainable model parts in phase 2: all means and bases, or the diffuse parts and "
                        "the specular albedo only (released code).", choices=TRAINABLE)
    # schedule
    epochs1: int = _f(20, "Phase-1 epochs (encoder only, the model frozen).", range=(0, None))
    lr1: float = _f(1e-4, "Phase-1 learning rate.")
    epochs2: int = _f(2, "Phase-2 epochs (encoder + model); 0 = phase 1 only (no SGD update of the model; "
                         "--solver ls solves it before training).",
                      range=(0, None))
    lr2: float = _f(1e-5, "Phase-2 encoder learning rate.")
    model_lr: float = _f(1e-5, "Phase-2 model learning rate.")
    batch_size: int = _f(8, "Images per step.", range=(1, None))
    betas: tuple[float, float] = _f((0.9, 0.999), "Adam betas (two numbers).", range=(0.0, 1.0))
    seed: int = _f(0, "Seed (encoder initialisation and batch order).", range=SEED_RANGE)
    # bookkeeping
    checkpoint_every: int = _f(500, "Steps between checkpoints (also one at each epoch end).", range=(1, None))
    n_reflectance: int | None = _f(None, "N_R, reflectance coefficients predicted (default: all of the model).",
                                   range=(1, None), option="--components")
    n_light: int | None = _f(None, "N_L, light coefficients predicted (default: all of the light model).",
                             range=(1, None), option="--light-components")
    variant: str = _f("paper", "Defaults of the paper or of the released training code (docs/finetune.md).",
                      choices=VARIANTS)
    extra: Mapping[str, Any] = field(default_factory=dict)

    def __post_init__(self):
        if self.arch not in ARCHS:
            raise ReflectmmError(f"finetune: --arch must be one of {', '.join(ARCHS)}, got {self.arch!r}")
        if self.photometric not in PHOTOMETRIC:
            raise ReflectmmError(f"finetune: photometric loss must be one of {PHOTOMETRIC}, got {self.photometric!r}")
        if self.model_reg not in MODEL_REG:
            raise ReflectmmError(f"finetune: model regulariser must be one of {MODEL_REG}, got {self.model_reg!r}")
        if self.trainable not in TRAINABLE:
            raise ReflectmmError(f"finetune: trainable must be one of {TRAINABLE}, got {self.trainable!r}")
        for k in ("width", "batch_size", "checkpoint_every"):
            if int(getattr(self, k)) < 1:
                raise ReflectmmError(f"finetune: {k} must be ≥ 1, got {getattr(self, k)}")
        for k in ("epochs1", "epochs2"):
            if int(getattr(self, k)) < 0:
                raise ReflectmmError(f"finetune: {k} must be ≥ 0, got {getattr(self, k)}")
        for k in ("w_photo", "w_per", "w_coef", "w_upd", "w_light", "w_ortho", "lr1", "lr2", "model_lr"):
            v = float(getattr(self, k))
            if not v >= 0 or v != v or v == float("inf"):
                raise ReflectmmError(f"finetune: {k} must be finite and ≥ 0, got {v}")

    @classmethod
    def released(cls, **overrides) -> "FinetuneConfig":
        """The released code's settings (yxuhan/ReflectanceMM train.sh / options): per-pixel RGB-norm photometric
        term at 1.92, only the diffuse and specular-albedo parts trainable, 5 joint epochs with the encoder at
        lr 1e-4 and the model at 1e-5, basis-norm + diffuse-orthogonality terms (10 each) instead of the L1 to the
        initial model, batch 16 in phase 1 and 8 in phase 2 (one batch size here: 8)."""
        base = dict(RELEASED)
        base.update(overrides)
        return cls(**base)

    def replace(self, **changes) -> "FinetuneConfig":
        return dataclasses.replace(self, **changes)

    def to_dict(self) -> dict[str, Any]:
        d = dataclasses.asdict(self)
        d["betas"] = list(self.betas)
        d["extra"] = dict(self.extra)
        return d

    @classmethod
    def from_dict(cls, d: Mapping[str, Any]) -> "FinetuneConfig":
        names = {f.name for f in dataclasses.fields(cls)}
        unknown = sorted(set(d) - names)
        if unknown:
            raise ReflectmmError(f"finetune: unknown config keys {unknown}")
        d = dict(d)
        if "betas" in d:
            d["betas"] = tuple(d["betas"])
        return cls(**d)
