"""Linear 3D morphable face models (the ``face-model`` artifact) and their loaders.

A :class:`FaceModel` holds a mean shape and linear shape / expression bases in model space
(millimetres, +y up, +z out of the face, +x to the subject's left; docs/pipeline.md)::

    vertices(α, δ) = mean_shape + Σ_k α_k · shape_basis[k] + Σ_k δ_k · exp_basis[k]

with the prior ``α_k ~ N(0, shape_sigma_k²)`` and ``δ_k ~ N(0, exp_sigma_k²)``: coefficients are *raw*
(in the units of the basis), sigma is their prior standard deviation.  Triangles are 0-based and wound
counter-clockwise seen from outside, so ``(v1 − v0) × (v2 − v0)`` points out of the face.

Loaders read the real BFM09 (``01_MorphableModel.mat`` + optional ``Exp_Pca.bin``) and Deep3DFaceRecon
(``BFM_model_front.mat``) layouts; see docs/geometry.md for the exact assumptions.
"""
from __future__ import annotations

import logging
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from reflectmm_cli.errors import ReflectmmError

log = logging.getLogger("reflectmm")

__all__ = ["FaceModel", "vertex_normals", "face_normals", "save_face_model", "load_face_model",
           "load_bfm09", "load_bfm_front", "face_model_from_artifact"]


