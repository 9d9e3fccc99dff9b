"""The in-the-wild shard dataset (kind ``wild-shard``, schema ``reflectmm.wild-shard/1``; docs/wild.md).

One uncompressed NPZ per shard of N aligned S×S images; its arrays (all documented in docs/wild.md):
``names``, ``split``, ``image`` (N,S,S,3) uint8, ``face_mask``/``skin_mask`` (N,S,S) bool, ``landmarks``
(N,68,2) float32, the packed G-buffer (``pix_offset`` (N+1,) int64, ``pix_yx``, ``vert_ids``, ``bary``,
``normal``, ``view``, ``reflect``, ``visible`` — see :mod:`reflectmm_cli.geometry.gbuffer`), the geometry
(``shape``, ``expression``, ``R``, ``t``, ``K``) and optional ``truth_*`` arrays on synthetic data.

* :func:`write_shard` — checks shapes/dtypes and writes with ``write_artifact(..., compress=False)``;
* :class:`Shard` / :func:`open_shard` — memory-maps every member through its zip offset (no copy, no
  decompression: pages are read on demand);
* batches for training, reconstruction and inspection are read by one reader,
  :class:`reflectmm_cli.finetune.shards.ShardSet` (``batch``, ``iter_batches``).
"""
from __future__ import annotations

import json
import logging
import os
import struct
import zipfile
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Mapping, Sequence

import numpy as np

from reflectmm_cli.artifacts import (CORRUPT_ERRORS, IMAGE_EXTENSIONS, META_KEY, check_schema, read_image_u8,
                                     write_artifact)
from reflectmm_cli.color import gamma_to_linear, srgb_to_linear
from reflectmm_cli.errors import ArtifactError, ReflectmmError
from reflectmm_cli.geometry.gbuffer import GBUFFER_KEYS

__all__ = ["SHARD_KIND", "ENCODINGS", "SPLITS", "PER_IMAGE_KEYS", "write_shard", "Shard", "open_shard",
           "linearize", "PrepareConfig", "WildInput", "list_wild_inputs", "name_split",
           "prepare_wild_images", "prepare_wild_shard", "shard_names", "geometry_hash"]

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


def _linearize_codes(x: np.ndarray, encoding: str) -> np.ndarray:
    if encoding == "gamma1.2":
        return gamma_to_linear(x, np.float32(1.2))
    if encoding == "srgb":
        return srgb_to_linear(x).astype(np.float32)
    if encoding == "linear":
        return x
    raise ReflectmmError(f"unknown image encoding {encoding!r} (one of {', '.join(ENCODINGS)})")


_LUT: dict[str, np.ndarray] = {}


def linearize(image_u8: np.ndarray, encoding: str) -> np.ndarray:
    """uint8 codes → linear float32 in [0, 1]: gamma1.2 ``x^1.2``, srgb the sRGB EOTF, linear ``x``.

    uint8 input goes through a 256-entry table of the same formula (one gather instead of a ``pow`` per
    value: the training reader linearises every batch's images); other dtypes are taken as codes 0–255."""
    a = np.asarray(image_u8)
    if a.dtype == np.uint8:
        lut = _LUT.get(encoding)
        if lut is None:
            lut = _LUT[encoding] = _linearize_codes(np.arange(256, dtype=np.float32) / 255.0, encoding)
        return lut[a]
    return _linearize_codes(np.asarray(a, np.float32) / 255.0, encoding)


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


