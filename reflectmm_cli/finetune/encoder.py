"""The reconstruction encoder: a ResNet-18/34/50 in plain torch predicting β (N_R), γ (N_L) and z (3).

Key names follow torchvision's ResNet (``conv1``, ``bn1``, ``layer1.0.conv1``, …, ``fc``), so an ImageNet trunk
converted to safetensors (e.g. ``safetensors.torch.save_file(torchvision_model.state_dict(), path)``) loads with
``--init-weights``; ``fc.*`` is always replaced by the zero-initialised head.

Input: (B, 3, S, S) float images as stored on disk (``uint8 / 255``, not linearised), normalised inside the network
with the ImageNet mean (0.485, 0.456, 0.406) and std (0.229, 0.224, 0.225) — the statistics the pretrained trunks
expect. Output head: Linear(features → N_R + N_L + 3), weights and bias zero at the start, so the first prediction
is β = 0, γ = 0 (the mean skin and the mean lighting shape) and z = z₀ (``z = softplus(o + softplus⁻¹(z₀))``).
"""
from __future__ import annotations

import math
from pathlib import Path

from reflectmm_cli.errors import ReflectmmError

__all__ = ["Encoder", "build_encoder", "load_trunk", "save_encoder", "load_encoder", "check_encoder_model",
           "encoder_model_sha", "read_encoder_meta", "budget_differences", "BUDGET_CONFIG_KEYS", "ENCODER_KIND"]

ENCODER_KIND = "finetune-encoder"
IMAGENET_MEAN = (0.485, 0.456, 0.406)
IMAGENET_STD = (0.229, 0.224, 0.225)
_LAYERS = {"resnet18": ("basic", (2, 2, 2, 2)), "resnet34": ("basic", (3, 4, 6, 3)),
           "resnet50": ("bottleneck", (3, 4, 6, 3))}


def _nn():
    import torch.nn as nn

    class BasicBlock(nn.Module):
        expansion = 1

        def __init__(self, cin, planes, stride=1, downsample=None):
            super().__init__()
            self.conv1 = nn.Conv2d(cin, planes, 3, stride, 1, bias=False)
            self.bn1 = nn.BatchNorm2d(planes)
            self.relu = nn.ReLU(inplace=True)
            self.conv2 = nn.Conv2d(planes, planes, 3, 1, 1, bias=False)
            self.bn2 = nn.BatchNorm2d(planes)
            self.downsample = downsample

        def forward(self, x):
            idt = x if self.downsample is None else self.downsample(x)
            out = self.relu(self.bn1(self.conv1(x)))
            return self.relu(self.bn2(self.conv2(out)) + idt)

    class Bottleneck(nn.Module):
        expansion = 4

        def __init__(self, cin, planes, stride=1, downsample=None):
            super().__init__()
            self.conv1 = nn.Conv2d(cin, planes, 1, bias=False)
            self.bn1 = nn.BatchNorm2d(planes)
            self.conv2 = nn.Conv2d(planes, planes, 3, stride, 1, bias=False)
            self.bn2 = nn.BatchNorm2d(planes)
            self.conv3 = nn.Conv2d(planes, planes * 4, 1, bias=False)
            self.bn3 = nn.BatchNorm2d(planes * 4)
            self.relu = nn.ReLU(inplace=True)
            self.downsample = downsample

        def forward(self, x):
            idt = x if self.downsample is None else self.downsample(x)
            out = self.relu(self.bn1(self.conv1(x)))
            out = self.relu(self.bn2(self.conv2(out)))
            return self.relu(self.bn3(self.conv3(out)) + idt)

    return nn, BasicBlock, Bottleneck


def build_encoder(arch: str, n_reflectance: int, n_light: int, width: int = 64, z0: float = 1.0):
    """A fresh :class:`Encoder` (deterministic for the current torch seed)."""
    return Encoder(arch, n_reflectance, n_light, width, z0)


