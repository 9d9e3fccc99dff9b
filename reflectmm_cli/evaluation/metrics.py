"""Image metrics in a face region: PSNR, SSIM and LPIPS (docs/design.md §1 step 8).

All images are (H,W,3) (or (H,W)) float arrays; ``mask`` (H,W) bool selects the face region.

* **PSNR** = ``10 log10(peak² / MSE)``, MSE over the masked pixels and all channels; ``peak`` defaults to 1
  (images in the display encoding, see :func:`encode_for_metrics`). Identical images give ``inf``.
* **SSIM** (Wang et al. 2004) through ``skimage.metrics.structural_similarity`` with Gaussian weighting
  (σ = 1.5, 11×11 window), population covariances, K1 = 0.01, K2 = 0.03, ``data_range = peak``; the full SSIM
  map is averaged over the masked pixels (per channel, then over channels). Pixels outside the mask are set to 0
  in both images first, so windows that straddle the border of the region compare the region's values only
  against zeros, identically in both images.
* **LPIPS** (Zhang et al. 2018): :class:`LPIPS` — the network written in plain torch (AlexNet or VGG16 trunk and
  the learned 1×1 "lin" layers); weights only from a state dict file the user gives. The spatial LPIPS map
  (each layer's distance upsampled bilinearly to the image size, as ``lpips``' ``spatial=True``) is averaged over
  the mask. Without weights there is no LPIPS number.
"""
from __future__ import annotations

import warnings
from pathlib import Path
from typing import Any

import numpy as np

from reflectmm_cli.color import encode_display
from reflectmm_cli.errors import ReflectmmError
from reflectmm_cli.threads import torch_threads

__all__ = ["encode_for_metrics", "psnr", "ssim", "LPIPS", "load_lpips", "lpips_distance", "DISPLAY_GAMMA"]

#: The Multi-PIE-style 8-bit encoding of docs/pipeline.md: stored = clip(linear, 0, 1) ** (1/1.2).
DISPLAY_GAMMA = 1.2


def encode_for_metrics(linear: np.ndarray, gamma: float = DISPLAY_GAMMA) -> np.ndarray:
    """Linear radiance → the display encoding the captures are stored in: ``clip(x, 0, 1) ** (1/gamma)``,
    float64, NaN kept (:func:`reflectmm_cli.color.encode_display`)."""
    return encode_display(linear, "gamma", gamma=gamma, nan_to_num=False, dtype=np.float64)


def _prep(pred, target, mask, name):
    a = np.asarray(pred, np.float64)
    b = np.asarray(target, np.float64)
    if a.shape != b.shape:
        raise ReflectmmError(f"{name}: prediction has shape {a.shape} but target has shape {b.shape}")
    if a.ndim not in (2, 3):
        raise ReflectmmError(f"{name}: images must be (H,W) or (H,W,C), got {a.shape}")
    if mask is None:
        m = np.ones(a.shape[:2], bool)
    else:
        m = np.asarray(mask, bool)
        if m.shape != a.shape[:2]:
            raise ReflectmmError(f"{name}: mask has shape {m.shape}, expected {a.shape[:2]}")
    if not m.any():
        raise ReflectmmError(f"{name}: the mask selects no pixel")
    return a, b, m


def psnr(pred, target, mask=None, peak: float = 1.0) -> float:
    """PSNR in dB over the masked pixels (all channels): ``10 log10(peak² / MSE)``; ``inf`` if identical."""
    a, b, m = _prep(pred, target, mask, "psnr")
    mse = float(np.mean((a[m] - b[m]) ** 2))
    if mse == 0.0:
        return float("inf")
    return float(10.0 * np.log10(peak ** 2 / mse))


def ssim(pred, target, mask=None, peak: float = 1.0, return_map: bool = False):
    """Mean SSIM over the masked pixels (Gaussian window σ = 1.5, data range ``peak``); see module docstring."""
    from skimage.metrics import structural_similarity

    a, b, m = _prep(pred, target, mask, "ssim")
    if min(a.shape[:2]) < 11:
        raise ReflectmmError(f"ssim: images must be at least 11×11 for the 11×11 Gaussian window, got {a.shape[:2]}")
    a = np.where(m[..., None] if a.ndim == 3 else m, a, 0.0)
    b = np.where(m[..., None] if b.ndim == 3 else m, b, 0.0)
    kw: dict[str, Any] = dict(data_range=peak, gaussian_weights=True, sigma=1.5, use_sample_covariance=False,
                              full=True)
    if a.ndim == 3:
        kw["channel_axis"] = -1
    _, smap = structural_similarity(a, b, **kw)
    per_pixel = smap.mean(-1) if smap.ndim == 3 else smap
    value = float(per_pixel[m].mean())
    return (value, per_pixel) if return_map else value