@dataclass
class FaceModel:
    """A linear face model. Shapes: N vertices, T triangles, Ks/Ke/Kt basis sizes.

    Attributes:
        mean_shape: (N, 3) float32 mean vertex positions, mm, model space.
        shape_basis: (Ks, N, 3) float32 identity basis (raw; coefficient prior std is ``shape_sigma``).
        shape_sigma: (Ks,) float32 prior standard deviation of each identity coefficient.
        exp_basis: (Ke, N, 3) float32 expression basis.
        exp_sigma: (Ke,) float32 prior standard deviation of each expression coefficient.
        triangles: (T, 3) int32, 0-based, counter-clockwise seen from outside (outward normals).
        uv: (N, 2) float32 texture coordinates in [0, 1]; v = 0 is the top of the face; the layout is
            left-right symmetric (mirror u ↔ 1 − u) for the built-in model.
        landmarks: (68,) int32 vertex indices in iBUG order.
        skin_mask: (N,) bool, True on skin (False on eyes, nostril interiors, ...).
        mean_tex, tex_basis, tex_sigma: optional per-vertex colour model ((N,3), (Kt,N,3), (Kt,)), linear [0,1].
        name: a short description.
        mirror: optional (N,) int32 precomputed mirror map (vertex i ↔ mirror[i] under x → −x).
        info: free-form JSON-able provenance (units detected by a loader, UV distortion, ...).
    """

    mean_shape: np.ndarray
    shape_basis: np.ndarray
    shape_sigma: np.ndarray
    exp_basis: np.ndarray
    exp_sigma: np.ndarray
    triangles: np.ndarray
    uv: np.ndarray
    landmarks: np.ndarray
    skin_mask: np.ndarray
    mean_tex: np.ndarray | None = None
    tex_basis: np.ndarray | None = None
    tex_sigma: np.ndarray | None = None
    name: str = "face model"
    mirror: np.ndarray | None = None
    info: dict[str, Any] = field(default_factory=dict)

    def __post_init__(self) -> None:
        self.mean_shape = np.ascontiguousarray(self.mean_shape, dtype=np.float32)
        n = self.mean_shape.shape[0] if self.mean_shape.ndim == 2 else -1
        if self.mean_shape.ndim != 2 or self.mean_shape.shape[1] != 3:
            raise ReflectmmError(f"face model: mean_shape must be (N, 3), got {self.mean_shape.shape}")

        def basis(name, arr):
            arr = np.ascontiguousarray(np.zeros((0, n, 3)) if arr is None else arr, dtype=np.float32)
            if arr.ndim != 3 or arr.shape[1:] != (n, 3):
                raise ReflectmmError(f"face model: {name} must be (K, {n}, 3), got {arr.shape}")
            return arr

        def sigma(name, arr, k):
            arr = np.ascontiguousarray(np.ones(k) if arr is None else arr, dtype=np.float32).reshape(-1)
            if arr.shape != (k,):
                raise ReflectmmError(f"face model: {name} must be ({k},), got {arr.shape}")
            return arr

        self.shape_basis = basis("shape_basis", self.shape_basis)
        self.shape_sigma = sigma("shape_sigma", self.shape_sigma, self.shape_basis.shape[0])
        self.exp_basis = basis("exp_basis", self.exp_basis)
        self.exp_sigma = sigma("exp_sigma", self.exp_sigma, self.exp_basis.shape[0])
        self.triangles = np.ascontiguousarray(self.triangles, dtype=np.int32)
        if self.triangles.ndim != 2 or self.triangles.shape[1] != 3:
            raise ReflectmmError(f"face model: triangles must be (T, 3), got {self.triangles.shape}")
        if self.triangles.size and (self.triangles.min() < 0 or self.triangles.max() >= n):
            raise ReflectmmError(f"face model: triangle indices must be in [0, {n}), got "
                                 f"[{self.triangles.min()}, {self.triangles.max()}]")
        self.uv = np.ascontiguousarray(self.uv, dtype=np.float32)
        if self.uv.shape != (n, 2):
            raise ReflectmmError(f"face model: uv must be ({n}, 2), got {self.uv.shape}")
        self.landmarks = np.ascontiguousarray(self.landmarks, dtype=np.int32).reshape(-1)
        if self.landmarks.size and (self.landmarks.min() < 0 or self.landmarks.max() >= n):
            raise ReflectmmError(f"face model: landmark indices must be in [0, {n})")
        self.skin_mask = np.ascontiguousarray(self.skin_mask, dtype=bool).reshape(-1)
        if self.skin_mask.shape != (n,):
            raise ReflectmmError(f"face model: skin_mask must be ({n},), got {self.skin_mask.shape}")
        if self.mean_tex is not None:
            self.mean_tex = np.ascontiguousarray(self.mean_tex, dtype=np.float32)
            if self.mean_tex.shape != (n, 3):
                raise ReflectmmError(f"face model: mean_tex must be ({n}, 3), got {self.mean_tex.shape}")
            self.tex_basis = basis("tex_basis", self.tex_basis)
            self.tex_sigma = sigma("tex_sigma", self.tex_sigma, self.tex_basis.shape[0])
        if self.mirror is not None:
            self.mirror = np.ascontiguousarray(self.mirror, dtype=np.int32).reshape(-1)
            if self.mirror.shape != (n,):
                raise ReflectmmError(f"face model: mirror must be ({n},), got {self.mirror.shape}")
        for name in ("mean_shape", "uv", "shape_basis", "shape_sigma", "exp_basis", "exp_sigma", "mean_tex",
                     "tex_basis", "tex_sigma"):
            _check_finite(getattr(self, name), name)

    # ------------------------------------------------------------------ sizes
    @property
    def n_vertices(self) -> int:
        return int(self.mean_shape.shape[0])

    @property
    def n_shape(self) -> int:
        return int(self.shape_basis.shape[0])

    @property
    def n_exp(self) -> int:
        return int(self.exp_basis.shape[0])

    # ------------------------------------------------------------------ evaluation
    def _coeffs(self, name: str, c, k: int) -> np.ndarray:
        if c is None:
            return np.zeros(k, dtype=np.float64)
        c = np.asarray(c, dtype=np.float64).reshape(-1)
        if c.shape[0] > k:
            raise ReflectmmError(f"face model: {c.shape[0]} {name} coefficients given, the model has {k}")
        if not np.all(np.isfinite(c)):
            raise ReflectmmError(f"face model: {name} coefficients contain NaN/inf")
        return np.pad(c, (0, k - c.shape[0]))

    def vertices(self, shape=None, exp=None) -> np.ndarray:
        """(N, 3) float32 vertices for raw coefficients (shorter vectors are zero-padded)."""
        a = self._coeffs("shape", shape, self.n_shape)
        d = self._coeffs("expression", exp, self.n_exp)
        v = self.mean_shape.astype(np.float64)
        if self.n_shape:
            v = v + np.tensordot(a, self.shape_basis, axes=(0, 0))
        if self.n_exp:
            v = v + np.tensordot(d, self.exp_basis, axes=(0, 0))
        return v.astype(np.float32)

    def vertices_torch(self, shape, exp=None, *, device=None, dtype=None):
        """Differentiable (N, 3) (or (B, N, 3) for (B, K) coefficients) vertices as a torch tensor."""
        import torch

        ref = shape if torch.is_tensor(shape) else exp if torch.is_tensor(exp) else None
        dtype = dtype or (ref.dtype if ref is not None else torch.float32)
        device = device or (ref.device if ref is not None else "cpu")
        cache = self.__dict__.setdefault("_torch_cache", {})
        key = (str(device), dtype)
        if key not in cache:
            cache[key] = (torch.as_tensor(self.mean_shape, dtype=dtype, device=device),
                          torch.as_tensor(self.shape_basis.reshape(self.n_shape, -1), dtype=dtype, device=device),
                          torch.as_tensor(self.exp_basis.reshape(self.n_exp, -1), dtype=dtype, device=device))
        mean, sb, eb = cache[key]
        out = mean.reshape(-1)
        for name, c, b in (("shape", shape, sb), ("expression", exp, eb)):
            if c is None:
                continue
            c = torch.as_tensor(c, dtype=dtype, device=device)
            if c.shape[-1] > b.shape[0]:
                raise ReflectmmError(f"face model: {c.shape[-1]} {name} coefficients given, "
                                     f"the model has {b.shape[0]}")
            out = out + c @ b[: c.shape[-1]]
        return out.reshape(*out.shape[:-1], self.n_vertices, 3)

    def texture(self, tex=None) -> np.ndarray | None:
        """(N, 3) per-vertex colour of the optional texture model (None if the model has none)."""
        if self.mean_tex is None:
            return None
        b = self._coeffs("texture", tex, self.tex_basis.shape[0])
        return (self.mean_tex + np.tensordot(b, self.tex_basis, axes=(0, 0))).astype(np.float32)

    def mirror_index(self, tol: float | None = None) -> np.ndarray:
        """(N,) int32 vertex mirror map under x → −x of the mean shape.

        Uses the stored map when present; otherwise matches each vertex to the nearest vertex of the
        mirrored mean shape and raises ReflectmmError if any match is farther than ``tol`` mm (default 1 %
        of the bounding-box diagonal): the model is then not left-right symmetric.
        """
        if self.mirror is not None:
            return self.mirror
        from scipy.spatial import cKDTree

        v = self.mean_shape.astype(np.float64)
        m = v * np.array([-1.0, 1.0, 1.0])
        dist, idx = cKDTree(v).query(m)
        if tol is None:
            tol = 0.01 * float(np.linalg.norm(v.max(0) - v.min(0)))
        if dist.max() > tol:
            raise ReflectmmError(f"face model '{self.name}' is not left-right symmetric: the mirror of a vertex "
                                 f"is {dist.max():.3g} mm from the nearest vertex (tolerance {tol:.3g} mm)")
        return idx.astype(np.int32)

    def summary(self) -> str:
        return (f"{self.name}: {self.n_vertices} vertices, {len(self.triangles)} triangles, "
                f"{self.n_shape} shape / {self.n_exp} expression components, "
                f"{int(self.skin_mask.sum())} skin vertices")


