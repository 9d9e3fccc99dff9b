"""The in-the-wild shard dataset (kind ``wild-shard``, schema ``reflectmm.wild-shard/1``; docs/wild.md).

One uncompressed NPZ per shard of N aligned S×S images; its arrays (all documented in docs/wild.md):
``names``, ``split``, ``image`` (N,S,S,3) uint8, ``face_mask``/``skin_mask`` (N,S,S) bool, ``landmarks``
(N,68,2) float32, the packed G-buffer (``pix_offset`` (N+1,) int64, ``pix_yx``, ``vert_ids``, ``bary``,
``normal``, ``view``, ``reflect``, ``visible`` — see :mod:`reflectmm_cli.geometry.gbuffer`), the geometry
(``shape``, ``expression``, ``R``, ``t``, ``K``) and optional ``truth_*`` arrays on synthetic data.

* :func:`write_shard` — checks shapes/dtypes and writes with ``write_artifact(..., compress=False)``;
* :class:`Shard` / :func:`open_shard` — memory-maps every member through its zip offset (no copy, no
  decompression: pages are read on demand);
* :func:`iter_batches` — a torch-free batch iterator over one or more shards returning numpy arrays.
"""
from __future__ import annotations

import json
import struct
import zipfile
from pathlib import Path
from typing import Any, Iterator, Mapping, Sequence

import numpy as np

from reflectmm_cli.artifacts import META_KEY, check_schema, write_artifact
from reflectmm_cli.errors import ArtifactError, ReflectmmError
from reflectmm_cli.geometry.gbuffer import GBUFFER_KEYS

__all__ = ["SHARD_KIND", "ENCODINGS", "SPLITS", "PER_IMAGE_KEYS", "write_shard", "Shard", "open_shard",
           "iter_batches", "linearize"]

SHARD_KIND = "wild-shard"
ENCODINGS = ("gamma1.2", "srgb", "linear")
SPLITS = ("train", "val", "test")

# name → (dtype, shape after the leading N with S = image size; None = any)
_PER_IMAGE = {
    "image": (np.uint8, ("S", "S", 3)),
    "face_mask": (np.bool_, ("S", "S")),
    "skin_mask": (np.bool_, ("S", "S")),
    "landmarks": (np.float32, (68, 2)),
    "shape": (np.float32, (None,)),
    "expression": (np.float32, (None,)),
    "R": (np.float64, (3, 3)),
    "t": (np.float64, (3,)),
    "K": (np.float64, (3, 3)),
}
_PER_PIXEL = {
    "pix_yx": (np.int16, (2,)), "vert_ids": (np.int32, (3,)), "bary": (np.float32, (3,)),
    "normal": (np.float16, (3,)), "view": (np.float16, (3,)), "reflect": (np.float16, (3,)),
    "visible": (np.bool_, ()),
}
#: Arrays with one entry per image (the batch iterator slices these).
PER_IMAGE_KEYS = ("names", "split") + tuple(_PER_IMAGE)


def linearize(image_u8: np.ndarray, encoding: str) -> np.ndarray:
    """uint8 codes → linear float32 in [0, 1]: gamma1.2 ``x^1.2``, srgb the sRGB EOTF, linear ``x``."""
    x = np.asarray(image_u8, np.float32) / 255.0
    if encoding == "gamma1.2":
        return x ** np.float32(1.2)
    if encoding == "srgb":
        return np.where(x <= 0.04045, x / 12.92, ((x + 0.055) / 1.055) ** np.float32(2.4)).astype(np.float32)
    if encoding == "linear":
        return x
    raise ReflectmmError(f"unknown image encoding {encoding!r} (one of {', '.join(ENCODINGS)})")


def _check(path, name, arr, dtype, shape, n, S):
    if arr.dtype != dtype:
        raise ReflectmmError(f"shard array '{name}' must be {np.dtype(dtype).name}, got {arr.dtype}", path)
    want = [n] + [S if d == "S" else d for d in shape]
    if arr.ndim != len(want) or any(w is not None and w != g for w, g in zip(want, arr.shape)):
        raise ReflectmmError(f"shard array '{name}' has shape {arr.shape}, expected {tuple(want)}", path)


