"""Render a face model with reflectance under a point light or an environment map: the library entry of
``reflectmm render`` (:func:`render_face`).

Reflectance comes from a ``reflectance-maps`` artifact (albedo (3,S,S), weights (K,S,S), exponents (K,)) or a
``reflectance-model`` artifact sampled at coefficients β (units of σ; default the mean).  Geometry is the face
model's mean, given shape/expression coefficients, or a ``geometry`` artifact's fitted vertices.  Light is a
point light (``x,y,z[:I]``, radiant intensity I, ``E = I/d²``, optional ray-traced shadows) or SH environment
light (an equirectangular EXR/HDR projected to SH, or SH coefficients from a file).
"""
from __future__ import annotations

import json
import logging
import re
from pathlib import Path

import numpy as np

from reflectmm_cli.errors import ReflectmmError
from reflectmm_cli.params import ParamError, parse_list

log = logging.getLogger("reflectmm")

__all__ = ["parse_coeffs", "parse_point_light", "load_sh", "load_reflectance", "render_face", "layer_names",
           "REFLECTANCE_AT"]


def parse_coeffs(text: str | None, what: str = "coefficients") -> np.ndarray | None:
    """``"0.5,-1,2"`` or a path to .npy/.txt/.csv/.json → 1-D float array (None stays None).  A text file may
    separate its numbers by commas, spaces or line breaks.  Values must be finite."""
    if text is None or text == "":
        return None
    p = Path(text)
    if p.suffix.lower() in (".npy", ".txt", ".json", ".csv") and p.exists():
        try:
            if p.suffix.lower() == ".npy":
                c = np.asarray(np.load(p, allow_pickle=False), dtype=np.float64).reshape(-1)
            elif p.suffix.lower() == ".json":
                c = np.asarray(json.loads(p.read_text()), dtype=np.float64).reshape(-1)
            else:
                c = np.array([float(t) for t in re.split(r"[,\s]+", p.read_text().strip()) if t], np.float64)
        except (OSError, ValueError, TypeError) as exc:
            raise ReflectmmError(f"cannot read {what} ({exc})", p) from None
        where: Path | None = p
    else:
        try:
            c = np.array(parse_list(text if "," in text else ",".join(text.split()), what, float), np.float64)
        except ParamError:
            raise ReflectmmError(f"{what}: expected comma-separated numbers or a .npy/.txt/.csv/.json file, got "
                                 f"'{text}'") from None
        where = None
    if not np.all(np.isfinite(c)):
        raise ReflectmmError(f"{what}: the coefficients must be finite (got NaN or inf)", where)
    return c


#: How far a point light may be from the origin, per axis (1 km; the default intensity grows as the squared
#: distance, which overflows float64 beyond ~1e154 mm).
POINT_LIGHT_MAX_MM = 1e6


def parse_point_light(text: str) -> tuple[np.ndarray, np.ndarray | None]:
    """``"x,y,z"`` or ``"x,y,z:I"`` or ``"x,y,z:r,g,b"`` (mm; intensity in linear pixel units × mm²)."""
    pos, _, inten = text.partition(":")
    try:
        p = np.array(parse_list(pos, "--point-light", float), dtype=np.float64)
        i = None if not inten else np.array(parse_list(inten, "--point-light", float), dtype=np.float64)
    except ParamError:
        raise ReflectmmError(f"--point-light '{text}': expected x,y,z[:I] or x,y,z:r,g,b (numbers)") from None
    if p.shape != (3,) or (i is not None and i.size not in (1, 3)) or not np.all(np.isfinite(p)):
        raise ReflectmmError(f"--point-light '{text}': expected x,y,z[:I] or x,y,z:r,g,b")
    if float(np.max(np.abs(p))) > POINT_LIGHT_MAX_MM:
        raise ReflectmmError(f"--point-light '{text}': the light must be within {POINT_LIGHT_MAX_MM:g} mm of the "
                             "origin on each axis")
    if i is not None and (not np.all(np.isfinite(i)) or np.any(i < 0)):
        raise ReflectmmError(f"--point-light '{text}': intensity must be finite and ≥ 0")
    return p, i