# --------------------------------------------------------------------------- LPIPS

# Channel counts and layer layouts of the two trunks, with the module indices of torchvision's ``features``
# (which the ``lpips`` package's state dicts use as ``net.sliceN.<index>``).
_ALEX = {  # index: (in, out, kernel, stride, padding); 'M' = max pool 3/2
    "slices": [[0, 1], ["M2", 3, 4], ["M5", 6, 7], [8, 9], [10, 11]],
    "convs": {0: (3, 64, 11, 4, 2), 3: (64, 192, 5, 1, 2), 6: (192, 384, 3, 1, 1), 8: (384, 256, 3, 1, 1),
              10: (256, 256, 3, 1, 1)},
    "pool": (3, 2),
    "chns": [64, 192, 384, 256, 256],
}
_VGG_CFG = [64, 64, "M", 128, 128, "M", 256, 256, 256, "M", 512, 512, 512, "M", 512, 512, 512, "M"]


def _vgg_layout():
    convs, idx, cin = {}, 0, 3
    kinds = []
    for c in _VGG_CFG:
        if c == "M":
            kinds.append(("M", idx))
            idx += 1
        else:
            convs[idx] = (cin, c, 3, 1, 1)
            kinds.append(("C", idx))
            kinds.append(("R", idx + 1))
            idx += 2
            cin = c
    bounds = [(0, 4), (4, 9), (9, 16), (16, 23), (23, 30)]
    return convs, bounds


