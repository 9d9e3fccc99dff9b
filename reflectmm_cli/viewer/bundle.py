"""The data of an interactive viewer page: mesh, per-vertex reflectance models, lighting and the shading constants.

A bundle is one JSON document (``reflectmm.viewer/1``) whose arrays are stored as :class:`Blob` records
(little-endian bytes in base64 with their dtype and shape). The page reads nothing else: the shading constants
(``A_l/π``, ``B_l^i``, the lobe normalisations ``f_i`` and the SH recurrence constants) are computed here by
the same functions the renderer uses (:mod:`reflectmm_cli.shading`), so the page evaluates the contract of
docs/design.md §2 and never a second approximation of it. docs/viewer.md describes every field.

Encodings (:data:`ENCODINGS`): the per-vertex bases are float16 (the default; relative error ≤ 2⁻¹¹) or 8-bit
with one scale per component and channel (``u8``: error ≤ half a step of max|b|/127); means, positions, normals and
lighting are float32.
"""
from __future__ import annotations

import base64
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Mapping, Sequence

import numpy as np

from reflectmm_cli.errors import ReflectmmError
from reflectmm_cli.shading.sh import sh_order

__all__ = ["FORMAT", "ENCODINGS", "MAX_LOBES", "ViewerOptions", "Blob", "ModelData", "LightData",
           "decode_blob", "iter_blobs", "model_data", "light_model_data", "envmap_data", "build_bundle", "bundle_size"]

FORMAT = "reflectmm.viewer/1"

#: Basis encodings: ``f2`` (float16) or ``u8`` (8-bit, symmetric, one scale per component and channel).
ENCODINGS = ("f2", "u8")

#: Largest number of lobes the page shades (two vec4 weight attributes).
MAX_LOBES = 8

#: Largest SH order the page evaluates (its fragment shader is generated for the bundle's order).
MAX_ORDER = 12


@dataclass(frozen=True)
class ViewerOptions:
    """What goes into a page.

    Attributes:
        components: reflectance-model components embedded per model (capped by each model's own count).
        light_components: light-model components embedded (capped by the light model).
        sh_order: SH order of the environment maps' projection (the page's order is the largest embedded one).
        encoding: basis encoding, one of :data:`ENCODINGS`.
        camera_distance: initial camera distance (mm) of the orbit view.
        focal: focal length in pixels at the reference height ``focal_height`` (the page scales it with its
            canvas height, so a resized window keeps the field of view).
        focal_height: the canvas height (pixels) at which ``focal`` holds.
    """

    components: int = 10
    light_components: int = 10
    sh_order: int = 8
    encoding: str = "f2"
    camera_distance: float = 1000.0
    focal: float = 1500.0
    focal_height: int = 480

    def __post_init__(self) -> None:
        if self.components < 0 or self.light_components < 0:
            raise ReflectmmError("view: --components and --light-components must be ≥ 0")
        if not 0 <= self.sh_order <= MAX_ORDER:
            raise ReflectmmError(f"view: --sh-order must be in 0..{MAX_ORDER}, got {self.sh_order}")
        if self.encoding not in ENCODINGS:
            raise ReflectmmError(f"view: unknown encoding '{self.encoding}' (one of {', '.join(ENCODINGS)})")
        if not (self.camera_distance > 0 and self.focal > 0 and self.focal_height > 0):
            raise ReflectmmError("view: camera distance, focal and reference height must be > 0")


@dataclass
class Blob:
    """One array as bytes: ``dtype`` ∈ {f4, f2, u1, i1, u2, u4}, ``shape``, and for ``i1`` a per-row scale
    (rows = the first axis … the axes before the last ``scale_axes`` — see :func:`_quantise`)."""

    dtype: str
    shape: tuple[int, ...]
    data: bytes
    scale: np.ndarray | None = None

    def to_json(self) -> dict[str, Any]:
        d: dict[str, Any] = {"dtype": self.dtype, "shape": list(self.shape),
                             "data": base64.b64encode(self.data).decode("ascii")}
        if self.scale is not None:
            d["scale"] = [float(s) for s in self.scale.reshape(-1)]
            d["scale_shape"] = list(self.scale.shape)
        return d


_NP = {"f4": "<f4", "f2": "<f2", "u1": "u1", "i1": "i1", "u2": "<u2", "u4": "<u4"}


def _blob(a: np.ndarray, dtype: str) -> Blob:
    a = np.ascontiguousarray(np.asarray(a).astype(_NP[dtype]))
    return Blob(dtype, tuple(int(s) for s in a.shape), a.tobytes())