def _npy_memmap(path: Path, offset: int, size: int | None = None) -> np.ndarray:
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
    nbytes = int(np.prod(shape, dtype=object)) * dtype.itemsize
    if size is not None and data_off - offset + nbytes > size:
        raise ArtifactError(f"corrupt wild-shard: an array header claims {nbytes} bytes, its member holds "
                            f"{size - (data_off - offset)}", path)
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
        try:
            self._open()
        except CORRUPT_ERRORS as exc:
            raise ArtifactError(f"truncated or corrupt wild-shard ({type(exc).__name__}: "
                                f"{(str(exc).splitlines() or [''])[0]})", self.path) from None

    def _open(self) -> None:
        if not self.path.is_file():
            raise ArtifactError("shard file not found", self.path)
        if not zipfile.is_zipfile(self.path):
            raise ArtifactError("not an NPZ artifact (not a zip archive)", self.path)
        with zipfile.ZipFile(self.path) as zf:  # the kind first: another artifact is named as such
            if META_KEY + ".npy" not in zf.namelist():
                raise ArtifactError("not a reflectmm artifact (no __meta__ entry)", self.path)
            with zf.open(META_KEY + ".npy") as f:
                self.meta = json.loads(str(np.lib.format.read_array(f, allow_pickle=False).reshape(-1)[0]))
        check_schema(self.meta, SHARD_KIND, self.path)
        self._offsets = _member_offsets(self.path)
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
            off, size = self._offsets[name]
            try:
                self._cache[name] = _npy_memmap(self.path, off, size)
            except CORRUPT_ERRORS as exc:
                raise ArtifactError(f"corrupt wild-shard array '{name}' ({type(exc).__name__}: "
                                    f"{(str(exc).splitlines() or [''])[0]})", self.path) from None
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


# --------------------------------------------------------------------------- prepare-wild

_LM_EXT = (".pts", ".txt", ".npy")


@dataclass
class PrepareConfig:
    """Parameters of ``prepare-wild`` (recorded in the shard meta).

    The defaults here are the only ones: the ``prepare-wild`` stage (reflectmm_cli/stages/prepare_wild.py)
    declares its params with them and adds the ranges and choices that the command line and recipes validate."""

    size: int = 224
    aligned: bool = False           # images are already aligned S×S crops (landmarks in crop pixels)
    from_truth: bool = False        # geometry from synth-wild truth (implies aligned)
    encoding: str = "srgb"          # encoding of real images (synth wild records its own)
    shard_size: int = 256
    split_fractions: tuple = (0.9, 0.05, 0.05)   # by name hash, when no synth-wild manifest gives the split
    fit_landmark_iters: int = 200
    fit_photo_rounds: int = 1
    fit_photo_iters: int = 30

    def __post_init__(self) -> None:
        self.split_fractions = tuple(float(x) for x in self.split_fractions)

    def to_params(self) -> dict:
        d = dict(self.__dict__)
        d["split_fractions"] = list(self.split_fractions)
        return d


@dataclass
class WildInput:
    name: str
    image: Path
    landmarks: Path | None = None
    mask: Path | None = None


def list_wild_inputs(images_dir: str | Path, landmarks_dir: str | Path | None = None,
                     masks_dir: str | Path | None = None) -> list[WildInput]:
    """Images of a folder (sorted by name) paired with ``<landmarks_dir>/<stem>.pts|.txt|.npy`` (default: the
    images folder, then a sibling ``landmarks/``) and ``<masks_dir>/<stem>.png`` label images.  Missing
    partners are left None (reported per image later)."""
    images_dir = Path(images_dir)
    if not images_dir.is_dir():
        raise ReflectmmError("images folder not found", images_dir)
    files = sorted(p for p in images_dir.iterdir() if p.suffix.lower() in IMAGE_EXTENSIONS and p.is_file())
    if not files:
        raise ReflectmmError("no images (png/jpg/bmp/tif/webp) in folder", images_dir)
    other = sorted(p.name for p in images_dir.iterdir() if p.is_file() and not p.name.startswith(".")
                   and p.suffix.lower() not in IMAGE_EXTENSIONS + tuple(_LM_EXT))
    if other:
        logging.getLogger("reflectmm").warning(
            "%s: %d file(s) of another type left out (images are png/jpg/bmp/tif/webp): %s", images_dir, len(other),
            ", ".join(other[:5]) + (", …" if len(other) > 5 else ""))
    lm_dirs = [Path(landmarks_dir)] if landmarks_dir else [images_dir, images_dir.parent / "landmarks"]
    out = []
    for f in files:
        lm = next((d / (f.stem + e) for d in lm_dirs for e in _LM_EXT if (d / (f.stem + e)).is_file()), None)
        mk = None
        if masks_dir:
            mk = next((Path(masks_dir) / (f.stem + e) for e in (".png", ".bmp", ".tif")
                       if (Path(masks_dir) / (f.stem + e)).is_file()), None)
        out.append(WildInput(f.stem, f, lm, mk))
    return out