def load_sh(path: Path) -> np.ndarray:
    """SH coefficients (3, (L+1)²) from .npy / .txt / .json (also (n, 3)) or an NPZ with 'sh' / 'coeffs'."""
    path = Path(path)
    if not path.exists():
        raise ReflectmmError("file not found", path)
    try:
        if path.suffix.lower() == ".npy":
            a = np.load(path, allow_pickle=False)
        elif path.suffix.lower() == ".npz":
            with np.load(path, allow_pickle=False) as z:
                key = next((k for k in ("sh", "coeffs", "sh_coeffs") if k in z.files), None)
                if key is None:
                    raise ReflectmmError(f"no 'sh' or 'coeffs' array (has: {', '.join(z.files)})", path)
                a = z[key]
        elif path.suffix.lower() == ".json":
            a = np.asarray(json.loads(path.read_text()), dtype=np.float64)
        else:
            a = np.loadtxt(path, ndmin=2)
    except (OSError, ValueError) as exc:
        raise ReflectmmError(f"cannot read SH coefficients ({exc})", path) from None
    a = np.asarray(a, dtype=np.float64)
    if a.ndim == 2 and a.shape[1] == 3 and a.shape[0] != 3:
        a = a.T
    n = a.shape[-1] if a.ndim == 2 else 0
    if a.ndim != 2 or a.shape[0] != 3 or int(round(np.sqrt(n))) ** 2 != n:
        raise ReflectmmError(f"SH coefficients must be (3, (L+1)²), got {a.shape}", path)
    if not np.all(np.isfinite(a)):
        raise ReflectmmError("SH coefficients contain NaN or inf", path)
    return a


def load_reflectance(maps: Path | None, reflectance_model: Path | None, coeffs: str | None, at: str = "uv",
                     vertex_uv=None):
    """(albedo, weights, exponents) from maps or a model at β.

    ``at="uv"``: albedo (3,S,S) and weights (K,S,S); ``at="vertex"``: albedo (N,3) and weights (N,K) — the model's
    per-vertex part, or the maps sampled bilinearly at ``vertex_uv`` (N,2).
    """
    from reflectmm_cli.artifacts import read_artifact

    if at not in REFLECTANCE_AT:
        raise ReflectmmError(f"--reflectance must be one of {', '.join(REFLECTANCE_AT)}, got '{at}'")
    model = reflectance_model
    if (maps is None) == (model is None):
        raise ReflectmmError("give exactly one of --maps or --model")
    if maps is not None:
        art = read_artifact(maps, "reflectance-maps")
        a, w, e = art["albedo"], art["weights"], art["exponents"]
        if coeffs:
            raise ReflectmmError("--coeffs applies to --model only")
        for name, x in (("albedo", a), ("weights", w)):
            if not np.all(np.isfinite(x)):
                raise ReflectmmError(f"the maps' {name} contains NaN or inf", maps)
    else:
        from reflectmm_cli.model import sample_model

        art = read_artifact(model, "reflectance-model")
        beta = parse_coeffs(coeffs, "--coeffs")
        m = int(np.shape(art["sigma"])[0])
        if beta is None:
            beta = np.zeros(0)
        if beta.size > m:
            raise ReflectmmError(f"--coeffs: {beta.size} coefficients given, the model has {m}", model)
        if at == "vertex" and "vertex_albedo_mean" not in art.arrays:
            raise ReflectmmError("--reflectance vertex: the model has no per-vertex part", model)
        with np.errstate(over="ignore", invalid="ignore"):
            a, w = sample_model(art.arrays, beta if beta.size else np.zeros(1), "vertex" if at == "vertex" else "uv")
        if not (np.all(np.isfinite(a)) and np.all(np.isfinite(w))):
            raise ReflectmmError(f"--coeffs: the model's reflectance at these coefficients is not finite (largest "
                                 f"|β| {float(np.max(np.abs(beta))) if beta.size else 0.0:g} σ)", model)
        e = art["exponents"]
    a, w, e = np.asarray(a, np.float32), np.asarray(w, np.float32), np.asarray(e, np.float64).reshape(-1)
    if at == "vertex":
        if a.ndim == 3:  # maps → per vertex
            from .uv import sample_uv_map

            a, w = (np.asarray(sample_uv_map(x, np.asarray(vertex_uv, np.float64)), np.float32) for x in (a, w))
        return a, w, e
    if a.ndim != 3 or a.shape[0] != 3 or a.shape[1] != a.shape[2]:
        raise ReflectmmError(f"albedo must be (3, S, S), got {a.shape}", maps or model)
    if w.shape != (e.size,) + a.shape[1:]:
        raise ReflectmmError(f"weights must be ({e.size}, {a.shape[1]}, {a.shape[2]}), got {w.shape}", maps or model)
    return a, w, e