def write_shard(path: str | Path, arrays: Mapping[str, Any], *, encoding: str, face_model_sha256: str,
                face_model_path: str, params: Mapping[str, Any] | None = None, inputs: list | None = None,
                producer: Mapping[str, Any] | None = None, cache_key: str | None = None,
                extra_meta: Mapping[str, Any] | None = None) -> Path:
    """Validate and write one shard (uncompressed NPZ).  ``arrays`` holds every array of the format (see the
    module docstring) with the documented dtypes; ``truth_*`` arrays are passed through.  Meta records
    ``face_model`` {sha256, path (relative to the shard)}, ``image_size``, ``encoding`` and ``sh_order`` = 8.
    """
    path = Path(path)
    if encoding not in ENCODINGS:
        raise ReflectmmError(f"unknown image encoding {encoding!r} (one of {', '.join(ENCODINGS)})", path)
    a = {k: np.asarray(v) for k, v in arrays.items()}
    for k in ("names", "split", "pix_offset", *_PER_IMAGE, *_PER_PIXEL):
        if k not in a:
            raise ReflectmmError(f"shard is missing array '{k}'", path)
    n = len(a["names"])
    S = a["image"].shape[1] if a["image"].ndim == 4 else -1
    if a["names"].dtype.kind != "U" or a["split"].dtype.kind != "U" or a["split"].shape != (n,):
        raise ReflectmmError("shard arrays 'names' and 'split' must be (N,) unicode", path)
    bad = sorted(set(a["split"].tolist()) - set(SPLITS))
    if bad:
        raise ReflectmmError(f"shard split values {bad} are not train/val/test", path)
    for k, (dt, shp) in _PER_IMAGE.items():
        _check(path, k, a[k], dt, shp, n, S)
    off = a["pix_offset"]
    if off.dtype != np.int64 or off.shape != (n + 1,) or off[0] != 0 or np.any(np.diff(off) < 0):
        raise ReflectmmError("shard array 'pix_offset' must be (N+1,) int64, non-decreasing from 0", path)
    P = int(off[-1])
    for k, (dt, shp) in _PER_PIXEL.items():
        _check(path, k, a[k], dt, shp, P, S)
    counts = a["face_mask"].reshape(n, -1).sum(1)
    if not np.array_equal(counts, np.diff(off)):
        raise ReflectmmError("shard G-buffer rows do not match the face masks' pixel counts", path)
    if np.any(a["skin_mask"] & ~a["face_mask"]):
        raise ReflectmmError("shard skin_mask has pixels outside face_mask", path)
    meta = {"face_model": {"sha256": face_model_sha256, "path": face_model_path}, "image_size": int(S),
            "encoding": encoding, "sh_order": 8, "count": n}
    meta.update(extra_meta or {})
    return write_artifact(path, SHARD_KIND, a, params=params, inputs=inputs, producer=producer,
                          cache_key=cache_key, extra_meta=meta, compress=False)


def _member_offsets(path: Path) -> dict[str, tuple[int, int]]:
    """name → (offset of the member's data in the file, size) for the stored (uncompressed) zip members."""
    out = {}
    with zipfile.ZipFile(path) as zf, open(path, "rb") as f:
        for info in zf.infolist():
            if info.compress_type != zipfile.ZIP_STORED:
                raise ArtifactError(f"member {info.filename} is compressed; shards must be stored uncompressed "
                                    "to be memory-mapped", path)
            f.seek(info.header_offset)
            head = f.read(30)
            if head[:4] != b"PK\x03\x04":
                raise ArtifactError(f"corrupt zip local header of {info.filename}", path)
            name_len, extra_len = struct.unpack("<HH", head[26:30])
            out[info.filename[:-4] if info.filename.endswith(".npy") else info.filename] = (
                info.header_offset + 30 + name_len + extra_len, info.file_size)
    return out


def _npy_memmap(path: Path, offset: int) -> np.ndarray:
    with open(path, "rb") as f:
        f.seek(offset)
        version = np.lib.format.read_magic(f)
        if version == (1, 0):
            shape, fortran, dtype = np.lib.format.read_array_header_1_0(f)
        else:
            shape, fortran, dtype = np.lib.format.read_array_header_2_0(f)
        data_off = f.tell()
    if dtype.hasobject:
        raise ArtifactError("object arrays are not allowed in shards", path)
    if int(np.prod(shape)) == 0:
        return np.zeros(shape, dtype)
    return np.memmap(path, dtype=dtype, mode="r", offset=data_off, shape=shape, order="F" if fortran else "C")