def Encoder(arch: str, n_reflectance: int, n_light: int, width: int = 64, z0: float = 1.0):  # noqa: N802
    """Construct the encoder module (see the module docstring). ``forward(x) -> (β (B,N_R), γ (B,N_L), z (B,3))``."""
    import torch
    import torch.nn.functional as F

    nn, BasicBlock, Bottleneck = _nn()
    if arch not in _LAYERS:
        raise ReflectmmError(f"encoder: unknown arch {arch!r} (expected one of {', '.join(_LAYERS)})")
    kind, counts = _LAYERS[arch]
    block = BasicBlock if kind == "basic" else Bottleneck
    if z0 <= 0 or not math.isfinite(z0):
        raise ReflectmmError(f"encoder: z0 must be positive, got {z0}")

    class _Encoder(nn.Module):
        def __init__(self):
            super().__init__()
            self.arch, self.width, self.n_reflectance, self.n_light, self.z0 = arch, width, n_reflectance, n_light, z0
            self.conv1 = nn.Conv2d(3, width, 7, 2, 3, bias=False)
            self.bn1 = nn.BatchNorm2d(width)
            self.relu = nn.ReLU(inplace=True)
            self.maxpool = nn.MaxPool2d(3, 2, 1)
            cin = width
            for i, n in enumerate(counts):
                planes = width * 2 ** i
                stride = 1 if i == 0 else 2
                down = None
                if stride != 1 or cin != planes * block.expansion:
                    down = nn.Sequential(nn.Conv2d(cin, planes * block.expansion, 1, stride, bias=False),
                                         nn.BatchNorm2d(planes * block.expansion))
                blocks = [block(cin, planes, stride, down)]
                cin = planes * block.expansion
                blocks += [block(cin, planes) for _ in range(1, n)]
                setattr(self, f"layer{i + 1}", nn.Sequential(*blocks))
            self.avgpool = nn.AdaptiveAvgPool2d(1)
            self.fc = nn.Linear(cin, n_reflectance + n_light + 3)
            for m in self.modules():  # torchvision's initialisation
                if isinstance(m, nn.Conv2d):
                    nn.init.kaiming_normal_(m.weight, mode="fan_out", nonlinearity="relu")
                elif isinstance(m, nn.BatchNorm2d):
                    nn.init.ones_(m.weight)
                    nn.init.zeros_(m.bias)
            nn.init.zeros_(self.fc.weight)
            nn.init.zeros_(self.fc.bias)
            self.register_buffer("mean", torch.tensor(IMAGENET_MEAN).view(1, 3, 1, 1), persistent=False)
            self.register_buffer("std", torch.tensor(IMAGENET_STD).view(1, 3, 1, 1), persistent=False)
            self.z_offset = math.log(math.expm1(z0))  # softplus⁻¹(z0)

        def features(self, x):
            x = (x - self.mean.to(x.dtype)) / self.std.to(x.dtype)
            x = self.maxpool(self.relu(self.bn1(self.conv1(x))))
            x = self.layer4(self.layer3(self.layer2(self.layer1(x))))
            return torch.flatten(self.avgpool(x), 1)

        def forward(self, x):
            o = self.fc(self.features(x))
            R, L = self.n_reflectance, self.n_light
            return o[:, :R], o[:, R:R + L], F.softplus(o[:, R + L:] + self.z_offset)

        def describe(self) -> dict:
            return {"arch": self.arch, "width": self.width, "n_reflectance": self.n_reflectance,
                    "n_light": self.n_light, "z0": self.z0, "input": "uint8/255 as stored, ImageNet mean/std inside",
                    "keys": "torchvision ResNet names; fc = zero-initialised head"}

    return _Encoder()