# ---------------------------------------------------------------------------------------------- normals

def _check_finite(a, name: str, path=None) -> None:
    """Raise a one-line ReflectmmError if array ``a`` has NaN/inf, naming the first bad vertex/row."""
    if a is None:
        return
    a = np.asarray(a)
    ok = np.isfinite(a)
    if ok.all():
        return
    bad = ~ok.reshape(a.shape[0], -1).all(1) if a.ndim >= 1 and a.shape[0] else ~ok.reshape(1)
    where = {"mean_shape": "vertex", "uv": "vertex", "mean_tex": "vertex"}.get(name, "row")
    first = int(np.flatnonzero(bad)[0])
    raise ReflectmmError(f"face model: {name} has {int((~ok).sum())} NaN or infinite value(s) "
                         f"(first at {where} {first})", path)


def _is_torch(x) -> bool:
    """True for a torch tensor, without importing torch for numpy callers."""
    return type(x).__module__.split(".")[0] == "torch"


def face_normals(vertices, triangles, *, normalize: bool = True):
    """(T, 3) triangle normals ``(v1 − v0) × (v2 − v0)``; unit (0 for degenerate) or area-weighted (2·area)."""
    if _is_torch(vertices):
        import torch

        tri = torch.as_tensor(np.asarray(triangles), dtype=torch.long, device=vertices.device) \
            if not torch.is_tensor(triangles) else triangles.long()
        v0, v1, v2 = vertices[..., tri[:, 0], :], vertices[..., tri[:, 1], :], vertices[..., tri[:, 2], :]
        n = torch.cross(v1 - v0, v2 - v0, dim=-1)
        if normalize:
            ln = n.norm(dim=-1, keepdim=True)
            n = torch.where(ln > 0, n / ln.clamp_min(1e-30), torch.zeros_like(n))
        return n
    v = np.asarray(vertices, dtype=np.float64)
    t = np.asarray(triangles, dtype=np.int64)
    n = np.cross(v[..., t[:, 1], :] - v[..., t[:, 0], :], v[..., t[:, 2], :] - v[..., t[:, 0], :])
    if normalize:
        ln = np.linalg.norm(n, axis=-1, keepdims=True)
        n = np.divide(n, ln, out=np.zeros_like(n), where=ln > 0)
    return n


