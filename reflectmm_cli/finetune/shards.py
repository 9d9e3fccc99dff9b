"""Reading ``wild-shard`` datasets for training and reconstruction (schema ``reflectmm.wild-shard/1``, format in
docs/wild.md).

One reader: every shard is opened with :func:`reflectmm_cli.finetune.data.open_shard` (each array a read-only
memory map through its zip offset, pages read on demand), and :func:`load_shards` presents one or more of them as a
:class:`ShardSet` — the per-image and per-pixel arrays as :class:`Stacked` views that read only the rows a batch
asks for.  The same :class:`ShardSet` also wraps in-memory arrays (``reconstruct --images``).
"""
from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Mapping, Sequence

import numpy as np

from reflectmm_cli.errors import ReflectmmError

from .data import ENCODINGS, SHARD_KIND, Shard, linearize, open_shard

__all__ = ["SHARD_KIND", "ShardSet", "Stacked", "load_shards", "shardset_from_arrays", "iter_batches"]

_PER_IMAGE = ("names", "split", "image", "face_mask", "skin_mask")
_PER_PIXEL = ("pix_yx", "vert_ids", "bary", "normal", "view", "visible")


class Stacked:
    """Read-only concatenation of arrays along axis 0 without copying them (e.g. the memory maps of several shards).

    Indexing with an int, a slice or an integer array (first axis only) reads only the rows asked for; ``np.asarray(a)`` reads everything.  ``shape``, ``dtype``, ``size``, ``max()``.
    """

    def __init__(self, parts: Sequence[np.ndarray]):
        self.parts = list(parts)
        self.starts = np.concatenate([[0], np.cumsum([len(p) for p in self.parts])]).astype(np.int64)
        self.dtype = self.parts[0].dtype
        self.shape = (int(self.starts[-1]),) + tuple(self.parts[0].shape[1:])

    @property
    def size(self) -> int:
        return int(np.prod(self.shape))

    @property
    def ndim(self) -> int:
        return len(self.shape)

    def __len__(self) -> int:
        return self.shape[0]

    def __array__(self, dtype=None, copy=None):
        a = np.concatenate([np.asarray(p) for p in self.parts]) if len(self.parts) > 1 else np.array(self.parts[0])
        return a if dtype is None else a.astype(dtype)

    def max(self):
        return max(np.asarray(p).max() for p in self.parts if len(p))

    def rows(self, idx) -> np.ndarray:
        """The rows ``idx`` (int array, any order, repeats allowed) as one in-memory array."""
        idx = np.asarray(idx, np.int64).reshape(-1)
        if len(self.parts) == 1:
            return np.array(self.parts[0][idx])
        out = np.empty((len(idx),) + self.shape[1:], self.dtype)
        part = np.searchsorted(self.starts, idx, side="right") - 1
        for k in np.unique(part):
            sel = part == k
            out[sel] = self.parts[k][idx[sel] - self.starts[k]]
        return out

    def span(self, lo: int, hi: int) -> np.ndarray:
        """Rows ``lo:hi`` as a view of one part (memory map slice, no copy); the span must not cross two parts
        (an image's G-buffer rows never do: they lie in its own shard)."""
        part = int(np.searchsorted(self.starts, lo, side="right") - 1)
        a = int(lo - self.starts[part])
        if hi - lo > len(self.parts[part]) - a:
            raise IndexError(f"rows {lo}:{hi} cross two parts")
        return self.parts[part][a:a + (hi - lo)]

    def __getitem__(self, key):
        if isinstance(key, tuple):
            raise TypeError("Stacked arrays are indexed along the first axis only (a[i], a[idx], a[i:j])")
        if isinstance(key, (int, np.integer)):
            k = int(key) + (len(self) if int(key) < 0 else 0)
            part = int(np.searchsorted(self.starts, k, side="right") - 1)
            return np.array(self.parts[part][k - self.starts[part]])  # a writable copy of one row
        if isinstance(key, slice):
            key = np.arange(len(self))[key]
        return self.rows(key)


def _stack(parts):
    return Stacked(parts)