class LPIPS:
    """LPIPS distance network (``net`` = ``"alex"`` or ``"vgg"``) in plain torch; no weights built in.

    State dict keys (those of ``lpips.LPIPS(net=...).state_dict()``): ``net.sliceN.<i>.weight|bias`` for the
    trunk (torchvision ``features.<i>.*`` keys are accepted too) and ``linN.model.1.weight`` (shape (1,C_N,1,1))
    for the 5 learned layers (``linN.weight`` accepted). ``scaling_layer.*`` entries, if present, must equal the
    standard ImageNet shift/scale constants used here.
    """

    SHIFT = (-0.030, -0.088, -0.188)
    SCALE = (0.458, 0.448, 0.450)

    def __init__(self, net: str = "alex"):
        import torch

        if net not in ("alex", "vgg"):
            raise ReflectmmError(f"LPIPS: net must be 'alex' or 'vgg', got {net!r}")
        self.net = net
        self.params: dict[str, "torch.Tensor"] = {}
        self.layers: list[list[tuple]] = []  # per slice: ("conv", idx, stride, pad) | ("relu",) | ("pool", k, s)
        if net == "alex":
            convs = _ALEX["convs"]
            for sl in _ALEX["slices"]:
                ops = []
                for item in sl:
                    if isinstance(item, str):
                        ops.append(("pool", 3, 2))
                    elif item in convs:
                        ops.append(("conv", item, convs[item][3], convs[item][4]))
                    else:
                        ops.append(("relu",))
                self.layers.append(ops)
            self.chns = list(_ALEX["chns"])
        else:
            convs, bounds = _vgg_layout()
            pools = {4, 9, 16, 23}
            for lo, hi in bounds:
                ops = []
                for i in range(lo, hi):
                    if i in convs:
                        ops.append(("conv", i, 1, 1))
                    elif i in pools:
                        ops.append(("pool", 2, 2))
                    else:
                        ops.append(("relu",))
                self.layers.append(ops)
            self.chns = [64, 128, 256, 512, 512]
        self.conv_shapes = {}
        for s, ops in enumerate(self.layers):
            for op in ops:
                if op[0] == "conv":
                    cin, cout, k, _, _ = convs[op[1]]
                    self.conv_shapes[f"net.slice{s + 1}.{op[1]}.weight"] = (cout, cin, k, k)
                    self.conv_shapes[f"net.slice{s + 1}.{op[1]}.bias"] = (cout,)
        for i, c in enumerate(self.chns):
            self.conv_shapes[f"lin{i}.model.1.weight"] = (1, c, 1, 1)

    # ----------------------------------------------------------------- weights
    def expected_keys(self) -> dict[str, tuple]:
        """Canonical state-dict keys → shapes."""
        return dict(self.conv_shapes)

    def random_state_dict(self, seed: int = 0) -> dict[str, Any]:
        """A state dict of the right structure with random weights (lin layers non-negative) — for tests and
        for checking a pipeline; not a meaningful perceptual metric."""
        import torch

        g = torch.Generator().manual_seed(seed)
        sd = {}
        for k, shp in self.conv_shapes.items():
            t = torch.randn(shp, generator=g, dtype=torch.float32)
            if k.endswith(".weight") and k.startswith("net."):
                t = t * (2.0 / (shp[1] * shp[2] * shp[3])) ** 0.5
            elif k.startswith("lin"):
                t = t.abs() / shp[1]
            else:
                t = t * 0.01
            sd[k] = t
        return sd

    def _canonical(self, key: str) -> str:
        if key.startswith("features."):
            idx = int(key.split(".")[1])
            for s, ops in enumerate(self.layers):
                if any(op[0] == "conv" and op[1] == idx for op in ops):
                    return f"net.slice{s + 1}.{key[len('features.'):]}"
            return key
        if key.startswith("lin") and key.count(".") == 1:
            head, tail = key.split(".")
            return f"{head}.model.1.{tail}"
        if key.startswith("module."):
            return self._canonical(key[len("module."):])
        return key

    def load_state_dict(self, state: dict[str, Any], source: str | Path | None = None) -> "LPIPS":
        """Load trunk + lin weights; errors name the key (missing, unexpected shape, non-finite)."""
        import torch

        where = f"{source}: " if source is not None else ""
        canon: dict[str, Any] = {}
        for k, v in state.items():
            ck = self._canonical(str(k))
            if ck.startswith("scaling_layer."):
                ref = self.SHIFT if ck.endswith("shift") else self.SCALE
                vv = torch.as_tensor(v).reshape(-1).tolist()
                if len(vv) != 3 or max(abs(a - b) for a, b in zip(vv, ref)) > 1e-3:
                    raise ReflectmmError(f"{where}LPIPS weights: '{k}' = {vv} differs from the standard {ref}")
                continue
            canon[ck] = v
        missing = [k for k in self.conv_shapes if k not in canon]
        if missing:
            raise ReflectmmError(f"{where}LPIPS weights ({self.net}): missing key(s) {', '.join(missing[:6])}"
                                 + (" ..." if len(missing) > 6 else "")
                                 + f" (found {len(canon)} keys; a full lpips.LPIPS state dict with the trunk is "
                                   "needed, the lin-only files of the lpips package are not enough)")
        params = {}
        for k, shp in self.conv_shapes.items():
            t = torch.as_tensor(canon[k]).detach().to(torch.float32)
            if tuple(t.shape) != shp:
                raise ReflectmmError(f"{where}LPIPS weights ({self.net}): key '{k}' has shape {tuple(t.shape)}, "
                                     f"expected {shp}")
            if not torch.isfinite(t).all():
                raise ReflectmmError(f"{where}LPIPS weights: key '{k}' contains NaN or inf")
            params[k] = t
        self.params = params
        return self

    # ----------------------------------------------------------------- forward
    def features(self, x):
        """List of the 5 slice outputs for x (B,3,H,W) in [−1, 1]."""
        import torch
        import torch.nn.functional as F

        if not self.params:
            raise ReflectmmError("LPIPS: no weights loaded (give --lpips-weights FILE)")
        shift = torch.tensor(self.SHIFT, dtype=x.dtype, device=x.device).view(1, 3, 1, 1)
        scale = torch.tensor(self.SCALE, dtype=x.dtype, device=x.device).view(1, 3, 1, 1)
        h = (x - shift) / scale
        feats = []
        for s, ops in enumerate(self.layers):
            for op in ops:
                if op[0] == "conv":
                    w = self.params[f"net.slice{s + 1}.{op[1]}.weight"].to(x.device, x.dtype)
                    b = self.params[f"net.slice{s + 1}.{op[1]}.bias"].to(x.device, x.dtype)
                    h = F.conv2d(h, w, b, stride=op[2], padding=op[3])
                elif op[0] == "relu":
                    h = torch.relu(h)
                else:
                    h = F.max_pool2d(h, kernel_size=op[1], stride=op[2])
            feats.append(h)
        return feats

    def distance_map(self, x0, x1):
        """(B,1,H,W) spatial LPIPS map for x0, x1 (B,3,H,W) in [−1, 1]."""
        import torch
        import torch.nn.functional as F

        f0, f1 = self.features(x0), self.features(x1)
        out = 0
        for i, (a, b) in enumerate(zip(f0, f1)):
            a = a / (torch.sqrt((a ** 2).sum(1, keepdim=True)) + 1e-10)
            b = b / (torch.sqrt((b ** 2).sum(1, keepdim=True)) + 1e-10)
            d = F.conv2d((a - b) ** 2, self.params[f"lin{i}.model.1.weight"].to(x0.device, x0.dtype))
            out = out + F.interpolate(d, size=x0.shape[-2:], mode="bilinear", align_corners=False)
        return out

    def __call__(self, pred, target, mask=None) -> float:
        """LPIPS between two (H,W,3) images in [0, 1] (display encoding), averaged over ``mask``."""
        import torch

        a, b, m = _prep(pred, target, mask, "lpips")
        if a.ndim != 3 or a.shape[2] != 3:
            raise ReflectmmError(f"lpips: images must be (H,W,3), got {a.shape}")
        min_size = 32 if self.net == "vgg" else 31
        if min(a.shape[:2]) < min_size:
            raise ReflectmmError(f"lpips: images must be at least {min_size}×{min_size} for the {self.net} trunk, "
                                 f"got {a.shape[:2]}")
        t = lambda z: torch.as_tensor(np.where(m[..., None], z, 0.0) * 2 - 1,  # noqa: E731
                                      dtype=torch.float32).permute(2, 0, 1)[None]
        # small images: one thread is much faster than several contending ones (measured 70× on 2 busy cores)
        small = a.shape[0] * a.shape[1] <= 256 * 256
        with torch_threads(1 if small else None), torch.no_grad():
            dmap = self.distance_map(t(a), t(b))[0, 0].numpy()
        return float(dmap[m].mean())


