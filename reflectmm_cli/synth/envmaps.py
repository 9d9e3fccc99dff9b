"""Procedural HDR environment maps (equirectangular, linear radiance) with a dynamic range like real captures.

Equirectangular convention: the one of :mod:`reflectmm_cli.shading.envmap` — +y up, row 0 at the zenith,
column ``j`` at azimuth ``φ = 2π (j + ½)/W − π`` with the image centre (φ = 0) looking down −z, direction
``d = (sin φ sin θ, cos θ, −cos φ sin θ)``; height = width / 2.

Kinds (chosen in turn, parameters random per map):

* ``sky``: clear sky with a sun — a blue sky brightening towards the horizon, a small bright solar disc
  (angular radius ~0.5–1.2°, radiance 10⁴–10⁵ × the sky at the zenith) with a circumsolar glow, and a ground
  lit by sun and sky (Lambertian, albedo 0.1–0.3);
* ``overcast``: the CIE overcast sky ``L ∝ (1 + 2 cos θ)/3`` (grey, slightly tinted), a brighter patch where the
  sun shines through thin cloud, dark ground — low dynamic range, as real overcast captures;
* ``indoor``: a room (walls, floor, ceiling of random colours) with 1–3 windows (rectangles of daylight,
  radiance ~20–100× the walls) and 1–4 lamps (small warm discs, 10³–10⁴× the walls);
* ``colored``: a dark room with 2–4 saturated area lights (neon-like strips/discs of different hues).

Each map depends only on (seed, index), so ``--count 10`` and ``--count 20`` share their first 10 maps.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from reflectmm_cli.color import encode_display
from reflectmm_cli.errors import ReflectmmError

__all__ = ["ENVMAP_KINDS", "make_envmap", "tonemap", "envmap_contact_sheet", "write_envmaps"]

ENVMAP_KINDS = ("sky", "overcast", "indoor", "colored")


def _directions(width: int) -> np.ndarray:
    from reflectmm_cli.shading import equirect_directions

    return equirect_directions(width, width // 2)


def _dir(theta: float, phi: float) -> np.ndarray:
    """Unit direction at polar angle θ from +y and azimuth φ (the equirect convention)."""
    return np.array([math.sin(phi) * math.sin(theta), math.cos(theta), -math.cos(phi) * math.sin(theta)])


def _disc(d: np.ndarray, centre: np.ndarray, radius: float, soft: float) -> np.ndarray:
    """Smooth indicator of a cone of angular ``radius`` around ``centre`` (edge width ``soft`` rad)."""
    ang = np.arccos(np.clip(d @ centre, -1.0, 1.0))
    return np.clip((radius + soft - ang) / (2 * soft), 0.0, 1.0) if soft > 0 else (ang <= radius).astype(float)


def _pixel_solid_angle(d: np.ndarray) -> np.ndarray:
    H, W = d.shape[:2]
    return (2 * math.pi / W) * (math.pi / H) * np.sqrt(np.clip(1 - d[..., 1] ** 2, 0, 1))


def _source(d: np.ndarray, centre: np.ndarray, radius: float, soft: float) -> np.ndarray:
    """A disc-shaped light source whose integrated solid angle is exact at any resolution.

    The smooth disc mask is rescaled so that Σ mask · dω equals the cone's solid angle 2π(1 − cos r); a disc
    smaller than a pixel is splatted into the nearest pixel (so a 64-pixel-wide map keeps the sun's energy)."""
    mask = _disc(d, centre, radius, soft)
    dw = _pixel_solid_angle(d)
    target = 2 * math.pi * (1 - math.cos(radius))
    got = float((mask * dw).sum())
    if got < 0.5 * target:
        mask = np.zeros(d.shape[:2])
        i = np.unravel_index(np.argmax(d @ centre), mask.shape)
        mask[i] = target / dw[i]
        return mask
    return mask * (target / got)


def _rect(d: np.ndarray, phi0: float, phi1: float, el0: float, el1: float, soft: float = 0.01) -> np.ndarray:
    """Smooth indicator of an azimuth/elevation rectangle (window)."""
    phi = np.arctan2(d[..., 0], -d[..., 2])
    el = np.arcsin(np.clip(d[..., 1], -1, 1))
    dphi = np.angle(np.exp(1j * (phi - 0.5 * (phi0 + phi1))))
    half = 0.5 * (phi1 - phi0)
    a = np.clip((half - np.abs(dphi)) / soft + 0.5, 0, 1)
    b = np.clip((el - el0) / soft + 0.5, 0, 1) * np.clip((el1 - el) / soft + 0.5, 0, 1)
    return a * b


def _window(d: np.ndarray, phi0: float, phi1: float, el0: float, el1: float) -> np.ndarray:
    """An azimuth/elevation rectangle rescaled to its exact solid angle (φ1 − φ0)(sin el1 − sin el0)."""
    mask = _rect(d, phi0, phi1, el0, el1)
    target = (phi1 - phi0) * (math.sin(el1) - math.sin(el0))
    got = float((mask * _pixel_solid_angle(d)).sum())
    return mask * (target / got) if got > 0 else mask


def _smooth_noise(rng: np.random.Generator, d: np.ndarray, order: int = 4, amp: float = 0.2) -> np.ndarray:
    """Low-frequency multiplicative variation: exp of a random low-order SH field (band-limited)."""
    from reflectmm_cli.shading import sh_basis

    Y = sh_basis(d, order)
    c = rng.normal(size=Y.shape[-1]) / np.sqrt(Y.shape[-1])
    c[0] = 0.0
    return np.exp(amp * (Y @ c))


def _sky(rng, d):
    up = d[..., 1]
    sun_el = math.radians(rng.uniform(10, 65))
    sun_phi = rng.uniform(-math.pi, math.pi)
    sun = _dir(math.pi / 2 - sun_el, sun_phi)
    zenith = np.array([0.25, 0.45, 0.95]) * rng.uniform(0.6, 1.4)
    horizon = np.array([0.85, 0.9, 1.0]) * zenith.max() * rng.uniform(1.5, 2.5)
    t = np.clip(up, 0, 1)[..., None]
    sky = horizon + (zenith - horizon) * np.sqrt(t)
    cos_sun = np.clip(d @ sun, -1, 1)
    glow = 1.0 + 4.0 * np.exp((cos_sun - 1) / 0.01) + 0.5 * np.exp((cos_sun - 1) / 0.2)
    sky = sky * glow[..., None]
    radius = math.radians(rng.uniform(0.5, 1.2))
    sun_rad = zenith.max() * 10 ** rng.uniform(4.0, 5.0) * np.array([1.0, 0.96, 0.9])
    sky = sky + _source(d, sun, radius, radius * 0.15)[..., None] * sun_rad
    # ground: Lambertian, lit by the sun (cos of its elevation) and about π × the mean sky radiance
    albedo = np.array([0.25, 0.2, 0.15]) * rng.uniform(0.5, 1.2)
    e_ground = math.sin(sun_el) * sun_rad * math.pi * radius ** 2 + math.pi * 0.5 * (zenith + horizon)
    ground = albedo * e_ground / math.pi * _smooth_noise(rng, d, 6, 0.15)[..., None]
    return np.where((up >= 0)[..., None], sky, ground)


def _overcast(rng, d):
    up = d[..., 1]
    lum = rng.uniform(0.5, 2.0)
    tint = np.array([1.0, 1.0, 1.0]) + rng.normal(0, 0.03, 3)
    sky = lum * ((1 + 2 * np.clip(up, 0, 1)) / 3)[..., None] * tint
    sun = _dir(math.radians(rng.uniform(25, 70)), rng.uniform(-math.pi, math.pi))
    sky = sky * (1 + rng.uniform(1, 4) * np.exp((np.clip(d @ sun, -1, 1) - 1) / 0.05))[..., None]
    sky = sky * _smooth_noise(rng, d, 8, 0.25)[..., None]
    ground = lum * 0.15 * np.array([0.9, 0.85, 0.8]) * _smooth_noise(rng, d, 6, 0.2)[..., None]
    return np.where((up >= 0)[..., None], sky, ground)


def _room(rng, d, wall_level):
    up = d[..., 1]
    wall = rng.uniform(0.4, 1.0, 3) * wall_level
    floor = rng.uniform(0.2, 0.6, 3) * wall_level
    ceiling = np.full(3, rng.uniform(0.6, 1.0)) * wall_level
    img = np.where((up > 0.6)[..., None], ceiling, np.where((up < -0.4)[..., None], floor, wall))
    return img * _smooth_noise(rng, d, 6, 0.3)[..., None]


def _indoor(rng, d):
    level = rng.uniform(0.05, 0.2)
    img = _room(rng, d, level)
    for _ in range(rng.integers(1, 4)):
        phi = rng.uniform(-math.pi, math.pi)
        w = math.radians(rng.uniform(15, 45))
        el0 = math.radians(rng.uniform(-10, 10))
        el1 = el0 + math.radians(rng.uniform(20, 45))
        day = level * rng.uniform(20, 100) * np.array([0.9, 0.95, 1.05])
        img = img + _window(d, phi - w / 2, phi + w / 2, el0, el1)[..., None] * day
    for _ in range(rng.integers(1, 5)):
        centre = _dir(math.radians(rng.uniform(10, 80)), rng.uniform(-math.pi, math.pi))
        r = math.radians(rng.uniform(1.5, 4))
        lamp = level * 10 ** rng.uniform(3, 4) * np.array([1.0, 0.8, 0.55])
        img = img + _source(d, centre, r, r * 0.2)[..., None] * lamp
    return img


def _colored(rng, d):
    level = rng.uniform(0.01, 0.05)
    img = _room(rng, d, level)
    hues = rng.permutation(6)[: rng.integers(2, 5)]
    for k in hues:
        hue = k / 6 + rng.uniform(-0.05, 0.05)
        rgb = np.clip(np.abs(((hue * 6 + np.array([0, 4, 2])) % 6) - 3) - 1, 0, 1)  # HSV(h,1,1) → RGB
        rgb = 0.05 + 0.95 * rgb
        bright = level * 10 ** rng.uniform(2.5, 3.8)
        if rng.random() < 0.5:
            phi = rng.uniform(-math.pi, math.pi)
            el = math.radians(rng.uniform(-20, 50))
            w = math.radians(rng.uniform(20, 60))
            mask = _window(d, phi - w / 2, phi + w / 2, el, el + math.radians(rng.uniform(2, 5)))
        else:
            centre = _dir(math.radians(rng.uniform(20, 120)), rng.uniform(-math.pi, math.pi))
            r = math.radians(rng.uniform(4, 10))
            mask = _source(d, centre, r, r * 0.3)
        img = img + mask[..., None] * rgb * bright
    return img


_MAKERS = {"sky": _sky, "overcast": _overcast, "indoor": _indoor, "colored": _colored}


def make_envmap(seed: int, index: int, width: int = 512, kind: str | None = None) -> tuple[np.ndarray, str]:
    """One procedural equirectangular map: ``(image (width/2, width, 3) float32 linear radiance, kind)``.

    ``kind`` defaults to ``ENVMAP_KINDS[index % 4]``.  Deterministic in (seed, index, width, kind).
    """
    if width < 8 or width % 2:
        raise ReflectmmError(f"envmap width must be an even number ≥ 8, got {width}")
    kind = kind or ENVMAP_KINDS[index % len(ENVMAP_KINDS)]
    if kind not in _MAKERS:
        raise ReflectmmError(f"unknown envmap kind '{kind}' (known: {', '.join(ENVMAP_KINDS)})")
    rng = np.random.default_rng([int(seed), int(index), 0x5E7])
    img = _MAKERS[kind](rng, _directions(width))
    return np.ascontiguousarray(np.maximum(img, 0.0).astype(np.float32)), kind


def tonemap(img: np.ndarray, exposure: float | None = None) -> np.ndarray:
    """Display version of an HDR image: scale so the 90th-percentile luminance maps to 0.5, Reinhard on the
    luminance (hue kept), gamma 1/2.2.  Returns float in [0, 1]."""
    wl = np.array([0.2126, 0.7152, 0.0722])
    lum = img @ wl
    if exposure is None:
        p = float(np.percentile(lum, 90))
        exposure = 0.5 / p if p > 0 else 1.0
    x = img * exposure
    lx = (x @ wl)[..., None]
    return encode_display(x / (1 + lx), "gamma", nan_to_num=False)


def envmap_contact_sheet(images: list[np.ndarray], cols: int = 4, thumb_width: int = 256) -> np.ndarray:
    """Tone-mapped thumbnails on a grid (float RGB in [0, 1])."""
    import cv2

    th = thumb_width // 2
    cols = max(1, min(cols, len(images)))
    rows = (len(images) + cols - 1) // cols
    sheet = np.zeros((rows * (th + 4) + 4, cols * (thumb_width + 4) + 4, 3), np.float32)
    for i, img in enumerate(images):
        t = cv2.resize(tonemap(img).astype(np.float32), (thumb_width, th), interpolation=cv2.INTER_AREA)
        r, c = divmod(i, cols)
        sheet[4 + r * (th + 4): 4 + r * (th + 4) + th, 4 + c * (thumb_width + 4): 4 + c * (thumb_width + 4)
              + thumb_width] = t
    return sheet


def _write_rgb_exr(path: Path, img: np.ndarray, meta: dict) -> Path:
    """Float32 R,G,B EXR (zip) with the meta JSON in ``reflectmm:meta``, atomically and byte-reproducibly.

    Written with OpenImageIO directly rather than ``artifacts.write_exr`` because the OpenEXR writer stamps the
    current time into the header (``capDate``) unless a ``DateTime`` is given; a fixed one keeps reruns
    byte-identical.
    """
    import OpenImageIO as oiio

    from reflectmm_cli.artifacts import EXR_META_ATTR, atomic_path, canonical_json

    h, w = img.shape[:2]
    spec = oiio.ImageSpec(w, h, 3, "float")
    spec.channelnames = ("R", "G", "B")
    spec.attribute("compression", "zip")
    spec.attribute("DateTime", "1980:01:01 00:00:00")
    spec.attribute(EXR_META_ATTR, canonical_json(meta))
    with atomic_path(path, suffix=".exr") as tmp:
        out = oiio.ImageOutput.create(str(tmp))
        if out is None or not out.open(str(tmp), spec):
            raise ReflectmmError(f"cannot open EXR for writing: {oiio.geterror()}", path)
        ok = out.write_image(np.ascontiguousarray(img, dtype=np.float32))
        err = out.geterror()
        out.close()
        if not ok:
            raise ReflectmmError(f"cannot write EXR: {err}", path)
    return Path(path)


def write_envmaps(out_dir: str | Path, count: int, seed: int = 0, width: int = 512, *, meta_base: dict | None = None,
                  contact_sheet: bool = True) -> list[Path]:
    """Write ``count`` maps ``env_NNNN_<kind>.exr`` (float32 R,G,B + meta) and ``contact_sheet.png``."""
    from reflectmm_cli.artifacts import write_png
    from reflectmm_cli.progress import progress

    if count < 1:
        raise ReflectmmError(f"--count must be ≥ 1, got {count}")
    out = Path(out_dir)
    made = [make_envmap(seed, i, width) for i in progress(range(count), desc="envmaps", total=count, unit="map")]
    names = {out / f"env_{i:04d}_{kind}.exr" for i, (_, kind) in enumerate(made)}
    stale = sorted(p for p in out.glob("env_*.exr") if p not in names) if out.is_dir() else []
    if stale:  # an earlier run's maps would be read with these (build-light-pca takes the folder)
        raise ReflectmmError(f"holds {len(stale)} environment map(s) that this run would not overwrite (e.g. "
                             f"{stale[0].name}: an earlier run's count or seed); give an empty --out, or remove them",
                             out)
    paths, images = [], []
    for i, (img, kind) in enumerate(made):
        meta = dict(meta_base or {})
        meta.setdefault("schema", "reflectmm.envmap/1")
        meta["envmap"] = {"kind": kind, "index": i, "seed": seed, "width": width,
                          "convention": "equirect +y up, phi=0 at -z (reflectmm_cli.shading.envmap)",
                          "units": "linear radiance"}
        p = out / f"env_{i:04d}_{kind}.exr"
        _write_rgb_exr(p, img, meta)
        paths.append(p)
        images.append(img)
    if contact_sheet:
        paths.append(write_png(out / "contact_sheet.png", envmap_contact_sheet(images)))
    return paths
