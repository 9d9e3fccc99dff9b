"""Face-recognition features for the perceptual loss L_per: ArcFace ``iresnet`` in plain torch.

Weights come only from a path the user gives (none ship): a safetensors file with insightface's
``arcface_torch`` key names — ``conv1.weight``, ``bn1.*``, ``prelu.weight``, ``layer{1-4}.{i}.{bn1,conv1,bn2,prelu,
conv2,bn3}.*``, ``layer{1-4}.0.downsample.{0,1}.*``, ``bn2.*``, ``fc.{weight,bias}``, ``features.*`` — e.g. made from
insightface's ``backbone.pth`` with ``safetensors.torch.save_file(torch.load(p), out)``. The depth (iresnet18 / 34 /
50 / 100) is recognised from the number of blocks per stage in the file. Input: 112×112 RGB in [−1, 1]
(``(x − 0.5)/0.5``); output: 512-d embedding (compared by cosine). Without a weights file the loss is **off**
(reported as such in the log and the model's meta), never replaced by something else.

Crop: the shards' aligned 224² crops (Deep3DFaceRecon alignment) are warped to ArcFace's 112² five-point template
by the similarity that maps the five points of the 68 landmarks (eye centres, nose tip, mouth corners: the one
:func:`reflectmm_cli.finetune.align.five_points` that prepare-wild's alignment uses) onto the template (least
squares), then resampled bilinearly (differentiable w.r.t. the image).
"""
from __future__ import annotations

import re
from pathlib import Path

import numpy as np

from reflectmm_cli.errors import ReflectmmError

from .align import five_points

__all__ = ["IdentityNet", "build_iresnet", "load_identity_net", "ARCFACE_TEMPLATE"]

#: ArcFace's 112×112 five-point template (left eye, right eye, nose tip, left / right mouth corner), pixels.
ARCFACE_TEMPLATE = np.array([[38.2946, 51.6963], [73.5318, 51.5014], [56.0252, 71.7366], [41.5493, 92.3655],
                             [70.7299, 92.2041]])
_DEPTHS = {(2, 2, 2, 2): "iresnet18", (3, 4, 6, 3): "iresnet34", (3, 4, 14, 3): "iresnet50",
           (3, 13, 30, 3): "iresnet100"}


def _similarity(src: np.ndarray, dst: np.ndarray) -> np.ndarray:
    """2×3 similarity (least squares, Umeyama) mapping src (5,2) → dst (5,2)."""
    ms, md = src.mean(0), dst.mean(0)
    s, d = src - ms, dst - md
    cov = d.T @ s / len(src)
    U, S, Vt = np.linalg.svd(cov)
    D = np.diag([1.0, np.sign(np.linalg.det(U @ Vt))])
    R = U @ D @ Vt
    scale = (S * np.diag(D)).sum() / max((s * s).sum() / len(src), 1e-12)
    A = scale * R
    return np.concatenate([A, (md - A @ ms)[:, None]], 1)


def build_iresnet(layers=(3, 4, 14, 3), width: int = 64, embedding: int = 512):
    """ArcFace iresnet (insightface arcface_torch layout) for 112² input. ``width`` scales every stage (tests)."""
    import torch
    import torch.nn as nn

    class IBasicBlock(nn.Module):
        def __init__(self, cin, planes, stride=1, downsample=None):
            super().__init__()
            self.bn1 = nn.BatchNorm2d(cin, eps=1e-5)
            self.conv1 = nn.Conv2d(cin, planes, 3, 1, 1, bias=False)
            self.bn2 = nn.BatchNorm2d(planes, eps=1e-5)
            self.prelu = nn.PReLU(planes)
            self.conv2 = nn.Conv2d(planes, planes, 3, stride, 1, bias=False)
            self.bn3 = nn.BatchNorm2d(planes, eps=1e-5)
            self.downsample = downsample

        def forward(self, x):
            idt = x if self.downsample is None else self.downsample(x)
            out = self.bn3(self.conv2(self.prelu(self.bn2(self.conv1(self.bn1(x))))))
            return out + idt

    class IResNet(nn.Module):
        def __init__(self):
            super().__init__()
            self.conv1 = nn.Conv2d(3, width, 3, 1, 1, bias=False)
            self.bn1 = nn.BatchNorm2d(width, eps=1e-5)
            self.prelu = nn.PReLU(width)
            cin = width
            for i, n in enumerate(layers):
                planes = width * 2 ** i
                down = nn.Sequential(nn.Conv2d(cin, planes, 1, 2, bias=False), nn.BatchNorm2d(planes, eps=1e-5))
                blocks = [IBasicBlock(cin, planes, 2, down)] + [IBasicBlock(planes, planes) for _ in range(1, n)]
                setattr(self, f"layer{i + 1}", nn.Sequential(*blocks))
                cin = planes
            self.bn2 = nn.BatchNorm2d(cin, eps=1e-5)
            self.fc = nn.Linear(cin * 7 * 7, embedding)
            self.features = nn.BatchNorm1d(embedding, eps=1e-5)

        def forward(self, x):  # x (B,3,112,112) in [-1, 1]
            x = self.prelu(self.bn1(self.conv1(x)))
            x = self.layer4(self.layer3(self.layer2(self.layer1(x))))
            x = torch.flatten(self.bn2(x), 1)
            return self.features(self.fc(x))

    return IResNet()