def _is_safetensors(p: Path) -> bool:
    """A safetensors file starts with the little-endian u64 length of its JSON header, then ``{``."""
    with open(p, "rb") as f:
        head = f.read(9)
    return len(head) == 9 and head[8:9] == b"{" and 2 <= int.from_bytes(head[:8], "little") <= p.stat().st_size


def _torch_load_reason(exc: Exception) -> str:
    """The reason of a failed ``torch.load``, short: the weights-only unpickler's own words (not torch's paragraph
    on the ``weights_only`` default around them), else the first sentence of the message."""
    text = " ".join(str(exc).split())
    if "WeightsUnpickler error:" in text:
        reason = text.split("WeightsUnpickler error:", 1)[1].split(" Check the documentation", 1)[0].strip()
        return f"not loadable with weights_only=True: {reason[:120]}"
    return text.split(". ", 1)[0][:160] or "empty or truncated file"


def load_lpips(path: str | Path | None, net: str = "alex") -> LPIPS | None:
    """An :class:`LPIPS` with weights from ``path``, or None when no path is given (LPIPS is then reported as off,
    never estimated). The one loader of every verb: a safetensors file (the documented layout,
    :mod:`reflectmm_cli.evaluation.lpips`), or — recognised by its content — a torch state dict (or a dict holding
    one under ``state_dict``) read with ``weights_only=True`` (no code runs from the file)."""
    if path is None:
        return None
    import torch

    p = Path(path)
    if not p.is_file():
        raise ReflectmmError("LPIPS weights file not found", p)
    if _is_safetensors(p):
        try:
            from safetensors.torch import load_file

            state = load_file(str(p), device="cpu")
        except Exception as exc:  # safetensors raises several types for a bad header
            raise ReflectmmError(f"cannot read LPIPS weights as safetensors ({type(exc).__name__}: "
                                 f"{' '.join(str(exc).split())[:160]})", p) from None
        return LPIPS(net).load_state_dict(state, source=p)
    try:
        with warnings.catch_warnings():  # torch warns about pickle protocols on stderr, beside the one-line error
            warnings.simplefilter("ignore")
            state = torch.load(p, map_location="cpu", weights_only=True)
    except Exception as exc:  # torch raises many types for a bad file
        raise ReflectmmError(f"cannot read LPIPS weights as safetensors or a torch state dict "
                             f"({type(exc).__name__}: {_torch_load_reason(exc)})", p) from None
    if isinstance(state, dict) and "state_dict" in state and isinstance(state["state_dict"], dict):
        state = state["state_dict"]
    if not isinstance(state, dict):
        raise ReflectmmError(f"LPIPS weights: expected a state dict, got {type(state).__name__}", p)
    return LPIPS(net).load_state_dict(state, source=p)


def lpips_distance(model: LPIPS | None, pred, target, mask=None) -> float | None:
    """LPIPS or None when no model (no weights given)."""
    return None if model is None else model(pred, target, mask)
