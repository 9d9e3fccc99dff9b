"""Statistical lighting model: PCA of normalised SH lighting (docs/design.md §1 step 6).

Pipeline: each HDR environment map → SH up to ``order`` (:func:`project_envmap`) → ``rotations`` copies rotated
about the vertical (+y) axis by ``2πk/rotations`` (optionally each also tilted by ±``tilt`` degrees about +x),
done exactly in SH space with :func:`sh_rotation` → every colour channel divided by its own 0-th coefficient
(so every sample has K_00 = 1 per channel: the model describes the *shape* of the lighting; its per-channel
level is the separate scale z) → PCA.

A sample is the flattened (3, (L+1)²) array, channel-major (index ``c·(L+1)² + l² + l + m``).
Inverse (used by finetuning): ``K = z[c] · (mean + Σ_k γ_k σ_k b_k)`` reshaped to (3, (L+1)²) — γ is in units
of the per-component standard deviation σ_k, so a standard normal prior on γ matches the data.
"""
from __future__ import annotations

import logging
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Iterable

import numpy as np

from reflectmm_cli.color import linear_to_gamma
from reflectmm_cli.errors import ReflectmmError
from reflectmm_cli.geometry.rotations import rotation_x, rotation_y  # re-exported (public names of this module)
from reflectmm_cli.shading._array import any_torch, device_of
from reflectmm_cli.shading.envmap import envmap_from_sh, envmap_rgb, project_envmap
from reflectmm_cli.shading.sh import sh_order, sh_rotation

log = logging.getLogger("reflectmm")

__all__ = [
    "LIGHT_MODEL_KIND",
    "ENVMAP_SUFFIXES",
    "LightModel",
    "find_envmaps",
    "rotation_y",
    "rotation_x",
    "augmentation_rotations",
    "augment_sh",
    "normalise_sh",
    "fit_light_pca",
    "build_light_model",
    "light_from_coeffs",
    "light_model_arrays",
    "light_model_from_arrays",
    "light_model_preview",
]

LIGHT_MODEL_KIND = "light-model"
ENVMAP_SUFFIXES = (".exr", ".hdr", ".pic", ".rgbe")


@dataclass
class LightModel:
    """PCA lighting model. Shapes: F = 3·(order+1)² features, k components."""

    order: int
    mean: np.ndarray  # (F,)
    bases: np.ndarray  # (k, F) orthonormal rows
    sigma: np.ndarray  # (k,) std of the data along each basis
    explained_variance: np.ndarray  # (k,) = sigma²
    explained_variance_ratio: np.ndarray  # (k,) fraction of the total variance
    dc: np.ndarray  # (S, 3) per sample, the 0-th coefficient each channel was divided by
    sample_map: np.ndarray  # (S,) index of the source map of each sample
    sample_rotation: np.ndarray  # (S, 3, 3) rotation applied to each sample
    map_names: list[str] = field(default_factory=list)

    @property
    def n_coeffs(self) -> int:
        return (self.order + 1) ** 2

    @property
    def n_components(self) -> int:
        return int(self.bases.shape[0])


def find_envmaps(inputs: Iterable[str | Path]) -> list[Path]:
    """Expand folders (non-recursive … recursive) into HDR map files; keep explicit files as given.  A file reached
    twice (named twice, or named and inside a named folder) is kept once, and said: it would count twice."""
    files: list[Path] = []
    seen: set[Path] = set()
    for p in inputs:
        p = Path(p)
        found = (sorted(q for q in p.rglob("*")
                        if q.is_file() and q.suffix.lower() in ENVMAP_SUFFIXES and not q.name.startswith("."))
                 if p.is_dir() else [p])
        for q in found:
            key = q.resolve()
            if key in seen:
                log.warning("environment map %s given more than once: counted once", q)
                continue
            seen.add(key)
            files.append(q)
    return files


def augmentation_rotations(rotations: int = 1, tilt_deg: float = 0.0) -> list[np.ndarray]:
    """The augmentation rotations: ``R_y(2πk/N)`` for k < N, and with tilt > 0 also ``R_x(±tilt) R_y(2πk/N)``."""
    if int(rotations) != rotations or rotations < 1:
        raise ReflectmmError(f"--rotations must be an integer ≥ 1, got {rotations}")
    if not math.isfinite(tilt_deg) or not 0.0 <= tilt_deg <= 90.0:
        raise ReflectmmError(f"--tilt must be in [0, 90] degrees, got {tilt_deg}")
    out = []
    t = math.radians(tilt_deg)
    for k in range(int(rotations)):
        Ry = rotation_y(2.0 * math.pi * k / rotations)
        out.append(Ry)
        if t > 0:
            out.append(rotation_x(t) @ Ry)
            out.append(rotation_x(-t) @ Ry)
    return out