def _quantise(basis: np.ndarray) -> Blob:
    """(M, N, C) → int8 with one scale per (component, channel): ``b ≈ q · scale[m, c]``, ``|q| ≤ 127``."""
    b = np.asarray(basis, np.float64)
    top = np.abs(b).max(axis=1)  # (M, C)
    scale = np.where(top > 0, top / 127.0, 1.0)
    q = np.clip(np.rint(b / scale[:, None, :]), -127, 127).astype(np.int8)
    blob = _blob(q, "i1")
    blob.scale = scale.astype(np.float32)
    return blob


def decode_blob(d: Mapping[str, Any]) -> np.ndarray:
    """The array of a blob's JSON record (float32 for f2/i1; the page decodes the same way)."""
    raw = base64.b64decode(d["data"])
    a = np.frombuffer(raw, dtype=_NP[d["dtype"]]).reshape(d["shape"])
    if d["dtype"] == "i1":
        s = np.asarray(d["scale"], np.float32).reshape(d["scale_shape"])
        return a.astype(np.float32) * s[:, None, :]
    return a.astype(np.float32) if d["dtype"] == "f2" else a


@dataclass
class ModelData:
    """One reflectance model as the page needs it (per vertex)."""

    name: str
    exponents: np.ndarray  # (K,)
    sigma: np.ndarray  # (M,)
    albedo_mean: np.ndarray  # (N, 3)
    albedo_basis: np.ndarray  # (M, N, 3)
    weights_mean: np.ndarray  # (N, K)
    weights_basis: np.ndarray  # (M, N, K)
    n_components_total: int = 0
    source: str = ""


@dataclass
class LightData:
    """Lighting choices: named SH environments (3, (L+1)²) and an optional PCA light model."""

    envmaps: list[tuple[str, np.ndarray]] = field(default_factory=list)
    model_order: int | None = None
    model_mean: np.ndarray | None = None  # (3·(L+1)²,) normalised (K_00 = 1 per channel)
    model_bases: np.ndarray | None = None  # (k, F) orthonormal rows
    model_sigma: np.ndarray | None = None  # (k,)
    model_level: np.ndarray | None = None  # (3,) z: the mean 0-th coefficient of the data


def model_data(arrays: Mapping[str, Any], components: int, name: str, source: Path | str = "") -> ModelData:
    """The per-vertex part of a ``reflectance-model`` artifact's arrays, first ``components`` components.

    Raises ReflectmmError (one line, naming ``source``) for a model without a per-vertex part, more than
    :data:`MAX_LOBES` lobes, or non-finite values."""
    where = Path(source) if source else None
    keys = ("vertex_albedo_mean", "vertex_albedo_basis", "vertex_weights_mean", "vertex_weights_basis")
    files = set(getattr(arrays, "files", None) or arrays.keys())
    if not all(k in files for k in keys):
        raise ReflectmmError("view: the model has no per-vertex part (build it with --face-model: build-pca, "
                             "build-baseline and finetune do)", where)
    sigma = np.asarray(arrays["sigma"], np.float64).reshape(-1)
    exps = np.asarray(arrays["exponents"], np.float64).reshape(-1)
    m = min(int(components), sigma.size)
    am = np.asarray(arrays["vertex_albedo_mean"], np.float32)
    wm = np.asarray(arrays["vertex_weights_mean"], np.float32)
    ab = np.asarray(arrays["vertex_albedo_basis"], np.float32)[:m]
    wb = np.asarray(arrays["vertex_weights_basis"], np.float32)[:m]
    n = am.shape[0] if am.ndim == 2 else -1
    k = exps.size
    if am.shape != (n, 3) or wm.shape != (n, k) or ab.shape != (m, n, 3) or wb.shape != (m, n, k):
        raise ReflectmmError(f"view: inconsistent per-vertex arrays (albedo mean {am.shape}, weights mean "
                             f"{wm.shape}, {k} exponents)", where)
    if k > MAX_LOBES:
        raise ReflectmmError(f"view: {k} lobes; the viewer shades at most {MAX_LOBES}", where)
    for what, a in (("sigma", sigma), ("exponents", exps), ("albedo mean", am), ("weights mean", wm),
                    ("albedo basis", ab), ("weights basis", wb)):
        if not np.all(np.isfinite(a)):
            raise ReflectmmError(f"view: the model's {what} contains NaN or inf", where)
    if not np.all(sigma > 0):
        raise ReflectmmError(f"view: the model's sigma must be > 0 ({int((~(sigma > 0)).sum())} of its {sigma.size} "
                             "values are not): its sliders would move nothing", where)
    return ModelData(name, exps, sigma[:m], am, ab, wm, wb, n_components_total=int(sigma.size),
                     source=str(source))