@dataclass
class ShardSet:
    """N images of side S from one or more shards, G-buffers packed over P face pixels (offsets made global).

    Attributes mirror the shard arrays (``names``, ``split``, ``image``, ``face_mask``, ``skin_mask``,
    ``landmarks``, ``pix_offset`` (N+1,), ``pix_yx``, ``vert_ids``, ``bary``, ``normal``, ``view``, ``visible``);
    ``names``, ``split``, ``encoding`` (N,) and ``pix_offset`` are in memory, the others are memory maps
    (:class:`Stacked` over several shards) read row by row.  ``truth`` holds the optional ``truth_*`` arrays
    (first axis N); ``sources`` the shard paths; ``face_model`` the face-model reference of the first shard's
    meta ({sha256, path, resolved}).
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
        return _linear(self.image[i], str(self.encoding[i]))

    def batch(self, idx: Sequence[int], with_target: bool = True) -> dict:
        """Packed G-buffer of the images ``idx`` (numpy; see :func:`reflectmm_cli.finetune.render.batch_gbuffer`)
        plus ``images`` (B,S,S,3) uint8 as stored, ``linear`` (B,S,S,3) float32 and ``target`` (P,3)."""
        idx = [int(i) for i in idx]
        spans = [(int(self.pix_offset[i]), int(self.pix_offset[i + 1])) for i in idx]
        counts = [b - a for a, b in spans]
        n_pix = sum(counts)

        def take(a):  # each image's rows are one contiguous span: slices, not a fancy index per row
            parts = [a.span(lo, hi) if isinstance(a, Stacked) else a[lo:hi] for lo, hi in spans]
            return np.concatenate(parts) if parts else np.asarray(a[:0])

        yx = take(self.pix_yx).astype(np.int64)
        images = np.stack([np.asarray(self.image[i]) for i in idx]) if idx else \
            np.zeros((0, self.size, self.size, 3), np.uint8)
        out = {"offsets": np.concatenate([[0], np.cumsum(counts)]).astype(np.int64), "pix_yx": yx,
               "vert_ids": take(self.vert_ids), "bary": take(self.bary).astype(np.float32),
               "normal": take(self.normal).astype(np.float32), "view": take(self.view).astype(np.float32),
               "size": self.size, "images": images}
        img_of = np.repeat(np.arange(len(idx)), counts)
        skin = np.stack([np.asarray(self.skin_mask[i], bool) for i in idx]) if idx else np.zeros((0, 1, 1), bool)
        out["skin"] = skin[img_of, yx[:, 0], yx[:, 1]] if n_pix else np.zeros(0, bool)
        if with_target:
            lin = np.stack([self.linear_image(i) for i in idx]) if idx else np.zeros((0, self.size, self.size, 3))
            out["linear"] = lin.astype(np.float32)
            out["target"] = lin[img_of, yx[:, 0], yx[:, 1]] if n_pix else np.zeros((0, 3), np.float32)
        return out


def _linear(image: np.ndarray, encoding: str) -> np.ndarray:
    """Stored image → linear float32 (uint8 codes through :func:`~reflectmm_cli.finetune.data.linearize`; a float
    image, which only a hand-made shard holds, is taken as codes / 255)."""
    image = np.asarray(image)
    if image.dtype != np.uint8:
        image = np.asarray(image, np.float32) * 255.0
    return linearize(image, encoding)


def _check(path, a: Mapping[str, np.ndarray], meta) -> tuple[int, int, str]:
    """Shapes, emptiness and finiteness of one shard's arrays (memory maps: the float G-buffer is scanned once)."""
    miss = [k for k in _PER_IMAGE + _PER_PIXEL + ("pix_offset",) if k not in a]
    if miss:
        raise ReflectmmError(f"wild-shard is missing arrays {miss}", path)
    n = int(a["names"].shape[0])
    if n == 0:
        raise ReflectmmError("wild-shard holds no images (empty shard)", path)
    img = a["image"]
    if img.ndim != 4 or img.shape[0] != n or img.shape[3] != 3 or img.shape[1] != img.shape[2]:
        raise ReflectmmError(f"wild-shard: image must have shape ({n},S,S,3), got {img.shape}", path)
    if img.dtype != np.uint8:
        if img.dtype.kind != "f":
            raise ReflectmmError(f"wild-shard: image must be uint8, got {img.dtype}", path)
        bad = ~np.isfinite(np.asarray(img))
        if bad.any():
            i = int(np.flatnonzero(bad.reshape(n, -1).any(1))[0])
            raise ReflectmmError(f"wild-shard: image {i} ({a['names'][i]}) contains NaN or inf", path)
    S = int(img.shape[1])
    for k in ("face_mask", "skin_mask"):
        if a[k].shape != (n, S, S):
            raise ReflectmmError(f"wild-shard: {k} must have shape ({n},{S},{S}), got {a[k].shape}", path)
    off = np.asarray(a["pix_offset"], np.int64)
    P = int(a["vert_ids"].shape[0])
    if off.shape != (n + 1,) or off[0] != 0 or off[-1] != P or np.any(np.diff(off) < 0):
        raise ReflectmmError(f"wild-shard: pix_offset must be ({n + 1},) non-decreasing from 0 to P = {P}", path)
    if P == 0:
        raise ReflectmmError("wild-shard has no face pixels (empty G-buffer)", path)
    for k, c in (("pix_yx", 2), ("vert_ids", 3), ("bary", 3), ("normal", 3), ("view", 3)):
        if a[k].shape != (P, c):
            raise ReflectmmError(f"wild-shard: {k} must have shape ({P},{c}), got {a[k].shape}", path)
        if a[k].dtype.kind == "f" and not np.isfinite(a[k]).all():
            raise ReflectmmError(f"wild-shard: {k} contains NaN or inf", path)
    yx = np.asarray(a["pix_yx"])
    if yx.size and (int(yx.min()) < 0 or int(yx.max()) >= S):
        raise ReflectmmError(f"wild-shard: pix_yx holds pixel index {int(yx.min()) if int(yx.min()) < 0 else int(yx.max())}"
                             f" outside the {S}x{S} image", path)
    vid = np.asarray(a["vert_ids"])
    if vid.size and int(vid.min()) < 0:
        raise ReflectmmError(f"wild-shard: vert_ids holds a negative vertex id ({int(vid.min())})", path)
    for k in ("K", "R", "t", "landmarks", "shape", "expression"):
        if k in a and np.asarray(a[k]).dtype.kind == "f" and not np.isfinite(np.asarray(a[k])).all():
            i = int(np.flatnonzero(~np.isfinite(np.asarray(a[k])).reshape(n, -1).all(1))[0]) \
                if np.asarray(a[k]).shape[:1] == (n,) else 0
            raise ReflectmmError(f"wild-shard: {k} of image {i} ({a['names'][i]}) contains NaN or inf", path)
    enc = str(meta.get("encoding", "gamma1.2"))
    if enc not in ENCODINGS:
        raise ReflectmmError(f"wild-shard: unknown encoding {enc!r} (expected one of {', '.join(ENCODINGS)})", path)
    return n, S, enc