def load_trunk(encoder, path: str | Path) -> dict:
    """Load a pretrained trunk (torchvision key names, safetensors) into ``encoder``; ``fc.*`` is ignored.

    Raises one line naming the file on missing keys, unexpected keys or mismatched shapes. Returns counts.
    """
    from safetensors import SafetensorError
    from safetensors.torch import load_file

    path = Path(path)
    if not path.is_file():
        raise ReflectmmError("init weights not found", path)
    try:
        sd = load_file(str(path))
    except (SafetensorError, OSError, ValueError) as e:
        raise ReflectmmError(f"not a readable safetensors file ({e})", path) from None
    sd = {k: v for k, v in sd.items() if not k.startswith("fc.") and not k.endswith("num_batches_tracked")}
    own = {k: v for k, v in encoder.state_dict().items()
           if not k.startswith("fc.") and not k.endswith("num_batches_tracked")}
    missing = sorted(set(own) - set(sd))
    unexpected = sorted(set(sd) - set(own))
    if missing or unexpected:
        raise ReflectmmError(f"init weights do not match {encoder.arch} (width {encoder.width}): "
                             f"{len(missing)} missing keys (e.g. {missing[:2]}), {len(unexpected)} unexpected "
                             f"(e.g. {unexpected[:2]})", path)
    bad = [(k, tuple(sd[k].shape), tuple(v.shape)) for k, v in own.items() if tuple(sd[k].shape) != tuple(v.shape)]
    if bad:
        k, a, b = bad[0]
        raise ReflectmmError(f"init weights: {len(bad)} tensors of the wrong shape (e.g. {k}: {a}, expected {b})",
                             path)
    encoder.load_state_dict({**encoder.state_dict(), **{k: sd[k].to(own[k].dtype) for k in own}})
    return {"loaded": len(own)}


def save_encoder(encoder, path: str | Path, meta: dict) -> Path:
    """Encoder weights as safetensors (atomic) with the JSON meta (schema, arch, sizes, provenance) in the header."""
    import json

    from safetensors.torch import save

    from reflectmm_cli.artifacts import atomic_write_bytes, canonical_json

    m = {"schema": f"reflectmm.{ENCODER_KIND}/1", **encoder.describe(), **meta}
    sd = {k: v.detach().cpu().contiguous() for k, v in encoder.state_dict().items()}
    data = save(sd, metadata={"__meta__": canonical_json(json.loads(canonical_json(m)))})
    return atomic_write_bytes(path, data)


def encoder_model_sha(meta: dict) -> str | None:
    """sha256 of the reflectance model an encoder was trained with (its meta's ``model`` input), if recorded."""
    for ref in meta.get("inputs") or []:
        if isinstance(ref, dict) and ref.get("role") == "model" and isinstance(ref.get("sha256"), str):
            return ref["sha256"]
    return None


def check_encoder_model(meta: dict, encoder_path, model_path, *, allow_other_model: bool = False,
                        warn=None) -> None:
    """Refuse an encoder used with a model it was not trained for.

    Accepted: the model the encoder's meta records (by sha256), or a ``finetune`` output made from that model
    (its own meta's ``model`` input has that sha256 — the finetuned model of a run whose encoder this is, or of a
    control run). Anything else is a one-line error naming both files, or with ``allow_other_model`` a warning
    (``warn``, default the log). An encoder that records no model is not checked.
    """
    from reflectmm_cli.artifacts import read_meta, sha256_file

    trained = encoder_model_sha(meta)
    if trained is None:
        return
    given = sha256_file(model_path)
    if given == trained:
        return
    try:
        mmeta = read_meta(model_path)
    except ReflectmmError:
        mmeta = {}
    parent = encoder_model_sha(mmeta) if (mmeta.get("producer") or {}).get("stage") == "finetune" else None
    if parent == trained:
        return
    msg = (f"the encoder {encoder_path} was trained for another reflectance model than {model_path} (sha256 "
           f"{trained[:12]}…, not {given[:12]}…, nor a finetune output of it)")
    if not allow_other_model:
        raise ReflectmmError(msg + "; pass --allow-other-model to use it anyway")
    if warn is None:
        from reflectmm_cli.progress import log

        warn = log.warning
    warn("warning: " + msg + " (--allow-other-model)")