def light_model_data(arrays: Mapping[str, Any], components: int, light: LightData | None = None) -> LightData:
    """Add a ``light-model`` artifact's mean, first components and mean level to ``light``."""
    from reflectmm_cli.model.light import light_model_from_arrays

    lm = light_model_from_arrays(arrays)
    out = light or LightData()
    k = min(int(components), lm.n_components)
    out.model_order = lm.order
    out.model_mean = lm.mean
    out.model_bases = lm.bases[:k]
    out.model_sigma = lm.sigma[:k]
    try:
        level = np.asarray(arrays["dc_mean"], np.float64).reshape(3)
    except (KeyError, ValueError):
        level = np.ones(3)
    out.model_level = level if np.all(np.isfinite(level)) and np.all(level > 0) else np.ones(3)
    return out


def envmap_data(paths: Sequence[Path], order: int, light: LightData | None = None) -> LightData:
    """Project equirectangular maps to SH of ``order`` (the renderer's projection) and add them to ``light``."""
    from reflectmm_cli.shading import load_envmap, project_envmap

    out = light or LightData()
    for p in paths:
        out.envmaps.append((Path(p).stem, np.asarray(project_envmap(load_envmap(p), order), np.float64)))
    return out


def _pad_sh(K: np.ndarray, order: int) -> np.ndarray:
    """(3, n) → (3, (order+1)²) with exact zeros in the added bands."""
    out = np.zeros((3, (order + 1) ** 2))
    out[:, :K.shape[1]] = K
    return out


def _shading_constants(exponent_sets: Sequence[np.ndarray], order: int) -> dict[str, Any]:
    """A_l/π, and per model B_l^i and f_i, plus the constants of the SH recurrence (``shading/sh.py``)."""
    from reflectmm_cli.shading.sh import _legendre_consts, blinn_phong_norm, blinn_phong_sh_coeffs, lambert_sh_coeffs

    pmm, a, b = _legendre_consts(order)
    rec_a = [[a.get((l, m), 0.0) for l in range(order + 1)] for m in range(order + 1)]  # noqa: E741
    rec_b = [[b.get((l, m), 0.0) for l in range(order + 1)] for m in range(order + 1)]  # noqa: E741
    return {
        "order": order,
        "lambert_over_pi": (lambert_sh_coeffs(order) / math.pi).tolist(),
        "lobes": [{"B": np.atleast_2d(blinn_phong_sh_coeffs(e, order)).tolist(),
                   "norm": np.atleast_1d(blinn_phong_norm(np.asarray(e, np.float64))).tolist()}
                  for e in exponent_sets],
        "recurrence": {"pmm": list(pmm), "a": rec_a, "b": rec_b},
    }


def _front(vertices, normals, eye: np.ndarray):
    """(mask of the vertices facing the camera at ``eye``, their directions towards it)."""
    v = eye[None, :] - vertices
    front = (normals * v).sum(1) > 0
    return front, v[front]


def _default_exposure(vertices, normals, model: ModelData, K: np.ndarray, eye: np.ndarray) -> float:
    """The exposure of ``render``'s PNG (:func:`reflectmm_cli.color.auto_exposure`) for the mean face's radiance
    under SH lighting ``K``, on the vertices facing the camera instead of pixels."""
    from reflectmm_cli.color import auto_exposure
    from reflectmm_cli.shading import shade_env

    front, v = _front(vertices, normals, eye)
    if not front.any():
        return 1.0
    d, s = shade_env(model.albedo_mean[front].astype(np.float64), model.weights_mean[front].astype(np.float64),
                     model.exponents, normals[front].astype(np.float64), v, K)
    return auto_exposure(d + s)


def _point_exposure(vertices, normals, model: ModelData, eye: np.ndarray) -> float:
    """The same rule for the default point light (at the camera, irradiance π at the origin)."""
    from reflectmm_cli.color import auto_exposure
    from reflectmm_cli.shading import shade_directional

    front, v = _front(vertices, normals, eye)
    if not front.any():
        return 1.0
    E = math.pi * float(eye @ eye) / np.maximum((v ** 2).sum(1), 1e-30)
    return auto_exposure(shade_directional(model.albedo_mean[front].astype(np.float64),
                                           model.weights_mean[front].astype(np.float64), model.exponents,
                                           normals[front].astype(np.float64), v, v, np.repeat(E[:, None], 3, axis=1)))


#: The environment used when neither maps nor a light model are given: uniform unit radiance.
UNIFORM_SKY = "uniform"