def iter_batches(shards, batch_size: int, *, split: str | None = "train", shuffle: bool = True, seed: int = 0,
                 epoch: int = 0, drop_last: bool = False, with_target: bool = False):
    """Epoch iterator over the images of ``split`` (None: all) through :meth:`ShardSet.batch` — the reader training
    and ``reconstruct`` use (torch-free, numpy out).

    ``shards``: a :class:`ShardSet` or shard paths (opened with :func:`load_shards`). Each batch is
    :meth:`ShardSet.batch`'s dict plus ``index`` (B,) — the images' indices in the set, ascending within a batch
    (sequential reads) — and their ``names`` and ``split``. Order: a permutation from ``seed`` and ``epoch`` when
    ``shuffle``; deterministic.
    """
    if batch_size < 1:
        raise ReflectmmError(f"batch size must be ≥ 1, got {batch_size}")
    ss = shards if isinstance(shards, ShardSet) else load_shards(shards)
    sel = np.arange(len(ss)) if split is None else ss.indices(split)
    if shuffle:
        sel = sel[np.random.default_rng([int(seed), int(epoch)]).permutation(len(sel))]
    for b0 in range(0, len(sel), batch_size):
        idx = np.sort(sel[b0:b0 + batch_size])
        if drop_last and len(idx) < batch_size:
            break
        out = ss.batch(idx, with_target=with_target)
        out.update(index=idx, names=ss.names[idx], split=ss.split[idx])
        yield out