class IdentityNet:
    """A frozen ArcFace network plus the 224² → 112² alignment; ``features(images, landmarks)``."""

    def __init__(self, net, name: str, path: Path):
        self.net = net.eval()
        for p in self.net.parameters():
            p.requires_grad_(False)
        self.name, self.path = name, path

    def to(self, device):
        self.net.to(device)
        return self

    def align(self, images, landmarks):
        """(B,S,S,3) linear images (torch) + (B,68,2) crop landmarks → (B,3,112,112) in [−1, 1]."""
        import torch
        import torch.nn.functional as F

        B, S = images.shape[0], images.shape[1]
        thetas = []
        for b in range(B):
            lm = np.asarray(landmarks[b], np.float64)
            if not np.isfinite(lm).all() or np.ptp(lm[:, 0]) < 1e-6:  # no landmarks: centre crop of the face
                A = np.array([[112.0 / S, 0, 0], [0, 112.0 / S, 0]])
            else:
                A = _similarity(five_points(lm), ARCFACE_TEMPLATE)
            # output pixel (u,v) in 112² ← input pixel A⁻¹ (u,v); express in normalised coordinates
            M = np.vstack([A, [0, 0, 1]])
            Minv = np.linalg.inv(M)
            to_pix = np.array([[56.0, 0, 55.5], [0, 56.0, 55.5], [0, 0, 1]])  # out normalised → out pixels
            to_norm = np.array([[2.0 / S, 0, 1.0 / S - 1], [0, 2.0 / S, 1.0 / S - 1], [0, 0, 1]])  # in pixels → norm
            thetas.append((to_norm @ Minv @ to_pix)[:2])
        theta = torch.as_tensor(np.stack(thetas), dtype=images.dtype, device=images.device)
        x = images.permute(0, 3, 1, 2)
        grid = F.affine_grid(theta, (B, 3, 112, 112), align_corners=False)
        out = F.grid_sample(x, grid, mode="bilinear", padding_mode="zeros", align_corners=False)
        return (out.clamp(0, 1) - 0.5) / 0.5

    def features(self, images, landmarks):
        """(B, 512) embeddings of (B,S,S,3) linear images (differentiable w.r.t. the images)."""
        return self.net(self.align(images, landmarks).to(next(self.net.parameters()).dtype))


def load_identity_net(path: str | Path, device="cpu") -> IdentityNet:
    """ArcFace iresnet from a safetensors file (layout in the module docstring); one-line errors on bad files."""
    from safetensors.torch import load_file

    path = Path(path)
    if not path.is_file():
        raise ReflectmmError("identity-network weights not found", path)
    try:
        sd = load_file(str(path))
    except Exception as e:  # safetensors raises several types for a bad header
        raise ReflectmmError(f"not a readable safetensors file ({type(e).__name__}: {e})", path) from None
    if "conv1.weight" not in sd or "fc.weight" not in sd:
        raise ReflectmmError("not an ArcFace iresnet in insightface key layout (conv1.weight / fc.weight missing)",
                             path)
    counts = []
    for i in range(1, 5):
        ids = {int(m.group(1)) for k in sd for m in [re.match(rf"layer{i}\.(\d+)\.", k)] if m}
        counts.append(max(ids) + 1 if ids else 0)
    width = int(sd["conv1.weight"].shape[0])
    emb = int(sd["fc.weight"].shape[0])
    net = build_iresnet(tuple(counts), width, emb)
    sd = {k: v for k, v in sd.items() if not k.endswith("num_batches_tracked")}
    own = {k for k in net.state_dict() if not k.endswith("num_batches_tracked")}
    missing, unexpected = sorted(own - set(sd)), sorted(set(sd) - own)
    if missing or unexpected:
        raise ReflectmmError(f"identity weights do not match an iresnet with blocks {counts}: missing {missing[:3]}, "
                             f"unexpected {unexpected[:3]}", path)
    try:
        net.load_state_dict(sd, strict=False)
    except RuntimeError as e:
        raise ReflectmmError(f"identity weights have wrong shapes ({str(e).splitlines()[-1].strip()})", path) from None
    name = _DEPTHS.get(tuple(counts), f"iresnet{counts}")
    return IdentityNet(net, name, path).to(device)