#: Where reflectance is looked up: the UV maps at each hit's UV, or per vertex interpolated over the triangle.
REFLECTANCE_AT = ("uv", "vertex")


def layer_names(n_lobes: int) -> tuple[str, ...]:
    """The layers of :func:`render_face` (and of the viewer): full, diffuse, specular, lobeI, albedo, sumw,
    weightI (I = 0 … n_lobes − 1)."""
    return (("full", "diffuse", "specular") + tuple(f"lobe{i}" for i in range(n_lobes)) + ("albedo", "sumw")
            + tuple(f"weight{i}" for i in range(n_lobes)))


def _layer_inputs(layer: str, albedo: np.ndarray, weights: np.ndarray) -> tuple[np.ndarray, np.ndarray] | None:
    """(albedo, weights) whose shading is the layer (shading is linear in both), or None for a reflectance layer."""
    k_axis = 0 if weights.ndim == 3 else 1  # (K,S,S) maps or (N,K) per vertex
    if layer == "full":
        return albedo, weights
    if layer == "diffuse":
        return albedo, np.zeros_like(weights)
    if layer == "specular":
        return np.zeros_like(albedo), weights
    if layer.startswith("lobe"):
        keep = np.zeros_like(weights)
        idx = [slice(None)] * weights.ndim
        idx[k_axis] = int(layer[4:])
        keep[tuple(idx)] = weights[tuple(idx)]
        return np.zeros_like(albedo), keep
    return None


def _reflectance_image(raster, triangles, albedo, weights, uv, layer: str) -> np.ndarray:
    """(H,W,3) image of a reflectance layer (albedo, Σw, one weight) at the raster's hits, 0 elsewhere."""
    from .render import surface_reflectance

    img = np.zeros(raster.mask.shape + (3,), np.float32)
    if raster.mask.any():
        c, w = surface_reflectance(raster, triangles, albedo, weights, uv)
        val = c if layer == "albedo" else np.repeat(
            (w.sum(1) if layer == "sumw" else w[:, int(layer[6:])])[:, None], 3, axis=1)
        img[raster.mask] = val
    return img


# ------------------------------------------------------------------------------------------ library