def build_bundle(vertices: np.ndarray, triangles: np.ndarray, normals: np.ndarray, models: Sequence[ModelData],
                 light: LightData, options: ViewerOptions = ViewerOptions(), title: str = "") -> dict[str, Any]:
    """The page's JSON document.

    Args:
        vertices: (N, 3) mean face (mm, model space, +y up).
        triangles: (T, 3) vertex indices, counter-clockwise seen from outside.
        normals: (N, 3) unit vertex normals (the renderer's :func:`vertex_normals`).
        models: one model, or two for a side-by-side comparison (same vertex count).
        light: environment maps and/or a light model (a uniform sky is added when both are missing).
        options: :class:`ViewerOptions`.
    """
    if not 1 <= len(models) <= 2:
        raise ReflectmmError(f"view: one model, or two to compare, got {len(models)}")
    V = np.asarray(vertices, np.float64)
    T = np.asarray(triangles)
    Nn = np.asarray(normals, np.float64)
    n = V.shape[0]
    for md in models:
        if md.albedo_mean.shape[0] != n:
            raise ReflectmmError(f"view: the model has {md.albedo_mean.shape[0]} vertices, the face model {n}",
                                 Path(md.source) if md.source else None)
    envs = list(light.envmaps)
    if not envs and light.model_mean is None:
        envs.append((UNIFORM_SKY, _pad_sh(np.full((3, 1), math.sqrt(4 * math.pi)), 0)))
    orders = [sh_order(K.shape[1]) for _, K in envs] + ([light.model_order] if light.model_mean is not None else [])
    order = max(orders)
    if order > MAX_ORDER:
        raise ReflectmmError(f"view: lighting of SH order {order}; the viewer evaluates at most {MAX_ORDER}")
    eye = np.array([0.0, 0.0, options.camera_distance])
    ref = models[0]
    lights: dict[str, Any] = {"envmaps": [], "model": None}
    for name, K in envs:
        Kp = _pad_sh(K, order)
        lights["envmaps"].append({"name": name, "sh": _blob(Kp, "f4").to_json(),
                                  "exposure": _default_exposure(V, Nn, ref, Kp, eye)})
    if light.model_mean is not None:
        lo = light.model_order
        K0 = _pad_sh(light.model_mean.reshape(3, -1) * light.model_level[:, None], order)
        lights["model"] = {"order": lo, "mean": _blob(light.model_mean, "f4").to_json(),
                           "bases": _blob(light.model_bases, "f4").to_json(),
                           "sigma": [float(s) for s in light.model_sigma], "level": light.model_level.tolist(),
                           "exposure": _default_exposure(V, Nn, ref, K0, eye)}
    lights["point_exposure"] = _point_exposure(V, Nn, ref, eye)
    enc = (lambda b: _blob(b, "f2").to_json()) if options.encoding == "f2" else (lambda b: _quantise(b).to_json())
    doc_models = []
    for md in models:
        doc_models.append({
            "name": md.name, "source": Path(md.source).name if md.source else "",
            "exponents": md.exponents.tolist(), "sigma": md.sigma.tolist(),
            "n_components_total": md.n_components_total,
            "albedo_mean": _blob(md.albedo_mean, "f4").to_json(), "weights_mean": _blob(md.weights_mean, "f4").to_json(),
            "albedo_basis": enc(md.albedo_basis), "weights_basis": enc(md.weights_basis),
        })
    index_dtype = "u2" if n <= 65535 else "u4"
    return {
        "format": FORMAT,
        "title": title,
        "mesh": {"positions": _blob(V, "f4").to_json(), "normals": _blob(Nn, "f4").to_json(),
                 "triangles": _blob(T.reshape(-1, 3), index_dtype).to_json()},
        "models": doc_models,
        "lights": lights,
        "shading": _shading_constants([md.exponents for md in models], order),
        "camera": {"distance": options.camera_distance, "focal": options.focal, "focal_height": options.focal_height},
        "display": {"transfers": ["srgb", "gamma1.2"], "default": "srgb"},
    }


def iter_blobs(x: Any, name: str = ""):
    """(place, record) of every blob record in a bundle or part of one, depth first (``mesh.positions``,
    ``models[0].albedo_basis``, …)."""
    if isinstance(x, dict) and "dtype" in x and "data" in x:
        yield name, x
    elif isinstance(x, dict):
        for k, v in x.items():
            yield from iter_blobs(v, f"{name}.{k}" if name else k)
    elif isinstance(x, list):
        for i, v in enumerate(x):
            yield from iter_blobs(v, f"{name}[{i}]")


def bundle_size(doc: Mapping[str, Any]) -> dict[str, int]:
    """Bytes of base64 text per part of the bundle (mesh, each model's means and bases, lighting)."""
    def size(*parts) -> int:
        return sum(len(rec["data"]) for part in parts for _, rec in iter_blobs(part))

    out = {"mesh": size(doc["mesh"]), "lights": size(doc["lights"])}
    for i, m in enumerate(doc["models"]):
        out[f"model{i}.means"] = size(m["albedo_mean"], m["weights_mean"])
        out[f"model{i}.bases"] = size(m["albedo_basis"], m["weights_basis"])
    return out
