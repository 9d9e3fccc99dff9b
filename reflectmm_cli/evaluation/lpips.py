"""LPIPS (Zhang et al. 2018) weights from a safetensors file, and the distance reductions the evaluation uses.

Every verb loads the weights with :func:`reflectmm_cli.evaluation.metrics.load_lpips` (re-exported here), which
reads this safetensors layout and, recognised by content, a torch state dict of the same keys.

The network itself (AlexNet / VGG16 trunk + the five learned 1×1 "lin" layers, plain torch) is
:class:`reflectmm_cli.evaluation.metrics.LPIPS`. **No weights ship and none are downloaded**: the user gives a
safetensors file whose tensor names are those of ``lpips.LPIPS(net=...).state_dict()``:

==========================  ==================  =====================================================
key                         shape               meaning
==========================  ==================  =====================================================
``net.sliceN.<i>.weight``   (C_out, C_in, k, k)  trunk convolution ``i`` (torchvision ``features.<i>``)
``net.sliceN.<i>.bias``     (C_out,)             its bias
``linN.model.1.weight``     (1, C_N, 1, 1)       learned non-negative channel weights of layer N (0–4)
``scaling_layer.shift``     (1, 3, 1, 1)         optional; must be (−0.030, −0.088, −0.188)
``scaling_layer.scale``     (1, 3, 1, 1)         optional; must be (0.458, 0.448, 0.450)
==========================  ==================  =====================================================

(torchvision ``features.<i>.*`` and short ``linN.weight`` names are accepted too.) Converting the ``lpips``
package's weights, on a machine that has it: ``safetensors.torch.save_file({k: v.contiguous() for k, v in
lpips.LPIPS(net="alex").state_dict().items()}, "lpips_alex.safetensors")``.

Distance (per layer ℓ with features f⁰, f¹ of shape (C,H,W)): channel-normalise ``f̂ = f / (‖f‖₂ + 1e−10)``
(norm over channels at each pixel), ``d_ℓ(y,x) = Σ_c w_c (f̂⁰ − f̂¹)²`` (the 1×1 "lin" layer), then

* :func:`lpips_image_mean` — ``Σ_ℓ mean_{y,x} d_ℓ`` (the package's default ``spatial=False``; the released
  evaluation's number);
* the masked mean of ``Σ_ℓ upsample(d_ℓ)`` (bilinear to the image size; ``spatial=True``) — ``LPIPS.__call__``,
  the per-image face-region LPIPS of :mod:`.face_metrics`.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

from reflectmm_cli.errors import ReflectmmError
from reflectmm_cli.threads import torch_threads

from .metrics import LPIPS, load_lpips  # noqa: F401 - the one loader, re-exported

__all__ = ["load_lpips", "save_lpips_safetensors", "lpips_status", "lpips_image_mean",
           "layer_distances"]


def save_lpips_safetensors(state: dict, path: str | Path) -> Path:
    """Write a state dict (torch tensors or numpy arrays) as safetensors, atomically (e.g. for converting weights
    or for tests that generate them)."""
    import torch
    from safetensors.torch import save

    from reflectmm_cli.artifacts import atomic_write_bytes

    tensors = {str(k): torch.as_tensor(np.asarray(v) if not isinstance(v, torch.Tensor) else v)
               .detach().to(torch.float32).contiguous() for k, v in state.items()}
    return atomic_write_bytes(path, save(tensors))


def lpips_status(model: LPIPS | None) -> str:
    """``"on (alex)"`` / ``"off (no weights given)"`` — what reports print next to LPIPS."""
    return "off (no weights given)" if model is None else f"on ({model.net})"


def _to_tensor(img):
    import torch

    a = np.asarray(img, np.float64)
    if a.ndim != 3 or a.shape[2] != 3:
        raise ReflectmmError(f"lpips: images must be (H,W,3), got {a.shape}")
    return torch.as_tensor(a * 2.0 - 1.0, dtype=torch.float32).permute(2, 0, 1)[None]


def layer_distances(model: LPIPS, pred, target) -> list[np.ndarray]:
    """The five per-layer distance maps ``d_ℓ`` (H_ℓ,W_ℓ) float64 of two (H,W,3) images in [0, 1]."""
    import torch
    import torch.nn.functional as F

    small = np.shape(pred)[0] * np.shape(pred)[1] <= 256 * 256
    with torch_threads(1 if small else None), torch.no_grad():
        f0, f1 = model.features(_to_tensor(pred)), model.features(_to_tensor(target))
        out = []
        for i, (a, b) in enumerate(zip(f0, f1)):
            a = a / (torch.sqrt((a ** 2).sum(1, keepdim=True)) + 1e-10)
            b = b / (torch.sqrt((b ** 2).sum(1, keepdim=True)) + 1e-10)
            d = F.conv2d((a - b) ** 2, model.params[f"lin{i}.model.1.weight"])
            out.append(d[0, 0].double().numpy())
    return out


def lpips_image_mean(model: LPIPS, pred, target) -> float:
    """LPIPS of two (H,W,3) images in [0, 1] as the ``lpips`` package returns it by default: the sum over
    layers of each layer's spatial mean distance (whole image, no mask)."""
    return float(sum(d.mean() for d in layer_distances(model, pred, target)))