def render_face(face_model: Path, *, maps: Path | None = None, reflectance_model: Path | None = None,
                coeffs: str | None = None,
                point_light: str | None = None, envmap: Path | None = None, sh: Path | None = None,
                sh_order: int = 8, camera: str = "frontal", shadows: bool = False, shape: str | None = None,
                exp: str | None = None, geometry: Path | None = None, layer: str = "full",
                reflectance_at: str = "uv", env_rotation: float = 0.0) -> dict:
    """Library entry of ``reflectmm render``: returns image (H,W,3), mask, camera, light description.

    ``layer`` (:func:`layer_names`): the full shading, one part of it (diffuse, specular, one lobe alone) or a
    reflectance map (albedo, Σw, one lobe's weight; unshaded, no light needed beyond the one given).
    ``reflectance_at``: :data:`REFLECTANCE_AT`. ``env_rotation``: turn the environment by this many degrees
    about +y (exactly, in SH space).
    """
    from reflectmm_cli.artifacts import read_artifact
    from reflectmm_cli.geometry import (
        RayScene,
        load_face_model,
        parse_camera_spec,
        render_envmap,
        render_point_light,
        vertex_normals,
    )

    n_lights = sum(x is not None for x in (point_light, envmap, sh))
    if n_lights != 1:
        raise ReflectmmError("give exactly one light: --point-light, --envmap or --sh")
    fm = load_face_model(face_model)
    if geometry is not None:
        if shape or exp:
            raise ReflectmmError("--shape and --exp do not apply with --geometry (its fitted vertices are the face)",
                                 geometry)
        g = read_artifact(geometry, "geometry")
        verts = np.asarray(g["vertices"], dtype=np.float64)
        if verts.shape != fm.mean_shape.shape:
            raise ReflectmmError(f"geometry has {verts.shape[0]} vertices, the face model {fm.n_vertices}", geometry)
    else:
        verts = fm.vertices(parse_coeffs(shape, "--shape"), parse_coeffs(exp, "--exp"))
    albedo, weights, exps = load_reflectance(maps, reflectance_model, coeffs, reflectance_at, fm.uv)
    layers = layer_names(exps.size)
    if layer not in layers:
        raise ReflectmmError(f"--layer '{layer}': one of {', '.join(layers)}")
    cam = parse_camera_spec(camera)
    scene = RayScene(verts, fm.triangles, vertex_normals(verts, fm.triangles))
    uv = fm.uv if reflectance_at == "uv" else None
    parts = _layer_inputs(layer, albedo, weights)
    if parts is None:
        from reflectmm_cli.geometry import rasterize

        r = rasterize(scene, cam)
        return {"image": _reflectance_image(r, fm.triangles, albedo, weights, uv, layer), "mask": r.mask,
                "camera": cam, "light": {"type": "none", "layer": layer}}
    albedo, weights = parts
    light: dict = {}
    if point_light is not None:
        pos, inten = parse_point_light(point_light)
        if inten is None:
            inten = np.array([np.pi * float(pos @ pos)])  # irradiance π at the origin
        res = render_point_light(scene, cam, albedo, weights, exps, pos, inten, uv=uv, shadows=shadows)
        light = {"type": "point", "position": pos.tolist(), "intensity": np.atleast_1d(inten).tolist(),
                 "shadows": bool(shadows), "shadow_rays": res.rays}
        if shadows:
            log.info("shadow rays: %d cast, %d skipped (n·l ≤ 0)", res.rays["cast"], res.rays["skipped"])
    else:
        if shadows:
            log.warning("--shadows applies to point lights only; SH environment light has no visibility")
        if envmap is not None:
            from reflectmm_cli.shading import load_envmap, project_envmap

            K = project_envmap(load_envmap(envmap), sh_order)
            light = {"type": "envmap", "file": Path(envmap).name, "sh_order": sh_order}
        else:
            K = load_sh(sh)
            light = {"type": "sh", "file": Path(sh).name, "sh_order": int(np.sqrt(K.shape[1])) - 1}
        if env_rotation:
            from reflectmm_cli.geometry.rotations import rotation_y
            from reflectmm_cli.shading.sh import sh_order, sh_rotation

            K = K @ sh_rotation(rotation_y(np.radians(env_rotation)), sh_order(K.shape[1])).T
            light["rotation_deg"] = float(env_rotation)
        res = render_envmap(scene, cam, albedo, weights, exps, K, uv=uv)
    return {"image": res.image, "mask": res.mask, "camera": cam, "light": light}
