"""Ground-truth skin reflectance in UV space, driven by the face model's 68 landmarks.

Per identity, maps of size S×S (texel ``(row, col)`` ↔ ``u = (col + ½)/S``, ``v = (row + ½)/S``, row 0 at the
forehead; docs/pipeline.md):

* ``albedo (3, S, S)``: linear diffuse RGB from a two-pigment absorption model
  ``c = c0 · exp(−m·k_mel − h·k_hb)`` (melanin m sets the tone from light to dark skin, haemoglobin h the
  redness), with redder lips and cheeks, darker brows, a slight darkening at the jaw line and low-frequency
  mottling;
* ``roughness (S, S)``: GGX width α — low (sharp highlights) on the nose tip, nose ridge and forehead, high on
  the cheeks and brows;
* ``spec_intensity (S, S)``: specular scale ρ — strong on the nose and forehead (oily T-zone), weak on cheeks;
* ``spec_albedo (S, S)``: ρ × the GGX directional albedo at normal view (comparable to Σ w_i);
* ``weights (3, S, S)``: 3-lobe weights for exponents (1, 8, 64) — the NNLS fit of the GGX lobe at normal view
  (:func:`reflectmm_cli.synth.ggx.fit_lobes_to_ggx`).  In ``model`` mode these (plus a broad p = 1 sheen) *are*
  the rendering BRDF (exact) and ``spec_albedo = Σ w``; in ``ggx`` mode they are only the closest 3-lobe
  reference.

Facial features (``features=``): ``"plain"`` (the default) paints the eyes a uniform grey and leaves the rest to
the regions above; ``"painted"`` adds what a face detector's shape regression locks onto — a white sclera, a dark
iris and pupil, the upper lid's lash line, the dark line between the lips and the nostrils
(:func:`paint_features`; docs/synthetic.md, "Painted features").  Albedo only: no geometry and no specular change.

Regions are soft masks in UV space built from the landmarks' UV coordinates (polygons and thickened polylines,
blurred), so any face model with UVs and iBUG landmarks works.

Two skin models (``skin=``): ``"single"`` (the default, one GGX lobe per texel, as above) and ``"two-lobe"``: per
texel a mix of a sharp and a broad GGX lobe, ``ρ · ((1 − m) · GGX(α_sharp) + m · GGX(α_broad))``, the structure of
the dual-lobe skin specular of production skin shaders (docs/synthetic.md, "Two-lobe skin", for the sources).  The
base width α of the single model sets both lobes (``α_sharp = k_s · α``, ``α_broad = k_b · α``), the broad-lobe
weight ``m`` is lower on the oily T-zone and nose tip and higher on the cheeks, and ``k_s``, ``k_b`` and the mean
``m`` vary per identity (:class:`TwoLobeParams`).  ρ is rescaled per texel so that the mix has the single model's
specular albedo at normal view (only the lobe's shape changes, not how much it reflects).  In that model ``roughness`` holds α_sharp, ``roughness_broad``
α_broad and ``lobe_mix`` m; ``spec_albedo`` and the 3-lobe ``weights`` are those of the mix.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from reflectmm_cli.errors import ReflectmmError
from reflectmm_cli.shading.brdf import DEFAULT_EXPONENTS
from reflectmm_cli.synth.ggx import SKIN_F0, fit_lobes_to_ggx, ggx_specular_albedo

__all__ = ["SKIN_MODELS", "FEATURES", "SkinParams", "TwoLobeParams", "SkinMaps", "region_masks", "sample_skin_params",
           "sample_two_lobe_params", "skin_maps", "two_lobe_specular_albedo", "paint_features"]

#: The skin models of ``synth multipie --skin`` / ``synth wild --skin`` (the first is the default).
SKIN_MODELS = ("single", "two-lobe")

#: The facial features of ``synth multipie --features`` (the first is the default).
FEATURES = ("plain", "painted")


# absorption per unit pigment (R, G, B): melanin absorbs more towards blue, haemoglobin mostly green/blue
_C0 = np.array([0.72, 0.60, 0.52])
_K_MEL = np.array([1.5, 2.0, 2.5])
_K_HB = np.array([0.25, 2.0, 1.6])


@dataclass
class SkinParams:
    """Scalar parameters of one identity's skin (drawn by :func:`sample_skin_params`)."""

    melanin: float          # 0.02 (very light) … 1.0 (very dark)
    haemoglobin: float      # 0.04 … 0.14
    oiliness: float         # global specular scale, 0.7 … 1.4
    roughness_scale: float  # global α scale, 0.85 … 1.15
    brow_darkness: float    # albedo factor inside the brows, 0.25 … 0.6
    seed: int               # seed of the low-frequency variation

    def to_dict(self) -> dict:
        return dict(self.__dict__)


