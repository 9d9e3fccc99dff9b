"""Reading ``wild-shard`` datasets (schema ``reflectmm.wild-shard/1``, format in docs/finetune.md) for training.

Everything finetuning needs from the shards goes through :func:`load_shards` → :class:`ShardSet`, so the reader
can be replaced (e.g. by a memory-mapped one) without touching the training loop.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Sequence

import numpy as np

from reflectmm_cli.errors import ReflectmmError

__all__ = ["SHARD_KIND", "ShardSet", "load_shards", "linearise"]

SHARD_KIND = "wild-shard"
ENCODINGS = ("gamma1.2", "srgb", "linear")
_PER_IMAGE = ("names", "split", "image", "face_mask", "skin_mask")
_PER_PIXEL = ("pix_yx", "vert_ids", "bary", "normal", "view", "visible")


def linearise(image_u8: np.ndarray, encoding: str) -> np.ndarray:
    """(…,3) uint8 (or float in [0,1]) as stored → float32 linear radiance (gamma1.2: x^1.2; srgb: the sRGB EOTF)."""
    x = np.asarray(image_u8)
    x = x.astype(np.float32) / 255.0 if x.dtype == np.uint8 else x.astype(np.float32)
    if encoding == "gamma1.2":
        return np.power(np.clip(x, 0, None), 1.2, dtype=np.float32)
    if encoding == "srgb":
        return np.where(x <= 0.04045, x / 12.92, ((x + 0.055) / 1.055) ** 2.4).astype(np.float32)
    if encoding == "linear":
        return x
    raise ReflectmmError(f"unknown image encoding {encoding!r} (expected one of {', '.join(ENCODINGS)})")


@dataclass
class ShardSet:
    """N images of side S from one or more shards, G-buffers packed over P face pixels (offsets made global).

    Attributes mirror the shard arrays (``names``, ``split``, ``image``, ``face_mask``, ``skin_mask``,
    ``pix_offset`` (N+1,), ``pix_yx``, ``vert_ids``, ``bary``, ``normal``, ``view``, ``visible``);
    ``encoding`` (N,) per image; ``truth`` optional ``truth_*`` arrays (per image, first axis N);
    ``sources`` the shard paths; ``face_model`` the face-model reference of the first shard's meta.
    """

    names: np.ndarray
    split: np.ndarray
    image: np.ndarray
    face_mask: np.ndarray
    skin_mask: np.ndarray
    pix_offset: np.ndarray
    pix_yx: np.ndarray
    vert_ids: np.ndarray
    bary: np.ndarray
    normal: np.ndarray
    view: np.ndarray
    visible: np.ndarray
    encoding: np.ndarray
    size: int
    sh_order: int = 8
    truth: dict = field(default_factory=dict)
    sources: list = field(default_factory=list)
    face_model: dict | None = None
    landmarks: np.ndarray | None = None

    def __len__(self) -> int:
        return int(self.names.shape[0])

    def indices(self, split: str) -> np.ndarray:
        """Image indices of one split ("train" | "val" | "test")."""
        return np.flatnonzero(self.split == split)

    def linear_image(self, i: int) -> np.ndarray:
        """(S,S,3) float32 linear radiance of image i."""
        return linearise(self.image[i], str(self.encoding[i]))

    def batch(self, idx: Sequence[int], with_target: bool = True) -> dict:
        """Packed G-buffer of the images ``idx`` (numpy; see :func:`reflectmm_cli.finetune.render.batch_gbuffer`)
        plus ``images`` (B,S,S,3) uint8 as stored, ``linear`` (B,S,S,3) float32 and ``target`` (P,3)."""
        idx = [int(i) for i in idx]
        rows = [np.arange(self.pix_offset[i], self.pix_offset[i + 1]) for i in idx]
        counts = [len(r) for r in rows]
        r = np.concatenate(rows) if rows else np.zeros(0, np.int64)
        yx = self.pix_yx[r].astype(np.int64)
        out = {"offsets": np.concatenate([[0], np.cumsum(counts)]).astype(np.int64), "pix_yx": yx,
               "vert_ids": self.vert_ids[r], "bary": self.bary[r].astype(np.float32),
               "normal": self.normal[r].astype(np.float32), "view": self.view[r].astype(np.float32),
               "size": self.size, "images": self.image[idx]}
        img_of = np.repeat(np.arange(len(idx)), counts)
        out["skin"] = self.skin_mask[np.asarray(idx)[img_of], yx[:, 0], yx[:, 1]] if len(r) else np.zeros(0, bool)
        if with_target:
            lin = np.stack([self.linear_image(i) for i in idx]) if idx else np.zeros((0, self.size, self.size, 3))
            out["linear"] = lin.astype(np.float32)
            out["target"] = lin[img_of, yx[:, 0], yx[:, 1]] if len(r) else np.zeros((0, 3), np.float32)
        return out


def _check(path, arrays, meta):
    miss = [k for k in _PER_IMAGE + _PER_PIXEL + ("pix_offset",) if k not in arrays]
    if miss:
        raise ReflectmmError(f"wild-shard is missing arrays {miss}", path)
    n = int(arrays["names"].shape[0])
    if n == 0:
        raise ReflectmmError("wild-shard holds no images (empty shard)", path)
    img = arrays["image"]
    if img.ndim != 4 or img.shape[0] != n or img.shape[3] != 3 or img.shape[1] != img.shape[2]:
        raise ReflectmmError(f"wild-shard: image must have shape ({n},S,S,3), got {img.shape}", path)
    if img.dtype != np.uint8:
        if img.dtype.kind != "f":
            raise ReflectmmError(f"wild-shard: image must be uint8, got {img.dtype}", path)
        bad = ~np.isfinite(img)
        if bad.any():
            i = int(np.flatnonzero(bad.reshape(n, -1).any(1))[0])
            raise ReflectmmError(f"wild-shard: image {i} ({arrays['names'][i]}) contains NaN or inf", path)
    S = int(img.shape[1])
    for k in ("face_mask", "skin_mask"):
        if arrays[k].shape != (n, S, S):
            raise ReflectmmError(f"wild-shard: {k} must have shape ({n},{S},{S}), got {arrays[k].shape}", path)
    off = np.asarray(arrays["pix_offset"], np.int64)
    P = int(arrays["vert_ids"].shape[0])
    if off.shape != (n + 1,) or off[0] != 0 or off[-1] != P or np.any(np.diff(off) < 0):
        raise ReflectmmError(f"wild-shard: pix_offset must be ({n + 1},) non-decreasing from 0 to P = {P}", path)
    if P == 0:
        raise ReflectmmError("wild-shard has no face pixels (empty G-buffer)", path)
    for k, c in (("pix_yx", 2), ("vert_ids", 3), ("bary", 3), ("normal", 3), ("view", 3)):
        if arrays[k].shape != (P, c):
            raise ReflectmmError(f"wild-shard: {k} must have shape ({P},{c}), got {arrays[k].shape}", path)
        if arrays[k].dtype.kind == "f" and not np.isfinite(arrays[k]).all():
            raise ReflectmmError(f"wild-shard: {k} contains NaN or inf", path)
    enc = str(meta.get("encoding", "gamma1.2"))
    if enc not in ENCODINGS:
        raise ReflectmmError(f"wild-shard: unknown encoding {enc!r} (expected one of {', '.join(ENCODINGS)})", path)
    return n, S, enc


def load_shards(paths: Sequence[str | Path]) -> ShardSet:
    """Read and concatenate ``wild-shard`` artifacts (all of one image size and SH order).

    Raises :class:`ReflectmmError` (one line naming the file) on a wrong kind, an empty shard, missing or
    mis-shaped arrays, NaN/inf in images or G-buffers, or shards that disagree in image size.
    """
    from reflectmm_cli.artifacts import read_artifact

    if not paths:
        raise ReflectmmError("finetune: no data shards given (--data)")
    parts, S0, order0, fm = [], None, None, None
    for p in paths:
        art = read_artifact(p, SHARD_KIND)
        n, S, enc = _check(Path(p), art.arrays, art.meta)
        order = int(art.meta.get("sh_order", 8))
        if S0 is None:
            S0, order0 = S, order
            if art.meta.get("face_model"):
                fm = dict(art.meta["face_model"]) if isinstance(art.meta["face_model"], dict) else \
                    {"path": str(art.meta["face_model"])}
                if fm.get("path"):
                    fm["resolved"] = str((Path(p).parent / fm["path"]).resolve())
        elif S != S0:
            raise ReflectmmError(f"wild-shard: image size {S} differs from {S0} of {paths[0]}", p)
        parts.append((art.arrays, n, enc))
    offs, base = [], 0
    for a, n, _ in parts:
        offs.append(np.asarray(a["pix_offset"], np.int64)[:-1] + base)
        base += int(a["pix_offset"][-1])
    offs.append(np.array([base]))
    cat = lambda k: np.concatenate([a[k] for a, _, _ in parts])  # noqa: E731
    truth = {}
    tkeys = set.intersection(*[{k for k in a if k.startswith("truth_")} for a, _, _ in parts])
    for k in sorted(tkeys):
        truth[k] = cat(k)
    return ShardSet(names=cat("names").astype(str), split=cat("split").astype(str), image=cat("image"),
                    face_mask=cat("face_mask").astype(bool), skin_mask=cat("skin_mask").astype(bool),
                    pix_offset=np.concatenate(offs), pix_yx=cat("pix_yx"), vert_ids=cat("vert_ids"),
                    bary=cat("bary"), normal=cat("normal"), view=cat("view"), visible=cat("visible").astype(bool),
                    encoding=np.concatenate([np.full(n, enc) for _, n, enc in parts]), size=int(S0),
                    sh_order=int(order0), truth=truth, sources=[Path(p) for p in paths], face_model=fm)
