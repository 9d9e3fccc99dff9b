"""Small inputs for the viewer's tests: a procedural face, a reflectance model with a per-vertex part and K lobes,
an equirectangular environment map."""
from __future__ import annotations

from pathlib import Path

import numpy as np

from reflectmm_cli.artifacts import write_artifact, write_exr
from reflectmm_cli.geometry import procedural_face_model, save_face_model
from reflectmm_cli.model import add_vertex_model, fit_reflectance_pca, model_arrays

EXPONENTS = {1: [16.0], 3: [1.0, 8.0, 64.0], 5: [1.0, 4.0, 16.0, 64.0, 256.0]}


def face_model(path: Path, n_vertices: int = 6000):
    fm = procedural_face_model(n_vertices=n_vertices, n_shape=2, n_exp=2, seed=0)
    save_face_model(fm, path)
    return fm


def smooth_maps(rng, S: int, k: int):
    """Albedo (3,S,S) and weights (k,S,S) with structure at a few scales (so that β changes what one sees)."""
    yy, xx = np.mgrid[0:S, 0:S] / S
    def field(c):
        f = np.zeros((S, S))
        for _ in range(4):
            fx, fy, ph = rng.uniform(0.5, 4, 2).tolist() + [rng.uniform(0, 6.3)]
            f += np.sin(2 * np.pi * (fx * xx + fy * yy) + ph)
        return f / 4
    alb = np.stack([0.45 + 0.15 * field(c) for c in range(3)]) * np.array([1.0, 0.8, 0.7])[:, None, None]
    w = np.stack([np.clip(0.25 / k + 0.08 * field(c) / k, 0, None) for c in range(k)])
    return alb.astype(np.float32), w.astype(np.float32)


def reflectance_model(path: Path, fm, n_lobes: int = 3, n_ids: int = 6, S: int = 64, seed: int = 0) -> Path:
    rng = np.random.default_rng(seed)
    maps = [smooth_maps(rng, S, n_lobes) for _ in range(n_ids)]
    m = fit_reflectance_pca([a for a, _ in maps], [w for _, w in maps], np.array(EXPONENTS[n_lobes]),
                            components=n_ids - 1, ids=[f"{i:03d}" for i in range(n_ids)])
    add_vertex_model(m, fm.uv)
    write_artifact(path, "reflectance-model", model_arrays(m))
    return path


def envmap(path: Path, width: int = 128) -> Path:
    """A sky with a warm sun-like blob and a cool side: strong low bands and some detail."""
    h = width // 2
    th = (np.arange(h) + 0.5) / h * np.pi
    ph = (np.arange(width) + 0.5) / width * 2 * np.pi
    T, P = np.meshgrid(th, ph, indexing="ij")
    d = np.stack([np.sin(T) * np.sin(P), np.cos(T), np.sin(T) * np.cos(P)], -1)  # +y up
    sun = np.exp(-((d - np.array([0.5, 0.6, 0.62])) ** 2).sum(-1) / 0.08)
    img = np.stack([0.3 + 2.0 * sun, 0.35 + 1.6 * sun, 0.5 + 1.0 * sun], -1) * (0.6 + 0.4 * np.clip(d[..., 1], 0, 1))[..., None]
    img[..., 2] += 0.3 * np.clip(-d[..., 0], 0, 1)
    write_exr(path, {"R": img[..., 0].astype(np.float32), "G": img[..., 1].astype(np.float32),
                     "B": img[..., 2].astype(np.float32)})
    return path