#: Two-lobe skin: ranges of the per-identity draws (docs/synthetic.md, "Two-lobe skin").  The centres are the
#: defaults of Unreal Engine's subsurface-profile dual specular (perceptual roughness × 0.75 and × 1.30, i.e. GGX
#: α × 0.5625 and × 1.69, broad-lobe weight ("lobe mix") 0.85).
SHARP_SCALE_RANGE = (0.45, 0.70)
BROAD_SCALE_RANGE = (1.40, 2.00)
BROAD_WEIGHT_RANGE = (0.75, 0.92)
#: Clip ranges of the two widths and of the broad-lobe weight in every texel.
SHARP_ALPHA_RANGE = (0.08, 0.45)
BROAD_ALPHA_RANGE = (0.30, 1.0)
LOBE_MIX_RANGE = (0.30, 0.97)


@dataclass
class TwoLobeParams:
    """Per-identity parameters of the two-lobe skin (drawn by :func:`sample_two_lobe_params`)."""

    sharp_scale: float   # α_sharp = sharp_scale · α (α: the single model's width map)
    broad_scale: float   # α_broad = broad_scale · α
    broad_weight: float  # weight m of the broad lobe on plain skin (lower on the T-zone, higher on the cheeks)
    seed: int            # seed of the low-frequency variation of m

    def to_dict(self) -> dict:
        return dict(self.__dict__)


@dataclass
class SkinMaps:
    albedo: np.ndarray          # (3, S, S) float32
    roughness: np.ndarray       # (S, S) float32, GGX α (two-lobe: α of the sharp lobe)
    spec_intensity: np.ndarray  # (S, S) float32, ρ
    spec_albedo: np.ndarray     # (S, S) float32
    weights: np.ndarray         # (3, S, S) float32 for DEFAULT_EXPONENTS
    regions: dict[str, np.ndarray]
    params: SkinParams
    skin: str = "single"
    roughness_broad: np.ndarray | None = None  # (S, S) float32, two-lobe only: α of the broad lobe
    lobe_mix: np.ndarray | None = None         # (S, S) float32, two-lobe only: weight m of the broad lobe
    two_lobe: TwoLobeParams | None = None
    features: str = "plain"


def sample_skin_params(rng: np.random.Generator, tone: float | None = None) -> SkinParams:
    """Draw one identity's skin parameters; ``tone`` in [0, 1] fixes the melanin (0 light … 1 dark)."""
    t = rng.uniform(0.0, 1.0) if tone is None else float(tone)
    melanin = 0.03 * (1.0 / 0.03) ** (t ** 1.2)   # log-spaced 0.03 … 1.0
    return SkinParams(melanin=float(melanin), haemoglobin=float(rng.uniform(0.04, 0.14)),
                      oiliness=float(rng.uniform(0.7, 1.4)), roughness_scale=float(rng.uniform(0.85, 1.15)),
                      brow_darkness=float(rng.uniform(0.25, 0.6)), seed=int(rng.integers(0, 2**31 - 1)))


def sample_two_lobe_params(rng: np.random.Generator) -> TwoLobeParams:
    """Draw one identity's two-lobe parameters (uniform in the ranges above)."""
    return TwoLobeParams(sharp_scale=float(rng.uniform(*SHARP_SCALE_RANGE)),
                         broad_scale=float(rng.uniform(*BROAD_SCALE_RANGE)),
                         broad_weight=float(rng.uniform(*BROAD_WEIGHT_RANGE)), seed=int(rng.integers(0, 2**31 - 1)))