def vertex_normals(vertices, triangles, dtype=np.float32):
    """(N, 3) unit vertex normals: the area-weighted sum of adjacent triangle normals.

    numpy (float64 internally, returned as ``dtype``: float32 by default, float64 for the geometry fit) or torch
    (differentiable, batched over leading dims; the vertices' dtype).
    Degenerate (zero-area) triangles contribute nothing; a vertex with no non-degenerate triangle gets the zero
    vector — every output is finite.
    """
    if _is_torch(vertices):
        import torch

        tri = torch.as_tensor(np.asarray(triangles), dtype=torch.long, device=vertices.device) \
            if not torch.is_tensor(triangles) else triangles.long().to(vertices.device)
        fn = face_normals(vertices, tri, normalize=False)
        out = torch.zeros_like(vertices)
        for k in range(3):
            out = out.index_add(-2, tri[:, k], fn)
        ln = out.norm(dim=-1, keepdim=True)
        # gradient-safe normalisation: exact zero stays zero
        safe = torch.where(ln > 1e-20, ln, torch.ones_like(ln))
        return torch.where(ln > 1e-20, out / safe, torch.zeros_like(out))
    v = np.asarray(vertices, dtype=np.float64)
    t = np.asarray(triangles, dtype=np.int64)
    if v.ndim != 2 or v.shape[1] != 3:
        raise ReflectmmError(f"vertex_normals: vertices must be (N, 3), got {v.shape}")
    if t.ndim != 2 or t.shape[1] != 3:
        raise ReflectmmError(f"vertex_normals: triangles must be (T, 3), got {t.shape}")
    fn = face_normals(v, t, normalize=False)
    fn[~np.all(np.isfinite(fn), axis=1)] = 0.0
    out = np.zeros_like(v)
    for k in range(3):
        _accumulate(out, t[:, k], fn)
    ln = np.linalg.norm(out, axis=1, keepdims=True)
    out = np.divide(out, ln, out=np.zeros_like(out), where=ln > 1e-300)
    return out.astype(dtype)


def _accumulate(out: np.ndarray, idx: np.ndarray, vals: np.ndarray) -> None:
    # sequential, in triangle order (the same float64 sums as the geometry fit has always used)
    np.add.at(out, idx, vals)


# ---------------------------------------------------------------------------------------------- artifact I/O

_REQUIRED = ("mean_shape", "shape_basis", "shape_sigma", "exp_basis", "exp_sigma", "triangles", "uv",
             "landmarks", "skin_mask")
_OPTIONAL = ("mean_tex", "tex_basis", "tex_sigma", "mirror")


def save_face_model(model: FaceModel, path, *, params: dict | None = None, inputs: list | None = None,
                    producer: dict | None = None, cache_key: str | None = None) -> Path:
    """Write ``model`` as a ``face-model`` NPZ artifact (atomic, deterministic)."""
    from reflectmm_cli.artifacts import write_artifact

    arrays = {k: getattr(model, k) for k in _REQUIRED}
    for k in _OPTIONAL:
        if getattr(model, k) is not None:
            arrays[k] = getattr(model, k)
    p = dict(params or {})
    return write_artifact(path, "face-model", arrays, params=p, inputs=inputs, producer=producer,
                          cache_key=cache_key, extra_meta={"name": model.name, "info": model.info})


def face_model_from_artifact(art) -> FaceModel:
    """Build a :class:`FaceModel` from a read ``face-model`` artifact."""
    kw = {k: art[k] for k in _REQUIRED}
    for k in _OPTIONAL:
        if k in art.arrays:
            kw[k] = art.arrays[k]
    try:
        return FaceModel(**kw, name=str(art.meta.get("name", "face model")), info=dict(art.meta.get("info", {})))
    except ReflectmmError as exc:
        raise ReflectmmError(f"invalid face-model artifact: {exc}", art.path) from None