class Shard:
    """A ``wild-shard`` file opened for reading; every array is a read-only ``np.memmap`` into the file.

    ``shard[name]`` → array; ``shard.meta`` → dict; ``len(shard)`` → N; ``shard.gbuffer(i)`` → the G-buffer
    rows of image i (views); ``shard.encoding``; ``shard.image_size``.
    """

    def __init__(self, path: str | Path):
        self.path = Path(path)
        if not self.path.is_file():
            raise ArtifactError("shard file not found", self.path)
        if not zipfile.is_zipfile(self.path):
            raise ArtifactError("not an NPZ artifact (not a zip archive)", self.path)
        self._offsets = _member_offsets(self.path)
        if META_KEY not in self._offsets:
            raise ArtifactError("not a reflectmm artifact (no __meta__ entry)", self.path)
        self.meta = json.loads(str(np.asarray(_npy_memmap(self.path, self._offsets[META_KEY][0])).reshape(-1)[0]))
        check_schema(self.meta, SHARD_KIND, self.path)
        self._cache: dict[str, np.ndarray] = {}

    @property
    def names(self) -> list[str]:
        return sorted(k for k in self._offsets if k != META_KEY)

    def __contains__(self, name: str) -> bool:
        return name in self._offsets and name != META_KEY

    def __getitem__(self, name: str) -> np.ndarray:
        if name not in self:
            raise ArtifactError(f"wild-shard has no array '{name}'", self.path)
        if name not in self._cache:
            self._cache[name] = _npy_memmap(self.path, self._offsets[name][0])
        return self._cache[name]

    def __len__(self) -> int:
        return int(self["pix_offset"].shape[0]) - 1

    @property
    def encoding(self) -> str:
        return str(self.meta.get("encoding", "linear"))

    @property
    def image_size(self) -> int:
        return int(self.meta.get("image_size", self["image"].shape[1]))

    def gbuffer(self, i: int) -> dict[str, np.ndarray]:
        off = self["pix_offset"]
        a, b = int(off[i]), int(off[i + 1])
        out = {k: self[k][a:b] for k in GBUFFER_KEYS}
        out["face_mask"] = self["face_mask"][i]
        return out


def open_shard(path: str | Path) -> Shard:
    """Open a ``wild-shard`` NPZ for memory-mapped reading."""
    return Shard(path)


def iter_batches(shards: Sequence[str | Path | Shard], batch_size: int, *, split: str | None = "train",
                 shuffle: bool = True, seed: int = 0, epoch: int = 0, drop_last: bool = False,
                 keys: Sequence[str] | None = None) -> Iterator[dict[str, np.ndarray]]:
    """Batches of images (numpy, no torch) over the images of ``split`` (None: all) in the given shards.

    Each batch dict has the per-image arrays (B, ...) — ``image`` uint8 as stored, ``skin_mask``, ``face_mask``,
    ``landmarks``, geometry, ``truth_*`` when present — plus the batch's G-buffer rows concatenated:
    ``pix_offset`` (B+1,) int64 (relative to the batch), ``pix_yx`` … ``visible`` (P_batch, ...), and
    ``shard_index``/``image_index`` (B,) int64.  ``keys`` restricts the per-image arrays read.
    Order: a permutation of (shard, image) pairs from ``seed`` and ``epoch`` when ``shuffle``; deterministic.
    Images in a batch are read shard by shard in increasing index order (sequential disk access).
    """
    if batch_size < 1:
        raise ReflectmmError(f"batch size must be ≥ 1, got {batch_size}")
    sh = [s if isinstance(s, Shard) else open_shard(s) for s in shards]
    items = []
    for si, s in enumerate(sh):
        sel = np.arange(len(s)) if split is None else np.flatnonzero(np.asarray(s["split"]) == split)
        items.extend((si, int(i)) for i in sel)
    order = np.arange(len(items))
    if shuffle:
        order = np.random.default_rng([int(seed), int(epoch)]).permutation(len(items))
    for b0 in range(0, len(order), batch_size):
        idx = order[b0:b0 + batch_size]
        if drop_last and len(idx) < batch_size:
            break
        pairs = sorted(items[k] for k in idx)
        yield _gather(sh, pairs, keys)


def _gather(sh: list[Shard], pairs: list[tuple[int, int]], keys) -> dict[str, np.ndarray]:
    out: dict[str, list] = {}
    gb: dict[str, list] = {k: [] for k in GBUFFER_KEYS}
    counts = []
    for si, i in pairs:
        s = sh[si]
        names = [k for k in s.names if k not in GBUFFER_KEYS and k != "pix_offset"
                 and (keys is None or k in keys or k in ("names", "split"))]
        for k in names:
            out.setdefault(k, []).append(np.asarray(s[k][i]))
        off = s["pix_offset"]
        a, b = int(off[i]), int(off[i + 1])
        for k in GBUFFER_KEYS:
            gb[k].append(np.asarray(s[k][a:b]))
        counts.append(b - a)
    batch = {k: np.stack(v) for k, v in out.items()}
    for k, v in gb.items():
        batch[k] = np.concatenate(v, 0)
    batch["pix_offset"] = np.concatenate([[0], np.cumsum(counts)]).astype(np.int64)
    batch["shard_index"] = np.array([p[0] for p in pairs], np.int64)
    batch["image_index"] = np.array([p[1] for p in pairs], np.int64)
    return batch