def two_lobe_params_for(params: SkinParams) -> TwoLobeParams:
    """The two-lobe parameters of an identity, from its own stream (seeded by ``params.seed``), so that drawing
    them changes none of the draws of the single model."""
    return sample_two_lobe_params(np.random.default_rng([int(params.seed), 0x2B0B]))


def two_lobe_specular_albedo(alpha_sharp, alpha_broad, lobe_mix, spec_intensity=1.0, f0: float = SKIN_F0):
    """Directional albedo at normal view of the two-lobe specular: ``ρ ((1 − m) A(α_sharp) + m A(α_broad))`` with
    ``A`` the single GGX lobe's (:func:`reflectmm_cli.synth.ggx.ggx_specular_albedo`) — the BRDF is linear in
    its lobes, so the closed form of the mix is the mix of the closed forms."""
    m = np.asarray(lobe_mix, np.float64)
    return np.asarray(spec_intensity, np.float64) * ((1.0 - m) * ggx_specular_albedo(alpha_sharp, 1.0, f0)
                                                     + m * ggx_specular_albedo(alpha_broad, 1.0, f0))


def two_lobe_maps(R: dict[str, np.ndarray], alpha: np.ndarray, tl: TwoLobeParams, iod: float
                  ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(α_sharp, α_broad, m) of the two-lobe skin from the single model's width map ``alpha`` and the regions.

    The broad-lobe weight ``m`` drops on the oily, sharp T-zone (nose tip −0.35, nose −0.2, forehead −0.15, chin
    −0.05) and rises on the cheeks (+0.08) and brows (+0.1), around the identity's ``broad_weight``, with a
    low-frequency variation (±0.04); every value is clipped to the ranges above.
    """
    size = alpha.shape[-1]
    rng = np.random.default_rng(tl.seed)
    n = _low_freq(rng, size, 0.3 * iod)
    a_s = np.clip(tl.sharp_scale * alpha, *SHARP_ALPHA_RANGE)
    a_b = np.clip(tl.broad_scale * alpha, *BROAD_ALPHA_RANGE)
    m = tl.broad_weight - 0.35 * R["nose_tip"] - 0.2 * R["nose"] - 0.15 * R["forehead"] - 0.05 * R["chin"] \
        + 0.08 * R["cheeks"] + 0.1 * R["brows"] + 0.04 * n
    return a_s, a_b, np.clip(m, *LOBE_MIX_RANGE)


def _px(uv: np.ndarray, size: int) -> np.ndarray:
    """UV → texel coordinates (x = col, y = row) in the pixel-centre convention."""
    return np.asarray(uv, np.float64) * size - 0.5


def _blur(mask: np.ndarray, sigma_px: float) -> np.ndarray:
    import cv2

    if sigma_px <= 0.3:
        return mask
    k = int(2 * math.ceil(3 * sigma_px) + 1)
    return cv2.GaussianBlur(mask, (k, k), sigma_px, borderType=cv2.BORDER_REPLICATE)


def _poly(size: int, pts: np.ndarray, shift: int = 4) -> np.ndarray:
    import cv2

    m = np.zeros((size, size), np.float32)
    cv2.fillPoly(m, [np.round(pts * (1 << shift)).astype(np.int32)], 1.0, lineType=cv2.LINE_AA, shift=shift)
    return m


def _polyline(size: int, pts: np.ndarray, thickness: float, shift: int = 4) -> np.ndarray:
    import cv2

    m = np.zeros((size, size), np.float32)
    cv2.polylines(m, [np.round(pts * (1 << shift)).astype(np.int32)], False, 1.0,
                  thickness=max(1, int(round(thickness))), lineType=cv2.LINE_AA, shift=shift)
    return m


def _disc(size: int, centre: np.ndarray, radius: float) -> np.ndarray:
    yy, xx = np.mgrid[0:size, 0:size].astype(np.float64)
    r = np.hypot(xx - centre[0], yy - centre[1])
    return np.clip((radius - r) / max(radius * 0.5, 1e-6) + 0.5, 0, 1).astype(np.float32)


def region_masks(landmark_uv: np.ndarray, size: int) -> dict[str, np.ndarray]:
    """Soft region masks (S, S) in [0, 1] from the 68 iBUG landmarks' UV coordinates.

    Regions: ``lips``, ``brows``, ``eyes``, ``nose_tip``, ``nose`` (ridge and alae), ``forehead``, ``cheeks``,
    ``chin``, ``jaw`` (near the face outline).  Sizes scale with the inter-ocular distance in UV.
    """
    lm = np.asarray(landmark_uv, np.float64)
    if lm.shape != (68, 2) or not np.all(np.isfinite(lm)):
        raise ReflectmmError(f"skin maps need 68 finite landmark UVs, got shape {lm.shape}")
    p = _px(lm, size)
    iod = float(np.linalg.norm(p[36] - p[45]))
    if iod < 2.0:
        raise ReflectmmError(f"landmark UVs are degenerate (inter-ocular distance {iod:.2f} texels at S={size})")
    soft = 0.06 * iod
    m: dict[str, np.ndarray] = {}
    m["lips"] = _blur(_poly(size, p[48:60]), soft * 0.6)
    m["brows"] = _blur(_polyline(size, p[17:22], 0.12 * iod) + _polyline(size, p[22:27], 0.12 * iod), soft * 0.5)
    m["eyes"] = _blur(_poly(size, p[36:42]) + _poly(size, p[42:48]), soft * 0.3)
    tip = p[30]
    m["nose_tip"] = _blur(_disc(size, tip, 0.17 * iod), soft)
    m["nose"] = _blur(np.maximum(_polyline(size, p[27:31], 0.16 * iod), _poly(size, p[[31, 32, 33, 34, 35, 30]])),
                      soft)
    brow_y = p[17:27, 1].min()
    top = brow_y - 0.95 * iod
    x0, x1 = p[17, 0], p[26, 0]
    fh = np.array([[x0, brow_y - 0.15 * iod], [x1, brow_y - 0.15 * iod], [x1 - 0.1 * iod, top],
                   [x0 + 0.1 * iod, top]])
    m["forehead"] = _blur(_poly(size, fh), soft * 2)
    cheeks = np.zeros((size, size), np.float32)
    for eye, corner, jaw in ((p[36:42].mean(0), p[48], p[3]), (p[42:48].mean(0), p[54], p[13])):
        c = 0.45 * eye + 0.35 * corner + 0.2 * jaw
        cheeks = np.maximum(cheeks, _disc(size, c, 0.33 * iod))
    m["cheeks"] = _blur(cheeks, soft * 2.5)
    chin_c = 0.6 * p[8] + 0.4 * p[57]
    m["chin"] = _blur(_disc(size, chin_c, 0.28 * iod), soft * 1.5)
    m["jaw"] = _blur(_polyline(size, p[0:17], 0.25 * iod), soft * 3)
    return {k: np.clip(v, 0, 1).astype(np.float32) for k, v in m.items()}


def _low_freq(rng: np.random.Generator, size: int, scale_px: float) -> np.ndarray:
    """Zero-mean, unit-std smooth random field (Gaussian-blurred white noise)."""
    f = _blur(rng.normal(size=(size, size)).astype(np.float32), scale_px)
    s = float(f.std())
    return (f - f.mean()) / (s if s > 0 else 1.0)


def skin_maps(landmark_uv: np.ndarray, params: SkinParams, size: int = 256, *, f0: float = SKIN_F0,
              exponents=DEFAULT_EXPONENTS, brdf: str = "ggx", skin: str = "single",
              features: str = "plain") -> SkinMaps:
    """The reflectance maps of one identity (see the module docstring); deterministic in (landmarks, params).

    ``brdf="model"``: the weights are the rendering BRDF; on top of the GGX fit they get a broad-lobe "sheen"
    ``w_1 = 0.01 · (1 + cheeks + ½ chin) · oiliness`` (the fit alone leaves the p = 1 lobe at 0 almost
    everywhere, which would make an exact-recovery test of that lobe vacuous) and ``spec_albedo = Σ w``.
    """
    if brdf not in ("ggx", "model"):
        raise ReflectmmError(f"brdf must be 'ggx' or 'model', got {brdf!r}")
    if skin not in SKIN_MODELS:
        raise ReflectmmError(f"skin must be one of {', '.join(SKIN_MODELS)}, got {skin!r}")
    if features not in FEATURES:
        raise ReflectmmError(f"features must be one of {', '.join(FEATURES)}, got {features!r}")
    if size < 16:
        raise ReflectmmError(f"--uv-size must be ≥ 16, got {size}")
    R = region_masks(landmark_uv, size)
    rng = np.random.default_rng(params.seed)
    iod = float(np.linalg.norm(_px(landmark_uv, size)[36] - _px(landmark_uv, size)[45]))
    n1 = _low_freq(rng, size, 0.35 * iod)
    n2 = _low_freq(rng, size, 0.12 * iod)
    n3 = _low_freq(rng, size, 0.25 * iod)

    mel = params.melanin * np.exp(0.12 * n1 + 0.05 * n2) * (1 + 0.15 * R["jaw"])
    hb = params.haemoglobin * (1 + 1.2 * R["cheeks"] + 0.4 * R["nose_tip"] + 0.2 * R["chin"]) * np.exp(0.15 * n3)
    hb = hb + 0.35 * R["lips"]
    mel = mel * (1 + 0.25 * R["lips"])
    alb = _C0[:, None, None] * np.exp(-mel[None] * _K_MEL[:, None, None] - hb[None] * _K_HB[:, None, None])
    # brows: hair is darker and browner (independent of the skin's melanin)
    alb = alb * (1 - R["brows"] * (1 - params.brow_darkness * np.array([1.0, 0.85, 0.75])[:, None, None]))
    # eyes (not skin): greyish sclera, a non-skin value that solvers should not treat as skin
    alb = alb * (1 - R["eyes"]) + R["eyes"] * np.array([0.45, 0.42, 0.40])[:, None, None]
    if features == "painted":
        alb = paint_features(alb, landmark_uv, params.seed)

    rough = 0.42 + 0.06 * R["cheeks"] - 0.14 * R["nose_tip"] - 0.08 * R["nose"] - 0.07 * R["forehead"] \
        - 0.05 * R["lips"] + 0.2 * R["brows"] - 0.03 * R["chin"] - 0.2 * R["eyes"]
    rough = np.clip(rough * params.roughness_scale * np.exp(0.05 * n2), 0.12, 0.8)
    rho = 1.0 - 0.4 * R["cheeks"] + 1.0 * R["nose_tip"] + 0.5 * R["nose"] + 0.6 * R["forehead"] \
        + 0.2 * R["lips"] - 0.6 * R["brows"] + 0.2 * R["chin"] + 0.8 * R["eyes"]
    rho = np.clip(1.5 * rho * params.oiliness * np.exp(0.1 * n1), 0.05, 6.0)

    extra: dict = {}
    if skin == "two-lobe":
        tl = two_lobe_params_for(params)
        a_s, a_b, mix = two_lobe_maps(R, rough, tl, iod)
        # same specular albedo at normal view as the single model's lobe: only the lobe's shape changes
        rho = rho * ggx_specular_albedo(rough, 1.0, f0) / two_lobe_specular_albedo(a_s, a_b, mix, 1.0, f0)
        spec_alb = two_lobe_specular_albedo(a_s, a_b, mix, rho, f0)
        w = np.moveaxis((1.0 - mix)[..., None] * fit_lobes_to_ggx(a_s, rho, exponents, f0)
                        + mix[..., None] * fit_lobes_to_ggx(a_b, rho, exponents, f0), -1, 0)
        rough = a_s
        extra = dict(skin=skin, roughness_broad=a_b.astype(np.float32), lobe_mix=mix.astype(np.float32), two_lobe=tl)
    else:
        spec_alb = ggx_specular_albedo(rough, rho, f0)
        w = np.moveaxis(fit_lobes_to_ggx(rough, rho, exponents, f0), -1, 0)
    if brdf == "model":
        broad = int(np.argmin(np.asarray(exponents, np.float64)))
        w[broad] += 0.01 * (1 + R["cheeks"] + 0.5 * R["chin"]) * params.oiliness
        spec_alb = w.sum(0)
    return SkinMaps(albedo=alb.astype(np.float32), roughness=rough.astype(np.float32),
                    spec_intensity=rho.astype(np.float32), spec_albedo=spec_alb.astype(np.float32),
                    weights=w.astype(np.float32), regions=R, params=params, features=features, **extra)


#: Painted features (linear albedo; docs/synthetic.md, "Painted features").  Iris colours run from dark brown to
#: grey-blue; the darkening factors multiply the albedo under each mask.
SCLERA_ALBEDO = (0.62, 0.58, 0.55)
IRIS_BROWN = (0.10, 0.06, 0.035)
IRIS_GREY_BLUE = (0.16, 0.17, 0.19)
PUPIL_ALBEDO = 0.01
LASH_LINE_DARKENING = 0.85
MOUTH_LINE_DARKENING = 0.7
NOSTRIL_DARKENING = 0.6


def paint_features(albedo: np.ndarray, landmark_uv: np.ndarray, seed: int) -> np.ndarray:
    """The albedo ``(3, S, S)`` with eyes, lash lines, the mouth line and nostrils painted in, from the 68 iBUG
    landmarks' UV coordinates; deterministic in (albedo, landmarks, seed).

    Per eye (polygon 36–41 / 42–47 of width ``w``, corner to corner): a sclera of albedo :data:`SCLERA_ALBEDO`
    filling the polygon, an iris disc of radius 0.22 w and a pupil of radius 0.09 w at the polygon's centroid (both
    clipped to the polygon), and the upper lid's lash line (points 36–39 / 42–45, 0.035 IOD thick) darkened by
    :data:`LASH_LINE_DARKENING`.  The line between the lips (inner upper lip, points 60–64) is darkened by
    :data:`MOUTH_LINE_DARKENING`, and two discs of radius 0.05 IOD just above points 32 and 34 (the nostrils) by
    :data:`NOSTRIL_DARKENING`.  The iris colour is a per-identity mix of brown and grey-blue drawn from its own
    stream (seeded by ``seed``), so that painting changes none of the skin's draws.
    """
    alb = np.asarray(albedo, np.float64)
    size = alb.shape[-1]
    if alb.ndim != 3 or alb.shape[0] != 3 or alb.shape[1] != size:
        raise ReflectmmError(f"paint_features needs a (3, S, S) albedo, got shape {alb.shape}")
    lm = np.asarray(landmark_uv, np.float64)
    if lm.shape != (68, 2) or not np.all(np.isfinite(lm)):
        raise ReflectmmError(f"painted features need 68 finite landmark UVs, got shape {lm.shape}")
    p = _px(lm, size)
    iod = float(np.linalg.norm(p[36] - p[45]))
    rng = np.random.default_rng([int(seed), 0x1215])
    t, shade = rng.uniform(0.0, 1.0), rng.uniform(0.6, 1.4)
    iris = shade * ((1 - t ** 3) * np.asarray(IRIS_BROWN) + t ** 3 * np.asarray(IRIS_GREY_BLUE))

    def fill(a: np.ndarray, mask: np.ndarray, value) -> np.ndarray:
        return a * (1 - mask) + mask * np.asarray(value, np.float64).reshape(-1, 1, 1)

    out = alb.copy()
    for a in (36, 42):
        eye = _poly(size, p[a:a + 6])
        width = float(np.linalg.norm(p[a] - p[a + 3]))
        centre = p[a:a + 6].mean(0)
        out = fill(out, eye, SCLERA_ALBEDO)
        out = fill(out, _disc(size, centre, 0.22 * width) * eye, iris)
        out = fill(out, _disc(size, centre, 0.09 * width) * eye, PUPIL_ALBEDO)
        lash = _polyline(size, p[a:a + 4], max(1.0, 0.035 * iod))
        out = out * (1 - LASH_LINE_DARKENING * lash)
    mouth = _polyline(size, p[60:65], max(1.0, 0.03 * iod))
    out = out * (1 - MOUTH_LINE_DARKENING * mouth)
    for k in (32, 34):
        nostril = _blur(_disc(size, p[k] + np.array([0.0, -0.03 * iod]), 0.05 * iod), 0.5)
        out = out * (1 - NOSTRIL_DARKENING * nostril)
    return out