def augment_sh(coeffs: np.ndarray, rotations: list[np.ndarray]) -> np.ndarray:
    """(M, C, n) coefficients → (M·len(rotations), C, n), map-major: sample ``i·R + r`` is map i, rotation r."""
    coeffs = np.asarray(coeffs, dtype=np.float64)
    order = sh_order(coeffs.shape[-1])
    mats = np.stack([sh_rotation(R, order) for R in rotations])  # (R, n, n)
    out = np.einsum("rij,mcj->mrci", mats, coeffs)
    return out.reshape(-1, *coeffs.shape[1:])


def normalise_sh(coeffs: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Divide each channel by its own 0-th coefficient. (S, 3, n) → (normalised, dc (S, 3)).

    Raises if any 0-th coefficient is ≤ 0 (a map with no positive mean radiance in some channel).
    """
    dc = coeffs[..., 0].copy()
    if (dc <= 0).any():
        raise ReflectmmError("light model: a sample has a non-positive 0-th SH coefficient (black channel)")
    return coeffs / dc[..., None], dc


def fit_light_pca(samples: np.ndarray, components: int, log: Callable[[str], Any] | None = None
                  ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """PCA of (S, F) samples. Returns (mean, bases (k, F), sigma, explained_variance, ratio).

    k = min(components, S − 1, numerical rank); a message goes to ``log`` when that caps the request.
    Each basis is signed so that its largest-magnitude entry is positive (deterministic output).
    """
    X = np.asarray(samples, dtype=np.float64)
    S, F = X.shape
    mean = X.mean(0)
    Xc = X - mean
    if S > 1:
        _, s, Vt = np.linalg.svd(Xc, full_matrices=False)
    else:
        s, Vt = np.zeros(0), np.zeros((0, F))
    # rank relative to the samples' own scale too: rotating a constant map only adds round-off (~1e-16)
    scale = max(float(s[0]) if s.size else 0.0, float(np.abs(X).max()) * math.sqrt(S) if X.size else 0.0)
    tol = scale * max(S, F) * np.finfo(np.float64).eps
    rank = int((s > tol).sum()) if s.size and s[0] > 0 else 0
    k = min(int(components), rank)
    if k < components and log is not None:
        log(f"build-light-pca: {components} components requested, the data supports {k} "
            f"({S} samples, rank {rank}); keeping {k}")
    Vt = Vt[:k].copy()
    for i in range(k):
        j = int(np.argmax(np.abs(Vt[i])))
        if Vt[i, j] < 0:
            Vt[i] = -Vt[i]
    var = s[:k] ** 2 / max(S - 1, 1)
    total = float((s ** 2).sum() / max(S - 1, 1))
    ratio = var / total if total > 0 else np.zeros(k)
    return mean, Vt, np.sqrt(var), var, ratio


def build_light_model(maps: Iterable[str | Path | np.ndarray], *, order: int = 8, rotations: int = 1,
                      tilt: float = 0.0, components: int = 80, quadrature: str = "fejer",
                      log: Callable[[str], Any] | None = None, reader: Callable[[Path], np.ndarray] | None = None,
                      progress: Callable[[Iterable], Iterable] | None = None
                      ) -> tuple[LightModel, list[tuple[str, str]]]:
    """Library entry of ``build-light-pca``.

    Args:
        maps: paths of equirectangular HDR maps (EXR/HDR, any size; read with ``reader``, default
            :func:`reflectmm_cli.artifacts.read_image`) or (H, W, C) arrays.
        order, rotations, tilt, components, quadrature: see the module docstring / CLI.
        log: callable receiving human-readable messages (skipped maps, capped components).
    Returns:
        (model, skipped) where skipped lists (name, reason) of maps that could not be used.
    Raises:
        ReflectmmError if no map is usable.
    """
    if reader is None:
        from reflectmm_cli.artifacts import read_image as reader
    log = log or (lambda msg: None)
    if int(components) != components or components < 1:
        raise ReflectmmError(f"build-light-pca: --components must be an integer ≥ 1, got {components} "
                             f"(a light model of 0 components is only its mean)")
    rots = augmentation_rotations(rotations, tilt)
    coeffs, names, skipped = [], [], []
    items = list(maps)
    for item in (progress(items) if progress else items):
        name = str(item) if not isinstance(item, np.ndarray) else f"<array {len(names) + len(skipped)}>"
        try:
            img = envmap_rgb(item if isinstance(item, np.ndarray) else reader(Path(item)))
            K = project_envmap(img, order, quadrature=quadrature)
            if (K[:, 0] <= 0).any():
                raise ReflectmmError("a colour channel is entirely black")
        except ReflectmmError as e:
            msg = str(e)
            if msg.startswith(name + ": "):  # the reader already names the file
                msg = msg[len(name) + 2:]
            skipped.append((name, msg))
            log(f"build-light-pca: skipping {name}: {msg}")
            continue
        except Exception as e:  # unreadable file of any other kind: report, keep the rest
            skipped.append((name, f"{type(e).__name__}: {e}"))
            log(f"build-light-pca: skipping {name}: {type(e).__name__}: {e}")
            continue
        coeffs.append(K)
        names.append(name)
    if not coeffs:
        raise ReflectmmError(f"build-light-pca: none of the {len(items)} environment maps is usable"
                             + (f" (first problem: {skipped[0][0]}: {skipped[0][1]})" if skipped else ""))
    C = np.stack(coeffs)  # (M, 3, n)
    A = augment_sh(C, rots)  # (S, 3, n)
    Xn, dc = normalise_sh(A)
    notes: list[str] = []
    mean, bases, sigma, var, ratio = fit_light_pca(Xn.reshape(Xn.shape[0], -1), components, notes.append)
    if bases.shape[0] == 0:
        raise ReflectmmError(
            f"build-light-pca: the {len(coeffs)} usable map(s) x {len(rots)} rotation(s) give {Xn.shape[0]} "
            f"sample(s) that do not vary (after normalising each by its mean colour), so a light model would have "
            f"0 components; give more distinct environment maps or --rotations > 1")
    for note in notes:  # the cap on the component count, once there is a model to cap
        log(note)
    model = LightModel(order=int(order), mean=mean, bases=bases, sigma=sigma, explained_variance=var,
                       explained_variance_ratio=ratio, dc=dc,
                       sample_map=np.repeat(np.arange(len(coeffs)), len(rots)),
                       sample_rotation=np.tile(np.stack(rots), (len(coeffs), 1, 1)), map_names=names)
    return model, skipped


def light_model_arrays(model: LightModel) -> dict[str, np.ndarray]:
    """Arrays of the ``light-model`` artifact."""
    return {
        "order": np.array(model.order, dtype=np.int64),
        "mean": model.mean.astype(np.float64),
        "bases": model.bases.astype(np.float64),
        "sigma": model.sigma.astype(np.float64),
        "explained_variance": model.explained_variance.astype(np.float64),
        "explained_variance_ratio": model.explained_variance_ratio.astype(np.float64),
        "dc": model.dc.astype(np.float64),
        "dc_mean": model.dc.mean(0).astype(np.float64),
        "sample_map": model.sample_map.astype(np.int64),
        "sample_rotation": model.sample_rotation.astype(np.float64),
        "map_names": np.array(model.map_names, dtype=str),
    }


def light_model_from_arrays(arrays) -> LightModel:
    """Inverse of :func:`light_model_arrays` (accepts an Artifact, a dict or an NpzFile)."""
    get = (lambda k: arrays[k])
    try:
        order = int(np.asarray(get("order")))
        mean = np.asarray(get("mean"), dtype=np.float64)
        bases = np.asarray(get("bases"), dtype=np.float64)
        sigma = np.asarray(get("sigma"), dtype=np.float64)
    except KeyError as e:
        raise ReflectmmError(f"light model: missing array {e}") from None
    except (TypeError, ValueError) as e:
        raise ReflectmmError(f"light model: corrupt array ({type(e).__name__}: {e})") from None
    F = 3 * (order + 1) ** 2
    if mean.shape != (F,) or bases.ndim != 2 or bases.shape[1] != F or sigma.shape != (bases.shape[0],):
        raise ReflectmmError(f"light model: inconsistent shapes (order {order}, mean {mean.shape}, "
                             f"bases {bases.shape}, sigma {sigma.shape})")

    def opt(k, default):
        try:
            return np.asarray(get(k))
        except (KeyError, Exception):
            return default

    k = bases.shape[0]
    return LightModel(order=order, mean=mean, bases=bases, sigma=sigma,
                      explained_variance=opt("explained_variance", sigma ** 2),
                      explained_variance_ratio=opt("explained_variance_ratio", np.zeros(k)),
                      dc=opt("dc", np.zeros((0, 3))), sample_map=opt("sample_map", np.zeros(0, np.int64)),
                      sample_rotation=opt("sample_rotation", np.zeros((0, 3, 3))),
                      map_names=[str(s) for s in opt("map_names", np.array([], dtype=str))])


def _as_model(model) -> LightModel:
    if isinstance(model, LightModel):
        return model
    if hasattr(model, "arrays"):
        return light_model_from_arrays(model.arrays)
    if isinstance(model, (str, Path)):
        from reflectmm_cli.artifacts import read_artifact

        return light_model_from_arrays(read_artifact(model, LIGHT_MODEL_KIND).arrays)
    return light_model_from_arrays(model)


def light_from_coeffs(model, gamma, z=None):
    """SH lighting from PCA coefficients: ``K = z[c] · (mean + Σ_k γ_k σ_k b_k)``.

    Args:
        model: a :class:`LightModel`, a ``light-model`` Artifact, its path, or its arrays.
        gamma: (..., k') coefficients in units of σ (k' ≤ k uses the first k' components; k' = 0 → mean).
        z: (..., 3) per-channel scale (the 0-th coefficient of each channel), or None for 1.
    Returns:
        (..., 3, (L+1)²) SH coefficients (numpy, or torch — differentiable — if gamma or z is a tensor).
    """
    m = _as_model(model)
    n = m.n_coeffs
    if any_torch(gamma, z):
        import torch

        dev = device_of(gamma, z)
        g = gamma if any_torch(gamma) else torch.as_tensor(np.asarray(gamma, dtype=np.float64), device=dev)
        dt = g.dtype if g.is_floating_point() else torch.float32
        g = g.to(dt)
        kp = g.shape[-1]
        if kp > m.n_components:
            raise ReflectmmError(f"light_from_coeffs: gamma has {kp} coefficients, the model has {m.n_components}")
        B = torch.as_tensor(m.bases[:kp] * m.sigma[:kp, None], dtype=dt, device=g.device)
        mu = torch.as_tensor(m.mean, dtype=dt, device=g.device)
        x = (mu + g @ B).reshape(*g.shape[:-1], 3, n)
        if z is not None:
            zt = z.to(dt) if any_torch(z) else torch.as_tensor(np.asarray(z), dtype=dt, device=g.device)
            if zt.shape[-1] != 3:
                raise ReflectmmError(f"light_from_coeffs: z must have shape (..., 3), got {tuple(zt.shape)}")
            x = x * zt[..., None]
        return x
    g = np.asarray(gamma, dtype=np.float64)
    if g.ndim == 0:
        raise ReflectmmError("light_from_coeffs: gamma must have shape (..., k)")
    kp = g.shape[-1]
    if kp > m.n_components:
        raise ReflectmmError(f"light_from_coeffs: gamma has {kp} coefficients, the model has {m.n_components}")
    if not np.isfinite(g).all():
        raise ReflectmmError("light_from_coeffs: gamma contains NaN or inf")
    x = (m.mean + g @ (m.bases[:kp] * m.sigma[:kp, None])).reshape(*g.shape[:-1], 3, n)
    if z is not None:
        za = np.asarray(z, dtype=np.float64)
        if za.shape[-1:] != (3,):
            raise ReflectmmError(f"light_from_coeffs: z must have shape (..., 3), got {za.shape}")
        x = x * za[..., None]
    return x


def _tonemap(img: np.ndarray, level: float) -> np.ndarray:
    t = np.maximum(img, 0.0) / (2.0 * level)
    return linear_to_gamma(t / (1.0 + t), 2.2)


def light_model_preview(model, n_components: int = 4, width: int = 128, spread: float = 2.0) -> np.ndarray:
    """Preview image (float RGB in [0, 1]): row 0 the mean lighting, then one row per component k with
    ``mean − spread·σ_k b_k | mean | mean + spread·σ_k b_k`` as equirectangular maps (tone-mapped)."""
    m = _as_model(model)
    h = max(1, width // 2)
    level = 1.0 / math.sqrt(4.0 * math.pi)  # mean radiance of a normalised sample
    gap = 2
    kk = min(int(n_components), m.n_components)
    rows = 1 + kk
    canvas = np.ones((rows * h + (rows - 1) * gap, 3 * width + 2 * gap, 3), dtype=np.float32)

    def put(r, c, coeffs):
        img = envmap_from_sh(coeffs.reshape(3, -1), width, h)
        canvas[r * (h + gap):r * (h + gap) + h, c * (width + gap):c * (width + gap) + width] = _tonemap(img, level)

    put(0, 1, m.mean)
    for k in range(kk):
        d = spread * m.sigma[k] * m.bases[k]
        put(k + 1, 0, m.mean - d)
        put(k + 1, 1, m.mean)
        put(k + 1, 2, m.mean + d)
    return canvas