def load_face_model(path, **kwargs) -> FaceModel:
    """Load a face model from a ``face-model`` artifact, a BFM09 ``01_MorphableModel.mat`` or a
    Deep3DFaceRecon ``BFM_model_front.mat`` (dispatched by content, not by name)."""
    from reflectmm_cli.artifacts import read_artifact

    path = Path(path)
    if not path.exists():
        raise ReflectmmError("file not found", path)
    if path.is_dir():
        raise ReflectmmError("is a directory, expected a face model (a face-model artifact or a BFM .mat file)", path)
    if path.suffix.lower() == ".npz":
        return face_model_from_artifact(read_artifact(path, "face-model"))
    keys = _mat_keys(path)
    if "shapeMU" in keys:
        return load_bfm09(path, **kwargs)
    if "meanshape" in keys:
        return load_bfm_front(path, **kwargs)
    raise ReflectmmError("not a face model: neither a face-model artifact, a BFM09 01_MorphableModel.mat "
                         f"(key shapeMU) nor a Deep3DFaceRecon BFM_model_front.mat (key meanshape); "
                         f"keys found: {', '.join(sorted(keys)) or 'none'}", path)


# ---------------------------------------------------------------------------------------------- .mat loaders

def _mat_keys(path: Path) -> list[str]:
    import scipy.io

    try:
        return [k for k, *_ in scipy.io.whosmat(str(path))]
    except NotImplementedError:  # MATLAB v7.3 (HDF5)
        raise ReflectmmError("MATLAB v7.3 (HDF5) .mat files are not supported; re-save with "
                             "`save(..., '-v7')` or scipy.io.savemat", path) from None
    except Exception as exc:  # scipy raises several types for junk input
        raise ReflectmmError(f"not a readable .mat file ({type(exc).__name__}: {exc})", path) from None


def _loadmat(path: Path) -> dict[str, np.ndarray]:
    import scipy.io

    try:
        return scipy.io.loadmat(str(path))
    except NotImplementedError:
        raise ReflectmmError("MATLAB v7.3 (HDF5) .mat files are not supported; re-save with "
                             "`save(..., '-v7')` or scipy.io.savemat", path) from None
    except Exception as exc:
        raise ReflectmmError(f"not a readable .mat file ({type(exc).__name__}: {exc})", path) from None


def _get(mat: dict, key: str, path: Path, what: str) -> np.ndarray:
    if key not in mat:
        have = ", ".join(sorted(k for k in mat if not k.startswith("__")))
        raise ReflectmmError(f"missing key '{key}' ({what}); keys found: {have}", path)
    return np.asarray(mat[key])


def _as_points(a: np.ndarray, key: str, path: Path, n: int | None = None) -> np.ndarray:
    """(3N,1)/(1,3N)/(N,3) → (N,3) float64 (BFM interleaves x,y,z per vertex)."""
    a = np.asarray(a, dtype=np.float64)
    if a.ndim == 2 and a.shape[1] == 3 and a.shape[0] != 1 and (n is None or a.shape[0] == n):
        return a
    flat = a.reshape(-1)
    if flat.size % 3 or (n is not None and flat.size != 3 * n):
        exp = f"(3·{n}, 1)" if n is not None else "(3N, 1)"
        raise ReflectmmError(f"'{key}' has shape {a.shape}, expected {exp}", path)
    return flat.reshape(-1, 3)


def _as_basis(a: np.ndarray, key: str, path: Path, n: int) -> np.ndarray:
    """(3N, K) → (K, N, 3) float32 (the published BFM09 bases are ~128 MB each in float32)."""
    a = np.asarray(a, dtype=np.float32)
    if a.ndim != 2 or a.shape[0] != 3 * n:
        raise ReflectmmError(f"'{key}' has shape {a.shape}, expected (3·{n} = {3 * n}, K)", path)
    return np.ascontiguousarray(a.T.reshape(a.shape[1], n, 3))


def _as_triangles(a: np.ndarray, key: str, path: Path, n: int) -> np.ndarray:
    t = np.asarray(a)
    if t.ndim != 2 or 3 not in t.shape:
        raise ReflectmmError(f"'{key}' has shape {t.shape}, expected (T, 3)", path)
    if t.shape[1] != 3:
        t = t.T
    t = t.astype(np.int64) - 1  # 1-based in both formats
    if t.min() < 0 or t.max() >= n:
        raise ReflectmmError(f"'{key}' indices span [{t.min() + 1}, {t.max() + 1}] but must be 1-based in "
                             f"[1, {n}]", path)
    return t.astype(np.int32)


def detect_unit_scale(points: np.ndarray) -> tuple[float, str]:
    """Scale to millimetres from the extent of a face mesh: µm (BFM09), mm, or dm (Deep3DFaceRecon)."""
    diag = float(np.linalg.norm(points.max(0) - points.min(0)))
    if diag > 2e4:
        return 1e-3, "micrometres"
    if diag > 50:
        return 1.0, "millimetres"
    if diag > 0.5:
        return 100.0, "decimetres"
    return 1000.0, "metres"