def load_shards(paths: Sequence[str | Path]) -> ShardSet:
    """Open and concatenate ``wild-shard`` artifacts (all of one image size and SH order), memory-mapped.

    Raises :class:`ReflectmmError` (one line naming the file) on a wrong kind, an empty shard, missing or
    mis-shaped arrays, NaN/inf in images or G-buffers, or shards that disagree in image size.
    """
    if not paths:
        raise ReflectmmError("finetune: no data shards given (--data)")
    shards: list[tuple[Shard, int, str]] = []
    S0 = order0 = fm = None
    for p in paths:
        sh = open_shard(p)
        n, S, enc = _check(Path(p), sh, sh.meta)
        order = int(sh.meta.get("sh_order", 8))
        if S0 is None:
            S0, order0 = S, order
            ref = sh.meta.get("face_model")
            if ref:
                fm = dict(ref) if isinstance(ref, dict) else {"path": str(ref)}
                if fm.get("path"):
                    fm["resolved"] = str((Path(p).parent / fm["path"]).resolve())
        elif S != S0:
            raise ReflectmmError(f"wild-shard: image size {S} differs from {S0} of {paths[0]}", p)
        shards.append((sh, n, enc))
    arrays = {k: [s[k] for s, _, _ in shards] for k in _PER_IMAGE + _PER_PIXEL}
    if all("landmarks" in s for s, _, _ in shards):
        arrays["landmarks"] = [s["landmarks"] for s, _, _ in shards]
    truth_keys = set.intersection(*[{k for k in s.names if k.startswith("truth_")} for s, _, _ in shards])
    truth = {k: [s[k] for s, _, _ in shards] for k in sorted(truth_keys)}
    offsets = [np.asarray(s["pix_offset"], np.int64) for s, _, _ in shards]
    return _assemble(arrays, offsets, [enc for _, _, enc in shards], S0, order0, truth,
                     sources=[Path(p) for p in paths], face_model=fm)


def _assemble(arrays, offsets, encodings, size, order, truth, *, sources, face_model) -> ShardSet:
    base, offs = 0, []
    for o in offsets:
        offs.append(o[:-1] + base)
        base += int(o[-1])
    offs.append(np.array([base], np.int64))
    small = {k: np.concatenate([np.asarray(x) for x in arrays[k]]).astype(str) for k in ("names", "split")}
    enc = np.concatenate([np.full(len(o) - 1, e) for o, e in zip(offsets, encodings)])
    big = {k: _stack(arrays[k]) for k in ("image", "face_mask", "skin_mask") + _PER_PIXEL}
    lms = _stack(arrays["landmarks"]) if "landmarks" in arrays else None
    return ShardSet(**small, **big, pix_offset=np.concatenate(offs), encoding=enc, size=int(size), sh_order=int(order),
                    truth={k: _stack(v) for k, v in truth.items()}, sources=list(sources), face_model=face_model,
                    landmarks=lms)


def shardset_from_arrays(arrays: Mapping[str, np.ndarray], *, encoding: str, sh_order: int = 8,
                         face_model: dict | None = None) -> ShardSet:
    """A :class:`ShardSet` over in-memory shard arrays (the dict :func:`reflectmm_cli.finetune.data.
    prepare_wild_images` returns): what ``reconstruct --images`` reads instead of a shard file."""
    n, S, enc = _check(Path("<memory>"), arrays, {"encoding": encoding})
    a = {k: [np.asarray(arrays[k])] for k in _PER_IMAGE + _PER_PIXEL + ("landmarks",) if k in arrays}
    truth = {k: [np.asarray(v)] for k, v in arrays.items() if k.startswith("truth_")}
    return _assemble(a, [np.asarray(arrays["pix_offset"], np.int64)], [enc], S, sh_order, truth, sources=[],
                     face_model=face_model)