#: What an encoder's training budget is made of (issue 21's "same data, seed, schedule"): the settings of its
#: ``config`` that train the encoder (not those of the model update), its number of optimiser steps and image size.
BUDGET_CONFIG_KEYS = ("arch", "width", "batch_size", "epochs1", "epochs2", "lr1", "lr2", "betas", "seed",
                      "photometric", "w_photo", "w_per", "w_coef", "w_light")


def read_encoder_meta(path: str | Path) -> dict:
    """The JSON meta of :func:`save_encoder`'s file, without loading the weights; one-line errors for a missing,
    unreadable or foreign file."""
    import json

    from safetensors import safe_open

    path = Path(path)
    if not path.is_file():
        raise ReflectmmError("encoder file not found", path)
    try:
        with safe_open(str(path), "pt") as f:
            meta = json.loads((f.metadata() or {}).get("__meta__", "{}"))
    except Exception as e:  # safetensors raises several types for a bad header
        raise ReflectmmError(f"not a readable encoder safetensors file ({type(e).__name__}: {e})", path) from None
    if meta.get("schema") != f"reflectmm.{ENCODER_KIND}/1":
        raise ReflectmmError(f"not a reflectmm encoder (schema {meta.get('schema')!r})", path)
    return meta


def budget_differences(meta_a: dict, meta_b: dict) -> list[str]:
    """How the training budgets of two encoders differ (``"epochs1 8 against 6"``, ``"training data"``), from
    their metas: :data:`BUDGET_CONFIG_KEYS`, the optimiser steps, the image size and the sha256 of the ``data``
    inputs (where both record them). Empty when the two encoders had the same budget, so that their gain measures
    what else differs (the model)."""
    out = []
    ca, cb = meta_a.get("config") or {}, meta_b.get("config") or {}
    for k in BUDGET_CONFIG_KEYS:
        if k in ca and k in cb and ca[k] != cb[k]:
            out.append(f"{k} {ca[k]} against {cb[k]}")
    for k in ("steps", "image_size"):
        if k in meta_a and k in meta_b and meta_a[k] != meta_b[k]:
            out.append(f"{k} {meta_a[k]} against {meta_b[k]}")

    def data(m):
        refs = [r for r in m.get("inputs") or [] if isinstance(r, dict) and r.get("role") == "data"]
        return sorted(r.get("sha256") for r in refs) if refs else None

    da, db = data(meta_a), data(meta_b)
    if da is not None and db is not None and da != db:
        out.append("training data")
    return out


def load_encoder(path: str | Path, device="cpu", *, model=None, allow_other_model: bool = False, warn=None):
    """(encoder in eval mode, meta) from :func:`save_encoder`'s file; with ``model`` (a path), the pairing is
    checked first (:func:`check_encoder_model`)."""
    from safetensors.torch import load_file

    path = Path(path)
    meta = read_encoder_meta(path)
    try:
        sd = load_file(str(path))
    except Exception as e:  # safetensors raises several types for a bad header
        raise ReflectmmError(f"not a readable encoder safetensors file ({type(e).__name__}: {e})", path) from None
    bad = next((k for k, v in sorted(sd.items()) if v.is_floating_point() and not bool(v.isfinite().all())), None)
    if bad is not None:  # it would surface as a NaN albedo far downstream, naming neither file nor tensor
        raise ReflectmmError(f"encoder weight '{bad}' contains NaN or inf", path)
    if model is not None:
        check_encoder_model(meta, path, model, allow_other_model=allow_other_model, warn=warn)
    try:
        enc = Encoder(meta["arch"], int(meta["n_reflectance"]), int(meta["n_light"]), int(meta["width"]),
                      float(meta["z0"]))
    except (KeyError, TypeError, ValueError) as e:
        raise ReflectmmError(f"encoder meta is incomplete or corrupt ({type(e).__name__}: {e})", path) from None
    try:
        enc.load_state_dict(sd)
    except RuntimeError as e:
        raise ReflectmmError(f"encoder weights do not match their meta ({str(e).splitlines()[0]})", path) from None
    return enc.to(device).eval(), meta