def name_split(name: str, fractions=(0.9, 0.05, 0.05)) -> str:
    """Deterministic split of an image id by the sha256 of its name (FFHQ-like data: one image per person)."""
    import hashlib

    u = int.from_bytes(hashlib.sha256(name.encode()).digest()[:8], "big") / 2.0 ** 64
    f = np.cumsum(np.asarray(fractions, np.float64) / sum(fractions))
    return SPLITS[int(np.searchsorted(f, u, side="right"))] if u < f[-1] else SPLITS[-1]


def check_truth_mesh(truth_dir: Path, face_model, face_model_path=None) -> None:
    """``--from-truth`` applies the truth's coefficients to ``face_model`` and stores the truth's per-vertex
    reflectance beside them: both must be of one mesh.  One line naming the face model when the synth-wild
    identities have another vertex count."""
    from reflectmm_cli.artifacts import read_artifact

    first = next(iter(sorted((truth_dir / "identities").glob("id*.npz"))), None)
    if first is None:
        return  # the per-image reads name the missing files
    n_truth = int(read_artifact(first, "wild-truth", members=("vertex_albedo",))["vertex_albedo"].shape[0])
    n = int(np.asarray(face_model.mean_shape).shape[0])
    if n != n_truth:
        raise ReflectmmError(f"has {n} vertices, the synth-wild truth {n_truth} ({first}): --from-truth needs the "
                             "face model the truth was made with", face_model_path)


def _truth_for(truth_dir: Path, name: str):
    from reflectmm_cli.artifacts import read_artifact

    p = truth_dir / "truth" / f"{name}.npz"
    if not p.is_file():
        raise ReflectmmError("no synth-wild truth for this image", p)
    return read_artifact(p, "wild-truth")


def _truth_at_size(a: np.ndarray, size: int, interpolation: str = "linear") -> np.ndarray:
    """A synth-wild truth image (H,H[,C]) at the crop size S (the pixel-centre rescale of ``--from-truth``)."""
    from .align import warp_to_crop

    h = int(a.shape[0])
    if h == size:
        return a
    k = size / h
    A = np.array([[k, 0, (k - 1) / 2], [0, k, (k - 1) / 2]])
    return warp_to_crop(a, A, size, interpolation=interpolation)


def _landmarks_in_frame(inp: WildInput, img: np.ndarray, tr) -> np.ndarray:
    """The image's landmarks, refused when far outside its frame; with a synth-wild truth ``tr`` of another
    size than the image, the message says so (the image was resized after synth wild wrote it and its landmarks)."""
    from reflectmm_cli.landmarks import check_in_frame, read_landmarks

    h, w = img.shape[:2]
    try:
        return check_in_frame(read_landmarks(inp.landmarks), w, h, inp.landmarks)
    except ReflectmmError as exc:
        size = tuple(np.shape(tr["face_mask"])) if tr is not None and "face_mask" in tr.arrays else None
        if size is None or size == (h, w):
            raise
        raise ReflectmmError(f"image is {w}x{h}, but its synth-wild truth is {size[1]}x{size[0]} and its landmarks "
                             f"fall outside this frame: was the image resized after synth wild wrote it?",
                             inp.image) from exc