def _units(points: np.ndarray, units: str | float | None, path: Path) -> tuple[float, str]:
    named = {"um": 1e-3, "micrometres": 1e-3, "mm": 1.0, "millimetres": 1.0, "dm": 100.0, "decimetres": 100.0,
             "m": 1000.0, "metres": 1000.0}
    _check_finite(points, "mean_shape", path)  # a NaN extent would read as metres first
    if units is None or units == "auto":
        scale, name = detect_unit_scale(points)
        log.info("%s: coordinates look like %s (bounding-box diagonal %.4g); scaling by %g to mm",
                 path.name, name, float(np.linalg.norm(points.max(0) - points.min(0))), scale)
        return scale, name
    if isinstance(units, str):
        if units not in named:
            raise ReflectmmError(f"unknown units '{units}' (use auto, um, mm, dm or m)", path)
        return named[units], units
    return float(units), f"×{units}"


def load_exp_pca_bin(path, n_vertices: int | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Read Guo et al.'s ``Exp_Pca.bin`` (as Deep3DFaceRecon's ``LoadExpBasis``): little-endian int32 K, then
    float32 mean (3N) and float32 basis stored as K rows of 3N (x, y, z interleaved per vertex).

    Returns (mean (N,3), basis (K,N,3)) as float64 in the file's units.  N is inferred from the file size when
    ``n_vertices`` is None (the published file has N = 53215, K = 79).
    """
    path = Path(path)
    try:
        raw = path.read_bytes()
    except OSError as exc:
        raise ReflectmmError(f"cannot read ({exc.strerror})", path) from None
    if len(raw) < 4:
        raise ReflectmmError("truncated Exp_Pca.bin (no header)", path)
    k = int(np.frombuffer(raw[:4], dtype="<i4")[0])
    nfloat = (len(raw) - 4) // 4
    if k <= 0 or (len(raw) - 4) % 4 or nfloat % (3 * (k + 1)):
        raise ReflectmmError(f"Exp_Pca.bin size {len(raw)} bytes does not match int32 K={k} + float32 "
                             "mean(3N) + basis(K·3N)", path)
    n = nfloat // (3 * (k + 1))
    if n_vertices is not None and n != n_vertices:
        raise ReflectmmError(f"Exp_Pca.bin holds {n} vertices, expected {n_vertices}", path)
    data = np.frombuffer(raw[4:], dtype="<f4").astype(np.float64)
    mean = data[: 3 * n].reshape(n, 3)
    basis = data[3 * n:].reshape(k, n, 3)
    return mean, basis


def load_bfm09(path, exp_path=None, *, exp_std_path=None, exp_index_path=None, units: str | float | None = "auto",
               landmarks=None, uv=None) -> FaceModel:
    """Load BFM09 ``01_MorphableModel.mat``.

    Keys: ``shapeMU (3N,1)``, ``shapePC (3N,Ks)`` (orthonormal columns), ``shapeEV (Ks,1)`` (standard deviations),
    ``texMU (3N,1)``, ``texPC (3N,Kt)``, ``texEV (Kt,1)`` (0–255), ``tl (T,3)`` 1-based triangles.
    Coordinates are converted to mm (``units='auto'`` detects µm from the extent — the published file is in
    µm, which is why Deep3DFaceRecon divides by 1e5 to get decimetres).  The model's own triangle winding
    is kept if its normals point outwards on average, otherwise flipped (logged).

    Optional expression basis ``exp_path`` (``Exp_Pca.bin``, see :func:`load_exp_pca_bin`).  Its vertices are
    either the same N as the shape (used directly) or a subset given by ``exp_index_path`` (a .mat with
    ``trimIndex``, 1-based indices into the BFM09 vertices, as Deep3DFaceRecon's ``BFM_exp_idx.mat``); vertices
    outside the subset get no expression motion.  ``exp_std_path`` (``std_exp.txt``) gives the expression σ;
    without it σ = 1.  BFM09 has no UVs and no landmark indices: pass ``uv`` (N,2) / ``landmarks`` (68,) or get
    a symmetric cylindrical UV (:func:`reflectmm_cli.geometry.uv.cylindrical_uv`) and landmarks = −1 → empty.
    """
    path = Path(path)
    mat = _loadmat(path)
    mu = _get(mat, "shapeMU", path, "mean shape")
    raw_mean = _as_points(mu, "shapeMU", path)
    n = raw_mean.shape[0]
    scale, unit_name = _units(raw_mean, units, path)
    pc = _as_basis(_get(mat, "shapePC", path, "shape basis"), "shapePC", path, n)
    ev = np.asarray(_get(mat, "shapeEV", path, "shape standard deviations"), dtype=np.float64).reshape(-1)
    if ev.shape[0] != pc.shape[0]:
        raise ReflectmmError(f"'shapeEV' has {ev.shape[0]} values but 'shapePC' has {pc.shape[0]} columns", path)
    tri = _as_triangles(_get(mat, "tl", path, "triangles"), "tl", path, n)
    mean = raw_mean * scale
    # shapePC columns are orthonormal; shapeEV are the coefficient standard deviations (file units).
    shape_basis = pc
    shape_sigma = ev * scale
    info: dict[str, Any] = {"source": "BFM09", "units_detected": unit_name, "scale_to_mm": scale}

    mean_tex = tex_basis = tex_sigma = None
    if "texMU" in mat:
        tmu = _as_points(mat["texMU"], "texMU", path, n)
        tpc = _as_basis(_get(mat, "texPC", path, "texture basis"), "texPC", path, n)
        tev = np.asarray(_get(mat, "texEV", path, "texture standard deviations"), dtype=np.float64).reshape(-1)
        if tev.shape[0] != tpc.shape[0]:
            raise ReflectmmError(f"'texEV' has {tev.shape[0]} values but 'texPC' has {tpc.shape[0]} columns", path)
        mean_tex, tex_basis, tex_sigma = tmu / 255.0, tpc, tev / 255.0

    exp_basis = np.zeros((0, n, 3))
    exp_sigma = np.zeros(0)
    if exp_path is not None:
        _, eb = load_exp_pca_bin(exp_path)
        ne = eb.shape[1]
        if ne != n:
            if exp_index_path is None:
                raise ReflectmmError(f"Exp_Pca.bin has {ne} vertices but the shape model has {n}; pass the vertex "
                                     "subset (BFM_exp_idx.mat with 'trimIndex')", exp_path)
            emat = _loadmat(Path(exp_index_path))
            idx = np.asarray(_get(emat, "trimIndex", Path(exp_index_path), "expression vertex subset"))
            idx = idx.reshape(-1).astype(np.int64) - 1
            if idx.shape[0] != ne or idx.min() < 0 or idx.max() >= n:
                raise ReflectmmError(f"'trimIndex' must hold {ne} 1-based indices in [1, {n}], got "
                                     f"{idx.shape[0]} in [{idx.min() + 1}, {idx.max() + 1}]", exp_index_path)
            full = np.zeros((eb.shape[0], n, 3))
            full[:, idx] = eb
            eb = full
        exp_sigma = np.ones(eb.shape[0])
        if exp_std_path is not None:
            try:
                exp_sigma = np.loadtxt(str(exp_std_path), dtype=np.float64).reshape(-1)
            except (OSError, ValueError) as exc:
                raise ReflectmmError(f"cannot read expression standard deviations ({exc})", exp_std_path) from None
            if exp_sigma.shape[0] != eb.shape[0]:
                raise ReflectmmError(f"{exp_sigma.shape[0]} standard deviations for {eb.shape[0]} expression "
                                     "components", exp_std_path)
        exp_basis = eb * scale
        info["expression"] = str(Path(exp_path).name)

    tri, flipped = _orient_outward(mean, tri)
    if flipped:
        log.info("%s: triangle winding flipped so that normals point out of the face", path.name)
    info["winding_flipped"] = bool(flipped)
    return _finish_imported(mean, shape_basis, shape_sigma, exp_basis, exp_sigma, tri, mean_tex, tex_basis,
                            tex_sigma, landmarks, uv, None, "BFM09 " + path.name, info, path)


def load_bfm_front(path, *, units: str | float | None = "auto", recenter: bool = True, uv=None) -> FaceModel:
    """Load Deep3DFaceRecon's ``BFM_model_front.mat`` (35 709-vertex front face).

    Keys: ``meanshape (1,3N)``, ``idBase (3N,80)``, ``exBase (3N,64)``, ``meantex (1,3N)`` (0–255),
    ``texBase (3N,80)``, ``tri (T,3)``, ``point_buf (N,8)`` (unused: normals are recomputed), ``keypoints (1,68)``
    and ``skinmask (1,N)``; indices 1-based.  The bases already include the eigenvalues (``idBase = shapePC ·
    shapeEV / 1e5``), so σ = 1 for every coefficient and Deep3DFaceRecon's coefficients can be used as they
    are.  Units are decimetres → converted to mm (×100); ``recenter`` subtracts the mean vertex as
    Deep3DFaceRecon's ``ParametricFaceModel(recenter=True)`` does.
    """
    path = Path(path)
    mat = _loadmat(path)
    raw_mean = _as_points(_get(mat, "meanshape", path, "mean shape"), "meanshape", path)
    n = raw_mean.shape[0]
    scale, unit_name = _units(raw_mean, units, path)
    id_base = _as_basis(_get(mat, "idBase", path, "identity basis"), "idBase", path, n)
    ex_base = _as_basis(_get(mat, "exBase", path, "expression basis"), "exBase", path, n)
    tri = _as_triangles(_get(mat, "tri", path, "triangles"), "tri", path, n)
    kp = np.asarray(_get(mat, "keypoints", path, "68 landmark vertex indices")).reshape(-1).astype(np.int64) - 1
    if kp.shape[0] != 68 or kp.min() < 0 or kp.max() >= n:
        raise ReflectmmError(f"'keypoints' must hold 68 1-based vertex indices in [1, {n}], got {kp.shape[0]}",
                             path)
    skin = np.ones(n, dtype=bool)
    if "skinmask" in mat:
        sm = np.asarray(mat["skinmask"]).reshape(-1)
        if sm.shape[0] != n:
            raise ReflectmmError(f"'skinmask' has {sm.shape[0]} entries, expected {n}", path)
        skin = sm > 0.5
    mean_tex = tex_basis = tex_sigma = None
    if "meantex" in mat:
        mean_tex = _as_points(mat["meantex"], "meantex", path, n) / 255.0
        tex_basis = _as_basis(_get(mat, "texBase", path, "texture basis"), "texBase", path, n) / 255.0
        tex_sigma = np.ones(tex_basis.shape[0])
    mean = raw_mean * scale
    if recenter:
        mean = mean - mean.mean(0, keepdims=True)
    info = {"source": "Deep3DFaceRecon BFM_model_front", "units_detected": unit_name, "scale_to_mm": scale,
            "recentered": bool(recenter)}
    tri, flipped = _orient_outward(mean, tri)
    if flipped:
        log.info("%s: triangle winding flipped so that normals point out of the face", path.name)
    info["winding_flipped"] = bool(flipped)
    return _finish_imported(mean, id_base * scale, np.ones(id_base.shape[0]), ex_base * scale,
                            np.ones(ex_base.shape[0]), tri, mean_tex, tex_basis, tex_sigma, kp, uv, skin,
                            "Deep3DFaceRecon " + path.name, info, path)


def _orient_outward(mean: np.ndarray, tri: np.ndarray) -> tuple[np.ndarray, bool]:
    """Flip the winding if the area-weighted normals point towards the centroid on average."""
    fn = face_normals(mean, tri, normalize=False)
    cen = mean[tri].mean(1) - mean.mean(0)
    if float((fn * cen).sum()) < 0:
        return tri[:, [0, 2, 1]].copy(), True
    return tri, False


def _finish_imported(mean, sb, ss, eb, es, tri, mt, tb, ts, landmarks, uv, skin, name, info, path) -> FaceModel:
    from reflectmm_cli.geometry.uv import cylindrical_uv, uv_distortion

    n = mean.shape[0]
    _check_finite(mean, "mean_shape", path)  # before anything is computed from it
    extent = np.ptp(np.asarray(mean, np.float64).reshape(-1, 3), axis=0) if n else np.zeros(3)
    if (extent <= 0).sum() > 1:  # every vertex at one point or on one line: no surface (a blank or wrong array)
        raise ReflectmmError(f"face model: the mean shape spans {extent[0]:g} x {extent[1]:g} x {extent[2]:g} "
                             "(a point or a line, not a face): a blank or wrong 'meanshape' array", path)
    if uv is not None:
        _check_finite(uv, "uv", path)
    if uv is None:
        uv = cylindrical_uv(mean)
        info["uv"] = "cylindrical (computed)"
        info["uv_distortion"] = uv_distortion(mean, tri, uv)
    else:
        uv = np.asarray(uv, dtype=np.float64)
        info["uv"] = "given"
    lm = np.zeros(0, dtype=np.int32) if landmarks is None else np.asarray(landmarks).reshape(-1)
    if skin is None:
        skin = np.ones(n, dtype=bool)
    try:
        return FaceModel(mean, sb, ss, eb, es, tri, uv, lm, skin, mt, tb, ts, name=name, info=info)
    except ReflectmmError as exc:
        raise ReflectmmError(str(exc), path) from None