def _aligned_crop(inp: WildInput, img: np.ndarray, lm: np.ndarray, face_model, cfg: PrepareConfig, S: int
                  ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The S×S crop of an image, its landmarks in crop pixels and the 2×3 image → crop transform.

    ``--aligned`` / ``--from-truth`` images are square crops already, only rescaled (pixel-centre convention);
    others are aligned by their landmarks to the face model's."""
    from reflectmm_cli.finetune.align import align_image, warp_to_crop

    if cfg.aligned or cfg.from_truth:
        if img.shape[0] != img.shape[1]:
            raise ReflectmmError(f"--aligned image is {img.shape[1]}x{img.shape[0]}, not square", inp.image)
        k = S / img.shape[0]
        A = np.array([[k, 0, (k - 1) / 2], [0, k, (k - 1) / 2]])    # pixel-centre rescale
        crop = img if k == 1 else np.clip(np.round(warp_to_crop(img, A, S)), 0, 255).astype(np.uint8)
        lm_c = lm * k + (k - 1) / 2
    else:
        al = align_image(img, lm, face_model, S)
        crop, lm_c, A = al.image, al.landmarks, al.transform
    if not np.isfinite(lm_c).all():
        raise ReflectmmError("landmarks are not finite", inp.landmarks)
    return crop, lm_c, A


def _image_geometry(face_model, cfg: PrepareConfig, tr, lm_c: np.ndarray, lin: np.ndarray, K_crop: np.ndarray,
                    S: int) -> tuple[np.ndarray, ...]:
    """``(shape, expression, R, t, K)`` of one crop: the synth-wild truth rescaled to S (``--from-truth``), or
    fitted to the crop's landmarks (and photometric rounds, when asked)."""
    if cfg.from_truth:
        K0 = np.asarray(tr["K"], np.float64)
        kk = S / int(tr["face_mask"].shape[0])
        K = K0.copy()
        K[0, 0], K[1, 1] = K0[0, 0] * kk, K0[1, 1] * kk
        K[:2, 2] = (K0[:2, 2] + 0.5) * kk - 0.5       # pixel-centre convention (Camera.with_size)
        return (np.asarray(tr["shape"], np.float64), np.asarray(tr["expression"], np.float64),
                np.asarray(tr["R"], np.float64), np.asarray(tr["t"], np.float64), K)
    from reflectmm_cli.finetune.align import fit_single_image
    from reflectmm_cli.geometry_fit.fit import FitConfig

    fc = FitConfig(landmark_iters=cfg.fit_landmark_iters, photo_rounds=cfg.fit_photo_rounds,
                   photo_iters=cfg.fit_photo_iters, photo_blur_px=(1.0,), photo_vertices=1500)
    fit = fit_single_image(face_model, lm_c, lin if cfg.fit_photo_rounds > 0 else None, K_crop, config=fc, size=S)
    return fit.shape_coeffs, fit.exp_coeffs, fit.R[0], fit.t[0], K_crop


def _skin_mask(inp: WildInput, A: np.ndarray, gb: Mapping[str, np.ndarray], face_model, cfg: PrepareConfig, tr,
               lin: np.ndarray, S: int) -> np.ndarray:
    """Skin pixels of the crop that the fitted face covers: from a label image when one is given, from the
    synth-wild truth with ``--from-truth``, else the model's skin region where the crop's colour is skin-like."""
    from reflectmm_cli.finetune.align import skin_mask_from_labels, skin_mask_from_model, warp_to_crop

    vis_px = np.zeros((S, S), bool)
    yx = gb["pix_yx"][gb["visible"]].astype(np.int64)
    vis_px[yx[:, 0], yx[:, 1]] = True
    if inp.mask is not None:
        lab_c = warp_to_crop(read_image_u8(inp.mask)[..., 0], A, S, interpolation="nearest")
        return skin_mask_from_labels(lab_c) & vis_px
    if tr is not None and cfg.from_truth:
        return _truth_at_size(np.asarray(tr["skin_mask"], np.uint8), S, "nearest").astype(bool) & vis_px
    return skin_mask_from_model(gb, face_model.skin_mask, lin) & vis_px


def _vertex_errors(face_model, tr, verts: np.ndarray, R: np.ndarray, t: np.ndarray) -> tuple[float, float]:
    """RMS distance (mm) of the fitted vertices to the true ones in camera space, and the same after removing
    each set's centroid."""
    vt = face_model.vertices(tr["shape"], tr["expression"]).astype(np.float64)
    cam_t = vt @ np.asarray(tr["R"]).T + np.asarray(tr["t"])
    cam_f = verts @ R.T + t
    d = (cam_f - cam_f.mean(0)) - (cam_t - cam_t.mean(0))
    return (float(np.sqrt(np.mean(np.sum((cam_f - cam_t) ** 2, -1)))),
            float(np.sqrt(np.mean(np.sum(d * d, -1)))))


def _truth_arrays(tr, identity_truth, S: int) -> dict[str, np.ndarray]:
    """The ``truth_*`` shard arrays of one image: its light, its identity's per-vertex reflectance and its true
    diffuse and specular images at the crop size."""
    ia = identity_truth
    return {"truth_sh": np.asarray(tr["sh"], np.float32),
            "truth_vertex_albedo": np.asarray(ia["vertex_albedo"], np.float16),
            "truth_vertex_weights": np.asarray(ia["vertex_weights"], np.float16),
            "truth_vertex_spec_albedo": np.asarray(ia["vertex_spec_albedo"], np.float16),
            "truth_vertex_roughness": np.asarray(ia["vertex_roughness"], np.float16),
            "truth_diffuse": _truth_at_size(np.asarray(tr["diffuse"], np.float32), S).astype(np.float16),
            "truth_specular": _truth_at_size(np.asarray(tr["specular"], np.float32), S).astype(np.float16)}


#: A 68-point face spans at least this many pixels both ways (a detector's smallest faces span about 40).
MIN_LANDMARK_SPAN_PX = 4.0
#: A fitted face covers at least this fraction of its aligned crop (about a third in the Deep3DFaceRecon crop).
MIN_FACE_FRACTION = 0.02


def prepare_wild_images(inputs: Sequence[WildInput], face_model, cfg: PrepareConfig, *,
                        truth_dir: str | Path | None = None, splits: Mapping[str, str] | None = None,
                        progress_fn=None) -> tuple[dict[str, np.ndarray], dict, list[str]]:
    """Align, fit (or read) geometry, rasterise the G-buffer and build the skin mask of each input.

    Returns ``(arrays, report, errors)``: the shard arrays of the images that succeeded (see
    :func:`write_shard`), a report {per-image landmark RMSE (px), vertex error (mm, when truth exists),
    seconds}, and one-line error messages (each naming its file) for the images that were skipped.
    """
    import time

    from reflectmm_cli.geometry import RayScene, deep3d_camera
    from reflectmm_cli.geometry.camera import Camera
    from reflectmm_cli.geometry.gbuffer import gbuffer_from_raster, pack_gbuffers
    from reflectmm_cli.geometry.raycast import rasterize

    S = int(cfg.size)
    K_crop = deep3d_camera().with_size(S, S).K
    truth_dir = Path(truth_dir) if truth_dir is not None else None
    if cfg.from_truth and truth_dir is None:
        raise ReflectmmError("--from-truth needs the synth-wild folder (its truth/ sub-folder)")
    per: dict[str, list] = {k: [] for k in ("names", "split", "image", "skin_mask", "landmarks", "shape",
                                             "expression", "R", "t", "K")}
    truth: dict[str, list] = {}
    gbs, errors = [], []
    rep = {"names": [], "landmark_rmse_px": [], "vertex_error_mm": [], "seconds": []}
    id_cache: dict[int, Any] = {}
    it = progress_fn(inputs) if progress_fn else inputs
    for inp in it:
        t0 = time.perf_counter()
        try:
            if inp.landmarks is None:
                raise ReflectmmError("no landmark file with the same name (.pts/.txt/.npy)", inp.image)
            img = read_image_u8(inp.image)
            if not img.any():
                raise ReflectmmError("image is all black (nothing to reconstruct)", inp.image)
            if (img == 255).all():
                raise ReflectmmError("image is all white (saturated: nothing to reconstruct)", inp.image)
            tr = _truth_for(truth_dir, inp.name) if truth_dir is not None else None
            lm = _landmarks_in_frame(inp, img, tr)
            span = np.nanmax(lm, 0) - np.nanmin(lm, 0)
            if not (span >= MIN_LANDMARK_SPAN_PX).all():
                raise ReflectmmError(f"landmarks span {span[0]:.3g} x {span[1]:.3g} px: no face (they collapse to a "
                                     "point or a line)", inp.landmarks)
            encoding = tr.meta.get("encoding", cfg.encoding) if tr is not None else cfg.encoding
            crop, lm_c, A = _aligned_crop(inp, img, lm, face_model, cfg, S)
            lin = linearize(crop, encoding)
            shape, exp, R, t, K = _image_geometry(face_model, cfg, tr, lm_c, lin, K_crop, S)
            verts = face_model.vertices(shape, exp).astype(np.float64)
            cam = Camera(K, R, t, S, S, inp.name)
            gb = gbuffer_from_raster(rasterize(RayScene(verts, face_model.triangles), cam), face_model.triangles,
                                     cam)
            covered = int(np.asarray(gb["face_mask"]).sum())
            if covered < MIN_FACE_FRACTION * S * S:
                raise ReflectmmError(f"the fitted face covers {covered} pixel(s) of the {S}x{S} crop: a failed fit "
                                     "(landmarks of another image, or of no face)", inp.image)
            proj, _ = cam.project(verts[face_model.landmarks])
            rep_lm = float(np.sqrt(np.mean(np.sum((proj - lm_c) ** 2, -1))))
            skin = _skin_mask(inp, A, gb, face_model, cfg, tr, lin, S)
            verr, verr_centred, truth_row = float("nan"), None, None
            if tr is not None:
                verr, verr_centred = _vertex_errors(face_model, tr, verts, R, t)
                if cfg.from_truth:
                    ident = int(tr.meta["identity"])
                    if ident not in id_cache:
                        from reflectmm_cli.artifacts import read_artifact

                        id_cache.clear()
                        id_cache[ident] = read_artifact(truth_dir / "identities" / f"id{ident:05d}.npz", "wild-truth")
                    truth_row = _truth_arrays(tr, id_cache[ident], S)
        except ReflectmmError as exc:
            errors.append(str(exc).splitlines()[0])
            continue
        per["names"].append(inp.name)
        per["split"].append((splits or {}).get(inp.name) or name_split(inp.name, cfg.split_fractions))
        per["image"].append(crop)
        per["skin_mask"].append(skin & gb["face_mask"])
        per["landmarks"].append(np.asarray(lm_c, np.float32))
        per["shape"].append(np.asarray(shape, np.float32))
        per["expression"].append(np.asarray(exp, np.float32))
        per["R"].append(R), per["t"].append(t), per["K"].append(K)
        gbs.append(gb)
        for k_, v_ in (truth_row or {}).items():
            truth.setdefault(k_, []).append(v_)
        rep["names"].append(inp.name)
        rep["landmark_rmse_px"].append(rep_lm)
        rep["vertex_error_mm"].append(verr)
        if verr_centred is not None:
            rep.setdefault("vertex_error_centred_mm", []).append(verr_centred)
        rep["seconds"].append(time.perf_counter() - t0)
    arrays: dict[str, np.ndarray] = {}
    if gbs:
        arrays = {k: np.array(v) if k in ("names", "split") else np.stack(v) for k, v in per.items()}
        arrays["shape"] = arrays["shape"].astype(np.float32)
        arrays["expression"] = arrays["expression"].astype(np.float32)
        arrays.update(pack_gbuffers(gbs))
        arrays.update({k: np.stack(v) for k, v in truth.items()})
    return arrays, rep, errors


def geometry_hash(arrays: Mapping[str, np.ndarray], face_model_sha256: str) -> str:
    """sha256 of what the G-buffers depend on: the face model's hash, image size and each image's
    (shape, expression, R, t, K) — equal hashes mean identical G-buffers."""
    import hashlib

    h = hashlib.sha256(face_model_sha256.encode())
    h.update(str(int(np.asarray(arrays["image"]).shape[1])).encode())
    for k in ("shape", "expression", "R", "t", "K"):
        h.update(np.ascontiguousarray(arrays[k]).tobytes())
    return h.hexdigest()


def shard_names(n_images: int, shard_size: int) -> list[str]:
    return [f"shard_{i:05d}" for i in range(-(-n_images // max(1, shard_size)))]


def prepare_wild_shard(images_dir, out_dir, face_model, face_model_path, cfg: PrepareConfig, shard_index: int, *,
                       landmarks_dir=None, masks_dir=None, truth_dir=None, producer=None, cache_key=None,
                       progress_fn=None, key_when_skipped: bool = True) -> tuple[Path | None, dict, list[str]]:
    """One shard of ``prepare-wild``: images ``[i·M, (i+1)·M)`` of the sorted folder → ``out_dir/shard_NNNNN.npz``
    plus ``shard_NNNNN_overlay.png`` (skin masks over the first 16 crops).  Returns (path or None, report,
    errors).  ``truth_dir`` (a synth-wild folder) supplies the split, truth arrays and vertex errors.

    ``key_when_skipped=False``: a shard with skipped images is written without ``cache_key``, so a recipe does not
    call it up to date and the next run tries (and reports) the skipped images again."""
    from reflectmm_cli.artifacts import input_ref, read_artifact, sha256_file, write_png
    from reflectmm_cli.finetune.align import mask_overlay

    inputs = list_wild_inputs(images_dir, landmarks_dir, masks_dir)
    M = int(cfg.shard_size)
    chunk = inputs[shard_index * M:(shard_index + 1) * M]
    if not chunk:
        raise ReflectmmError(f"shard {shard_index} is empty ({len(inputs)} images, {M} per shard)", images_dir)
    if cfg.from_truth and truth_dir is not None:
        check_truth_mesh(Path(truth_dir), face_model, face_model_path)
    splits = None
    if truth_dir is not None and (Path(truth_dir) / "manifest.npz").is_file():
        man = read_artifact(Path(truth_dir) / "manifest.npz", "wild-manifest")
        splits = dict(zip(man["names"].tolist(), man["split"].tolist()))
    arrays, rep, errors = prepare_wild_images(chunk, face_model, cfg, truth_dir=truth_dir, splits=splits,
                                              progress_fn=progress_fn)
    out_dir = Path(out_dir)
    path = out_dir / f"{shard_names(len(inputs), M)[shard_index]}.npz"
    if not arrays:
        return None, rep, errors
    fm = Path(face_model_path)
    rel = os.path.relpath(fm.resolve(), out_dir.resolve())
    write_shard(path, arrays, encoding=str(_encoding_of(cfg, truth_dir)), face_model_sha256=sha256_file(fm),
                face_model_path=rel, params=cfg.to_params(), inputs=[input_ref("face_model", fm, out_dir)],
                producer=producer, cache_key=cache_key if (key_when_skipped or not errors) else None,
                extra_meta={"shard_index": shard_index, "skipped": errors,
                            "geometry_sha256": geometry_hash(arrays, sha256_file(fm)),
                            "landmark_rmse_px_median": float(np.median(rep["landmark_rmse_px"])),
                            "skin_labels": "CelebAMask-HQ ids 1 skin, 2 nose, 11 upper lip, 12 lower lip"
                            if masks_dir else None})
    n = min(16, len(arrays["names"]))
    tiles = [mask_overlay(arrays["image"][i], arrays["skin_mask"][i]) for i in range(n)]
    cols = min(4, n)
    rows = -(-n // cols)
    S = arrays["image"].shape[1]
    sheet = np.zeros((rows * S, cols * S, 3), np.uint8)
    for i, tl in enumerate(tiles):
        r, c = divmod(i, cols)
        sheet[r * S:(r + 1) * S, c * S:(c + 1) * S] = tl
    write_png(out_dir / f"{path.stem}_overlay.png", sheet)
    return path, rep, errors


def _encoding_of(cfg: PrepareConfig, truth_dir) -> str:
    if truth_dir is not None and (Path(truth_dir) / "manifest.npz").is_file():
        from reflectmm_cli.artifacts import read_meta

        return read_meta(Path(truth_dir) / "manifest.npz").get("encoding", cfg.encoding)
    return cfg.encoding
