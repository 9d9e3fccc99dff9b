"""``synth wild``: in-the-wild-like renders with ground truth, for finetuning (docs/wild.md).

Per image: an identity (shape from the face model's prior and a skin population that differs on purpose from
``synth multipie``, :func:`sample_wild_skin`), a random expression, a head pose (yaw ±50°, pitch ±20°, roll ±10°)
seen by the Deep3DFaceRecon camera (focal 1015, centre 112, 224², model in mm at 1 m), one of a pool of
procedural HDR maps (:mod:`reflectmm_cli.synth.envmaps`) randomly rotated and scaled, rendered with Lambert + GGX
under that full map with ray-traced self-shadowing (:mod:`reflectmm_cli.synth.wild_light` says exactly what is
modelled), the map behind the head, an optional hand/hat-like occluder, sensor noise, display encoding and 8-bit
PNG.  Reflectance is per vertex of the face model, interpolated with the hit's barycentrics (what a G-buffer
shader sees).
"""
from __future__ import annotations

import logging
import math
import time
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Callable

import numpy as np

from reflectmm_cli.color import encode_display
from reflectmm_cli.errors import ReflectmmError
from reflectmm_cli.geometry.rotations import euler_yxz_to_matrix
from reflectmm_cli.shading.brdf import DEFAULT_EXPONENTS
from reflectmm_cli.synth.ggx import (SKIN_F0, fit_lobes_to_ggx, ggx_directional, ggx_specular_albedo,
                                     ggx_two_lobe_directional)
from reflectmm_cli.synth.skin import (SKIN_MODELS, region_masks, sample_two_lobe_params, two_lobe_maps,
                                      two_lobe_specular_albedo)
from reflectmm_cli.synth.wild_light import SplitMap, _hammersley, ggx_view_albedo, sample_ggx_h, split_map

__all__ = ["WildConfig", "WildSkin", "head_pose_rotation", "sample_wild_skin", "WildScene", "sample_scene",
           "IdentityGeometry", "vertex_ambient_occlusion", "vertex_lobe_visibility", "identity_expression",
           "render_wild", "reference_radiance", "encode_codes", "synth_wild", "ENCODINGS"]

log = logging.getLogger("reflectmm")

ENCODINGS = ("gamma1.2", "srgb")
ROUGHNESS_RANGE = (0.05, 0.9)   # GGX α: p=64 ↔ α≈0.17 and p=1 ↔ α≈0.8 (α = √(2/(p+2))), so both ends lie outside


@dataclass
class WildConfig:
    """Parameters of ``synth wild`` (recorded in every artifact's meta).

    The defaults here are the only ones: the ``synth-wild`` stage (reflectmm_cli/stages/synth_wild.py) declares
    its params with them and adds the ranges and choices that the command line and recipes validate."""

    count: int = 16
    seed: int = 0
    size: int = 224
    images_per_identity: int = 4
    occluder_fraction: float = 0.2
    landmark_noise: float = 1.0      # σ of the Gaussian landmark noise (pixels at --size)
    encoding: str = "gamma1.2"
    noise: float = 0.004             # read noise σ (linear); shot noise σ² = 0.0004·x on top
    envmaps: int = 8                 # size of the map pool
    envmap_width: int = 512
    uv_size: int = 256
    face_vertices: int = 35000       # procedural face model resolution (when no face model is given)
    ao_rays: int = 12                # ambient-occlusion rays per touched vertex
    spec_rays: int = 6               # GGX-lobe visibility rays per touched vertex
    prefilter_width: int = 128
    expression_per_identity: bool = True   # one expression per identity: geometry, Embree scene and ambient
                                           # occlusion are then computed once per identity
    split: tuple = (0.8, 0.1, 0.1)   # train/val/test fractions of the identities
    skin: str | None = None          # None = "single" (one GGX lobe) or "two-lobe" (sharp + broad GGX; synth/skin.py);
                                     # None, as the stage's param, so that the default stays out of params and keys

    def __post_init__(self) -> None:
        self.split = tuple(float(x) for x in self.split)
        if self.skin is not None and self.skin not in SKIN_MODELS:
            raise ReflectmmError(f"--skin must be one of {', '.join(SKIN_MODELS)}, got {self.skin!r}")

    def to_params(self) -> dict:
        d = asdict(self)
        d["split"] = list(self.split)
        if self.skin in (None, "single"):  # the default is not recorded: data sets made before --skin stay byte-identical
            d.pop("skin")
        return d


def head_pose_rotation(yaw_deg: float, pitch_deg: float = 0.0, roll_deg: float = 0.0) -> np.ndarray:
    """(3, 3) rotation of the head in model space: ``Rz(roll) · Rx(pitch) · Ry(yaw)`` (degrees; model +y up,
    +z out of the face).  Yaw > 0 turns the face towards the model's +x, pitch > 0 tilts the chin up.
    The model → OpenCV camera rotation of the Deep3D camera is ``diag(1, −1, −1) · head_pose_rotation(...)``."""
    y, p, r = (math.radians(float(a)) for a in (yaw_deg, pitch_deg, roll_deg))
    return euler_yxz_to_matrix(y, p, r)


# --------------------------------------------------------------------------- identities

@dataclass
class WildSkin:
    """Per-vertex reflectance of one identity (V vertices of the face model).

    albedo (V,3) linear diffuse; roughness (V,) GGX α; spec_intensity (V,) ρ; spec_albedo (V,) the GGX
    directional albedo at normal view (comparable to Σw); weights (V,3) the 3-lobe (1, 8, 64) NNLS equivalent;
    skin (V,) bool (skin vertices: the model's skin region minus eyes and brows); params: the scalar draws.
    Two-lobe skin: ``roughness`` is α of the sharp lobe, ``roughness_broad`` (V,) α of the broad one and
    ``lobe_mix`` (V,) the broad lobe's weight m (None for the single-lobe skin).
    """

    albedo: np.ndarray
    roughness: np.ndarray
    spec_intensity: np.ndarray
    spec_albedo: np.ndarray
    weights: np.ndarray
    skin: np.ndarray
    params: dict
    roughness_broad: np.ndarray | None = None
    lobe_mix: np.ndarray | None = None


def _blur(x, s):
    import cv2

    k = int(2 * math.ceil(3 * s) + 1)
    return cv2.GaussianBlur(x.astype(np.float32), (k, k), s, borderType=cv2.BORDER_REPLICATE)


def _spots(rng, size, centres_mask, n, r_lo, r_hi):
    """Sum of n soft round spots with centres drawn where ``centres_mask`` (S,S) is large."""
    import cv2

    out = np.zeros((size, size), np.float32)
    p = centres_mask.ravel().astype(np.float64)
    if n <= 0 or p.sum() <= 0:
        return out
    idx = rng.choice(size * size, size=n, p=p / p.sum())
    for k in idx:
        yx = divmod(int(k), size)
        cv2.circle(out, (yx[1], yx[0]), max(1, int(round(rng.uniform(r_lo, r_hi)))), 1.0, -1, cv2.LINE_AA)
    return np.clip(_blur(out, 0.8), 0, 1)


def sample_wild_skin(model, rng: np.random.Generator, uv_size: int = 256, f0: float = SKIN_F0,
                     skin_model: str = "single") -> WildSkin:
    """One identity of the wild population, per vertex.  Differs from ``synth multipie`` (synth/skin.py) on
    purpose: melanin 0.01–1.6 (multipie 0.03–1.0), haemoglobin 0.02–0.2, freckles (30 %) and moles, make-up
    lips (40 %: a saturated colour, glossier), stubble shadow (30 %), a global oily/dry state scaling ρ by
    0.3–2.5 and α by 0.55–1.8, α clipped to [0.05, 0.9] (sharper and broader than the 1/8/64 basis).

    ``skin_model="two-lobe"``: that α sets a sharp and a broad GGX lobe mixed per region
    (:func:`reflectmm_cli.synth.skin.two_lobe_maps`, the identity's two-lobe draws taken after every other draw),
    ρ rescaled to keep the specular albedo at normal view.
    """
    from reflectmm_cli.geometry.uv import sample_uv_map

    S = int(uv_size)
    lm_uv = model.uv[model.landmarks].astype(np.float64)
    R = region_masks(lm_uv, S)
    t = rng.uniform()
    mel = 0.01 * (1.6 / 0.01) ** (t ** 1.1)
    hb = rng.uniform(0.02, 0.2)
    oily = float(np.exp(rng.uniform(math.log(0.3), math.log(2.5))))
    rough_scale = float(np.exp(rng.uniform(math.log(0.55), math.log(1.8))))
    freckles = rng.uniform() < 0.3
    makeup = rng.uniform() < 0.4
    stubble = rng.uniform() < 0.3
    n1 = _blur(rng.normal(size=(S, S)), S / 25)
    n1 = (n1 - n1.mean()) / max(float(n1.std()), 1e-6)
    n2 = _blur(rng.normal(size=(S, S)), S / 80)
    n2 = (n2 - n2.mean()) / max(float(n2.std()), 1e-6)
    c0 = np.array([0.74, 0.60, 0.50])
    k_mel, k_hb = np.array([1.4, 2.1, 2.7]), np.array([0.2, 2.2, 1.5])
    melm = mel * np.exp(0.15 * n1 + 0.05 * n2)
    hbm = hb * (1 + 1.3 * R["cheeks"] + 0.5 * R["nose_tip"]) * np.exp(0.2 * n2) + 0.3 * R["lips"]
    spots = np.zeros((S, S), np.float32)
    if freckles:
        spots += 0.5 * _spots(rng, S, R["cheeks"] + R["nose"] + 0.3 * R["forehead"], int(rng.integers(40, 160)),
                              0.5, 1.5)
    spots += _spots(rng, S, R["cheeks"] + R["forehead"] + R["chin"] + R["jaw"], int(rng.integers(0, 4)), 1.0, 2.5)
    melm = melm * (1 + 1.5 * spots) + 0.3 * spots
    alb = c0[:, None, None] * np.exp(-melm[None] * k_mel[:, None, None] - hbm[None] * k_hb[:, None, None])
    lips = R["lips"][None]
    rough = 0.4 + 0.08 * R["cheeks"] - 0.15 * R["nose_tip"] - 0.1 * R["nose"] - 0.08 * R["forehead"] \
        + 0.25 * R["brows"] - 0.2 * R["eyes"]
    rho = 1.0 - 0.4 * R["cheeks"] + 1.2 * R["nose_tip"] + 0.6 * R["nose"] + 0.7 * R["forehead"] \
        - 0.6 * R["brows"] + 0.8 * R["eyes"]
    params = {"melanin": mel, "haemoglobin": hb, "oiliness": oily, "roughness_scale": rough_scale,
              "freckles": bool(freckles), "makeup": bool(makeup), "stubble": bool(stubble)}
    if makeup:
        col = np.array([rng.uniform(0.35, 0.6), rng.uniform(0.02, 0.15), rng.uniform(0.04, 0.25)])
        alb = alb * (1 - 0.9 * lips) + 0.9 * lips * col[:, None, None]
        rough = rough - 0.25 * R["lips"]
        rho = rho + 1.5 * R["lips"]
        params["lip_colour"] = col.tolist()
    if stubble:
        beard = np.clip(R["jaw"] + R["chin"] + _blur(((np.arange(S)[:, None] > lm_uv[33, 1] * S)
                                                       & (np.arange(S)[:, None] < lm_uv[51, 1] * S)
                                                       & (np.abs(np.arange(S)[None, :] - lm_uv[33, 0] * S)
                                                          < 0.15 * S)).astype(np.float32), 3), 0, 1)
        beard = beard * (1 - R["lips"])
        dens = rng.uniform(0.2, 0.5) * np.clip(0.7 + 0.3 * n2, 0, 1.3)
        alb = alb * (1 - dens * beard)[None] + (dens * beard)[None] * np.array([0.05, 0.04, 0.035])[:, None, None]
        rough = rough + 0.3 * beard
        rho = rho * (1 - 0.5 * beard)
        params["stubble_density"] = float(dens.mean())
    brow_dark = rng.uniform(0.15, 0.6)
    alb = alb * (1 - R["brows"] * (1 - brow_dark))
    alb = alb * (1 - R["eyes"]) + R["eyes"] * np.array([0.5, 0.47, 0.45])[:, None, None]
    rough = np.clip(rough * rough_scale * np.exp(0.08 * n2), *ROUGHNESS_RANGE)
    rho = np.clip(1.4 * rho * oily * np.exp(0.15 * n1), 0.03, 8.0)
    uv = model.uv.astype(np.float64)
    v_alb = np.clip(sample_uv_map(alb.astype(np.float32), uv), 0.0, 1.0)
    non_skin = sample_uv_map(np.maximum(R["eyes"], R["brows"]).astype(np.float32), uv)
    skin = np.asarray(model.skin_mask, bool) & (non_skin < 0.5)
    if skin_model == "two-lobe":
        tl = sample_two_lobe_params(rng)
        p = lm_uv * S - 0.5
        a_s, a_b, mix = two_lobe_maps(R, rough, tl, float(np.linalg.norm(p[36] - p[45])))
        params["two_lobe"] = tl.to_dict()
        v_as, v_ab = sample_uv_map(a_s.astype(np.float32), uv), sample_uv_map(a_b.astype(np.float32), uv)
        v_mix = sample_uv_map(mix.astype(np.float32), uv)
        # the specular albedo of the single lobe of width α, redistributed into the two lobes
        v_rho = sample_uv_map(rho.astype(np.float32), uv) * ggx_specular_albedo(
            sample_uv_map(rough.astype(np.float32), uv), 1.0, f0) / two_lobe_specular_albedo(v_as, v_ab, v_mix, 1.0, f0)
        w = (1.0 - v_mix)[:, None] * fit_lobes_to_ggx(v_as, v_rho, DEFAULT_EXPONENTS, f0) \
            + v_mix[:, None] * fit_lobes_to_ggx(v_ab, v_rho, DEFAULT_EXPONENTS, f0)
        return WildSkin(albedo=v_alb.astype(np.float32), roughness=v_as.astype(np.float32),
                        spec_intensity=v_rho.astype(np.float32),
                        spec_albedo=two_lobe_specular_albedo(v_as, v_ab, v_mix, v_rho, f0).astype(np.float32),
                        weights=w.astype(np.float32), skin=skin, params=params,
                        roughness_broad=v_ab.astype(np.float32), lobe_mix=v_mix.astype(np.float32))
    v_rough = sample_uv_map(rough.astype(np.float32), uv)
    v_rho = sample_uv_map(rho.astype(np.float32), uv)
    return WildSkin(albedo=v_alb.astype(np.float32), roughness=v_rough.astype(np.float32),
                    spec_intensity=v_rho.astype(np.float32),
                    spec_albedo=ggx_specular_albedo(v_rough, v_rho, f0).astype(np.float32),
                    weights=fit_lobes_to_ggx(v_rough, v_rho, DEFAULT_EXPONENTS, f0).astype(np.float32),
                    skin=skin, params=params)


# --------------------------------------------------------------------------- scenes

@dataclass
class WildScene:
    """Everything random about one image (besides the identity's reflectance)."""

    name: str
    identity: int
    shape: np.ndarray
    expression: np.ndarray
    pose_deg: np.ndarray     # (yaw, pitch, roll)
    R: np.ndarray            # model → OpenCV camera
    t: np.ndarray
    K: np.ndarray
    envmap: int
    env_rotation: np.ndarray  # light-frame direction d sees the map at env_rotationᵀ d
    env_factor: float         # random exposure factor (the final scale also normalises the face brightness)
    occluder: str             # "none" | "hand" | "hat"
    seed: int


def _rng(seed: int, *key) -> np.random.Generator:
    return np.random.default_rng([int(seed) & 0xFFFFFFFF, *[int(k) for k in key], 0x57D])


def identity_shape(model, seed: int, identity: int) -> np.ndarray:
    rng = _rng(seed, identity, 1)
    return np.clip(rng.normal(size=model.n_shape), -3, 3) * model.shape_sigma.astype(np.float64)


def identity_expression(model, seed: int, identity: int) -> np.ndarray:
    rng = _rng(seed, identity, 5)
    return np.clip(rng.normal(size=model.n_exp), -2.5, 2.5) * model.exp_sigma.astype(np.float64) * 0.7


def sample_scene(model, cfg: WildConfig, index: int) -> WildScene:
    """The random scene of image ``index`` (0-based); depends on (seed, index) only."""
    from reflectmm_cli.geometry import deep3d_camera

    rng = _rng(cfg.seed, index, 2)
    ident = index // int(cfg.images_per_identity)
    exp = np.clip(rng.normal(size=model.n_exp), -2.5, 2.5) * model.exp_sigma.astype(np.float64) * 0.7
    if cfg.expression_per_identity:
        exp = identity_expression(model, cfg.seed, ident)
    pose = np.array([rng.uniform(-50, 50), rng.uniform(-20, 20), rng.uniform(-10, 10)])
    R = np.diag([1.0, -1.0, -1.0]) @ head_pose_rotation(*pose)
    cam = deep3d_camera()
    t = cam.t + np.array([rng.normal(0, 4.0), rng.normal(0, 4.0), rng.normal(0, 40.0)])
    K = cam.with_size(cfg.size, cfg.size).K
    az, tilt, spin = rng.uniform(-180, 180), rng.normal(0, 12), rng.normal(0, 5)
    env_rot = head_pose_rotation(az, tilt, spin)
    occ = "none"
    if rng.uniform() < cfg.occluder_fraction:
        occ = "hand" if rng.uniform() < 0.5 else "hat"
    return WildScene(name=f"w{cfg.seed:03d}_{index:06d}", identity=ident, shape=identity_shape(model, cfg.seed, ident),
                     expression=exp, pose_deg=pose, R=R, t=t, K=K, envmap=int(rng.integers(0, cfg.envmaps)),
                     env_rotation=env_rot, env_factor=float(np.exp(rng.uniform(-0.35, 0.35))), occluder=occ,
                     seed=int(rng.integers(0, 2**31 - 1)))


# --------------------------------------------------------------------------- rendering

def _frame(n: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    a = np.where(np.abs(n[:, :1]) < 0.9, np.array([[1.0, 0, 0]]), np.array([[0, 1.0, 0]]))
    t1 = np.cross(n, a)
    t1 /= np.linalg.norm(t1, axis=1, keepdims=True)
    return t1, np.cross(n, t1)


_GOLDEN = 0.6180339887498949


def vertex_ambient_occlusion(scene, verts, normals, ids, n_rays: int, phase: float = 0.0) -> np.ndarray:
    """(M,) fraction of ``n_rays`` cosine-distributed rays (Hammersley, rotated about the normal by an angle that
    depends only on the vertex id and ``phase``) leaving vertex ``ids`` unoccluded — the same value whichever
    image asks for it first."""
    x, n = verts[ids], normals[ids]
    M = len(ids)
    if n_rays <= 0 or M == 0:
        return np.ones(M)
    eps = scene.default_eps * 3
    t1, t2 = _frame(n)
    rot = 2 * math.pi * np.modf(ids * _GOLDEN + phase)[0]
    u = _hammersley(n_rays)
    r = np.sqrt(u[:, 0])
    a = 2 * math.pi * u[:, 1][None, :] + rot[:, None]
    lx, ly = r[None, :] * np.cos(a), r[None, :] * np.sin(a)
    lz = np.broadcast_to(np.sqrt(1 - u[:, 0])[None, :], (M, n_rays))
    d = (lx[..., None] * t1[:, None] + ly[..., None] * t2[:, None] + lz[..., None] * n[:, None]).reshape(-1, 3)
    o = np.repeat(x + eps * n, n_rays, 0)
    occ = scene.occluded(o, d, np.full(len(d), 1e5)).reshape(M, n_rays)
    return 1.0 - occ.mean(1)


def vertex_lobe_visibility(scene, verts, normals, eye, alpha, ids, n_rays: int, rng) -> np.ndarray:
    """(M,) fraction of ``n_rays`` GGX-lobe directions (half vectors ~ D(h)(n·h), reflected about the view,
    above the horizon) from vertex ``ids`` that escape; 1 where no sample is above the horizon."""
    x, n = verts[ids], normals[ids]
    M = len(ids)
    if n_rays <= 0 or M == 0:
        return np.ones(M)
    eps = scene.default_eps * 3
    t1, t2 = _frame(n)
    rot = rng.uniform(0, 2 * math.pi, M)
    v = eye[None, :] - x
    v /= np.linalg.norm(v, axis=1, keepdims=True)
    u = _hammersley(n_rays)
    hl = sample_ggx_h(np.broadcast_to(u, (M, n_rays, 2)), alpha[:, None])     # (M, k, 3) local
    c, s_ = np.cos(rot)[:, None], np.sin(rot)[:, None]
    hx, hy = c * hl[..., 0] - s_ * hl[..., 1], s_ * hl[..., 0] + c * hl[..., 1]
    h = hx[..., None] * t1[:, None] + hy[..., None] * t2[:, None] + hl[..., 2:3] * n[:, None]
    vh = (h * v[:, None]).sum(-1)
    l = 2 * vh[..., None] * h - v[:, None]
    ok = ((l * n[:, None]).sum(-1) > 0) & (vh > 0)
    o = np.repeat(x + eps * n, n_rays, 0)
    occ = np.ones(M * n_rays, bool)
    okf = ok.reshape(-1)
    occ[okf] = scene.occluded(o[okf], l.reshape(-1, 3)[okf], np.full(int(okf.sum()), 1e5))
    cnt = ok.sum(1)
    return np.where(cnt > 0, ((~occ.reshape(M, n_rays)) & ok).sum(1) / np.maximum(cnt, 1), 1.0)


class IdentityGeometry:
    """Vertices, normals, Embree scene and a lazily filled per-vertex ambient-occlusion cache of one
    (shape, expression); shared by the images of an identity."""

    def __init__(self, model, shape, expression, phase: float = 0.0):
        from reflectmm_cli.geometry import RayScene, vertex_normals

        self.shape = np.asarray(shape, np.float64)
        self.expression = np.asarray(expression, np.float64)
        self.vertices = model.vertices(self.shape, self.expression).astype(np.float64)
        self.normals = vertex_normals(self.vertices, model.triangles).astype(np.float64)
        self.scene = RayScene(self.vertices, model.triangles, self.normals)
        self.ao = np.full(len(self.vertices), np.nan)
        self.phase = float(phase)

    def matches(self, shape, expression) -> bool:
        return np.array_equal(self.shape, shape) and np.array_equal(self.expression, expression)

    def ambient_occlusion(self, ids, n_rays: int) -> np.ndarray:
        miss = ids[np.isnan(self.ao[ids])]
        if miss.size:
            self.ao[miss] = vertex_ambient_occlusion(self.scene, self.vertices, self.normals, miss, n_rays,
                                                     self.phase)
        return self.ao[ids]


def render_wild(model, skin: WildSkin, sc: WildScene, env: SplitMap, cfg: WildConfig, *, stats: dict | None = None,
                geometry: IdentityGeometry | None = None) -> dict:
    """Render one image (linear, before occluder/noise/encoding).

    Returns a dict: ``gbuffer`` (float16 G-buffer of :mod:`reflectmm_cli.geometry.gbuffer`), ``diffuse``,
    ``specular`` (S,S,3) float32 linear radiance of the face (0 elsewhere; unit scale), ``background`` (S,S,3)
    the map behind the head, ``face`` (S,S) bool pixels shaded as face (hits with n·v > 0), ``sh`` (3, 81) the
    order-8 SH of the full map in the light frame (unit scale), ``landmarks`` (68, 2), ``scene`` (RayScene),
    ``vertices`` (V,3).  ``geometry``: an :class:`IdentityGeometry` of the same (shape, expression) to reuse.
    """
    from reflectmm_cli.geometry import Camera, rasterize
    from reflectmm_cli.geometry.gbuffer import gbuffer_from_raster, model_to_light
    from reflectmm_cli.shading import lambert_sh_coeffs, sh_basis, sh_rotation
    from reflectmm_cli.geometry.raycast import shadow_mask

    st = stats if stats is not None else {}
    t0 = time.perf_counter()
    S = int(cfg.size)
    if geometry is None or not geometry.matches(sc.shape, sc.expression):
        geometry = IdentityGeometry(model, sc.shape, sc.expression, phase=_GOLDEN * sc.identity)
    verts, normals, scene = geometry.vertices, geometry.normals, geometry.scene
    cam = Camera(sc.K, sc.R, sc.t, S, S, sc.name)
    ras = rasterize(scene, cam)
    st["raster_s"] = st.get("raster_s", 0) + time.perf_counter() - t0
    gb = gbuffer_from_raster(ras, model.triangles, cam, dtype=np.float64)
    M = model_to_light(sc.R)                     # model → light frame
    Q = sc.env_rotation                          # light frame → map: d_map = Qᵀ d_light
    vis = gb["visible"]
    yx = gb["pix_yx"][vis]
    ids = gb["vert_ids"][vis]
    b = gb["bary"][vis].astype(np.float64)
    n_l, v_l, r_l = gb["normal"][vis], gb["view"][vis], gb["reflect"][vis]
    alb = np.einsum("pk,pkc->pc", b, skin.albedo[ids].astype(np.float64))
    alpha = np.einsum("pk,pk->p", b, skin.roughness[ids].astype(np.float64))
    rho = np.einsum("pk,pk->p", b, skin.spec_intensity[ids].astype(np.float64))
    # per-vertex visibility of the touched vertices
    t1 = time.perf_counter()
    uid, inv = np.unique(ids, return_inverse=True)
    ao_v = geometry.ambient_occlusion(uid, cfg.ao_rays)
    vs_v = vertex_lobe_visibility(scene, verts, normals, cam.center, skin.roughness[uid].astype(np.float64), uid,
                                  cfg.spec_rays, _rng(sc.seed, 7))
    inv = inv.reshape(ids.shape)
    ao = (b * ao_v[inv]).sum(1)
    vspec = (b * vs_v[inv]).sum(1)
    two = skin.lobe_mix is not None
    if two:  # the broad lobe: its own width, weight and lobe visibility
        alpha_b = np.einsum("pk,pk->p", b, skin.roughness_broad[ids].astype(np.float64))
        mix = np.einsum("pk,pk->p", b, skin.lobe_mix[ids].astype(np.float64))
        vs_b = vertex_lobe_visibility(scene, verts, normals, cam.center,
                                      skin.roughness_broad[uid].astype(np.float64), uid, cfg.spec_rays,
                                      _rng(sc.seed, 13))
        vspec_b = (b * vs_b[inv]).sum(1)
    st["visibility_s"] = st.get("visibility_s", 0) + time.perf_counter() - t1
    # residual: SH irradiance × AO, split-sum specular × lobe visibility
    t2 = time.perf_counter()
    K_res = env.residual_sh @ sh_rotation(Q, 8).T            # map frame → light frame
    A = lambert_sh_coeffs(8)
    Aw = np.repeat(A, 2 * np.arange(9) + 1)
    Yn = sh_basis(n_l, 8)
    E_res = Yn @ (K_res * Aw[None, :]).T                       # (P, 3)
    diffuse = alb / math.pi * np.maximum(E_res, 0.0) * ao[:, None]
    ndv = np.clip((n_l * v_l).sum(1), 1e-4, 1.0)
    spec_pref = env.specular(r_l @ Q, alpha)                   # rows: Qᵀ r
    if two:
        specular = (rho * (1.0 - mix) * ggx_view_albedo(alpha, ndv) * vspec)[:, None] * spec_pref \
            + (rho * mix * ggx_view_albedo(alpha_b, ndv) * vspec_b)[:, None] * env.specular(r_l @ Q, alpha_b)
    else:
        specular = (rho * ggx_view_albedo(alpha, ndv) * vspec)[:, None] * spec_pref
    # sources: GGX with a shadow ray per pixel and source
    x_model = ras.position[ras.mask][vis].astype(np.float64)
    n_model = ras.normal[ras.mask][vis].astype(np.float64)
    for dmap, E in zip(env.source_dirs, env.source_irradiance):
        d_l = Q @ dmap
        d_model = M.T @ d_l
        lit = (n_l @ d_l) > 0
        if lit.any():
            far = x_model[lit] + 1e5 * d_model
            lit_idx = np.flatnonzero(lit)
            ok = shadow_mask(scene, x_model[lit], n_model[lit], far)
            li = lit_idx[ok]
            if two:
                _, dd, ss = ggx_two_lobe_directional(alb[li], rho[li], alpha[li], alpha_b[li], mix[li], n_l[li],
                                                     np.broadcast_to(d_l, (len(li), 3)), v_l[li],
                                                     np.broadcast_to(E, (len(li), 3)), return_parts=True)
            else:
                _, dd, ss = ggx_directional(alb[li], rho[li], alpha[li], n_l[li], np.broadcast_to(d_l, (len(li), 3)),
                                            v_l[li], np.broadcast_to(E, (len(li), 3)), return_parts=True)
            diffuse[li] += dd
            specular[li] += ss
    st["shading_s"] = st.get("shading_s", 0) + time.perf_counter() - t2
    D = np.zeros((S, S, 3), np.float32)
    Sp = np.zeros((S, S, 3), np.float32)
    D[yx[:, 0], yx[:, 1]] = diffuse
    Sp[yx[:, 0], yx[:, 1]] = specular
    face = np.zeros((S, S), bool)
    face[yx[:, 0], yx[:, 1]] = True
    # background: the map seen through each pixel
    t3 = time.perf_counter()
    _, dirs = cam.rays()
    bg = env.radiance((dirs @ M.T) @ Q).reshape(S, S, 3).astype(np.float32)
    st["background_s"] = st.get("background_s", 0) + time.perf_counter() - t3
    lm, _ = cam.project(verts[model.landmarks])
    gb16 = {k: (v.astype(np.float16) if k in ("normal", "view", "reflect") else v) for k, v in gb.items()}
    return {"gbuffer": gb16, "diffuse": D, "specular": Sp, "background": bg, "face": face,
            "sh": env.sh @ sh_rotation(Q, 8).T, "landmarks": lm, "scene": scene, "vertices": verts,
            "ao": ao, "spec_visibility": vspec, "geometry": geometry}


def reference_radiance(scene, x_model, n_model, eye, M, env: SplitMap, Q, albedo, rho, alpha, *,
                       chunk: int = 8192) -> tuple[np.ndarray, np.ndarray]:
    """Brute-force reference: for each point, the rendering integral as a sum over **every pixel** of the
    full-resolution map (radiance × pixel solid angle, Lambert + GGX, one shadow ray per map pixel above the
    horizon).  x_model, n_model (P, 3) model space; M model → light; Q light → map; returns (diffuse, specular)
    (P, 3) at unit scale.  Cost: ~H·W/2 rays per point.
    """
    from reflectmm_cli.shading import equirect_directions, equirect_weights

    img = env.image.astype(np.float64)
    H, W, _ = img.shape
    d_map = equirect_directions(W, H).reshape(-1, 3)
    om = np.repeat(equirect_weights(W, H, "area"), W)
    L = img.reshape(-1, 3)
    d_model = (d_map @ Q.T) @ M                                  # map → light → model
    P = len(x_model)
    dif, spe = np.zeros((P, 3)), np.zeros((P, 3))
    eps = scene.default_eps * 3
    for i in range(P):
        n = n_model[i] / np.linalg.norm(n_model[i])
        x = x_model[i]
        v = eye - x
        v /= np.linalg.norm(v)
        up = d_model @ n > 0
        idx = np.flatnonzero(up & (L.sum(1) > 0))
        for s in range(0, len(idx), chunk):
            j = idx[s:s + chunk]
            occ = scene.occluded(np.broadcast_to(x + eps * n, (len(j), 3)), d_model[j], np.full(len(j), 1e5))
            j = j[~occ]
            E = L[j] * om[j, None]
            _, dd, ss = ggx_directional(np.broadcast_to(albedo[i], (len(j), 3)), rho[i], alpha[i],
                                        np.broadcast_to(n, (len(j), 3)), d_model[j],
                                        np.broadcast_to(v, (len(j), 3)), E, return_parts=True)
            dif[i] += dd.sum(0)
            spe[i] += ss.sum(0)
    return dif, spe


# --------------------------------------------------------------------------- occluders, noise, encoding

def draw_occluder(kind: str, rng: np.random.Generator, face: np.ndarray, landmarks: np.ndarray, sh: np.ndarray
                  ) -> tuple[np.ndarray, np.ndarray]:
    """A hand- or hat-like occluder: (mask (S,S) bool, linear colour image (S,S,3)).

    hand: an ellipse (palm) with 4 finger bars entering from the lower left/right over the chin/cheek;
    hat: a band over the forehead with a brim.  Shaded as Lambert with the order-1 SH irradiance of the map
    for a camera-facing normal (no visibility).
    """
    import cv2

    S = face.shape[0]
    m = np.zeros((S, S), np.uint8)
    lm = landmarks
    iod = float(np.linalg.norm(lm[36] - lm[45]))
    if kind == "hand":
        side = -1 if rng.uniform() < 0.5 else 1
        cx = float(lm[8, 0] + side * rng.uniform(0.3, 0.9) * iod)
        cy = float(lm[8, 1] + rng.uniform(-0.2, 0.4) * iod)
        ax = (int(0.7 * iod), int(0.55 * iod))
        ang = rng.uniform(-40, 40)
        cv2.ellipse(m, (int(cx), int(cy)), ax, ang, 0, 360, 1, -1)
        tip = np.array([-side * 1.0, -1.0]) / math.sqrt(2)
        perp = np.array([tip[1], -tip[0]])
        for f in range(4):
            base = np.array([cx, cy]) + (f - 1.5) * 0.28 * iod * perp
            end = base + rng.uniform(0.8, 1.2) * iod * tip
            cv2.line(m, tuple(int(v) for v in base), tuple(int(v) for v in end), 1, max(1, int(0.2 * iod)))
        col = np.array([0.55, 0.38, 0.3]) * np.exp(-rng.uniform(0, 1.2) * np.array([1.4, 2.1, 2.7]))
    else:
        top = float(lm[17:27, 1].min())
        brim = top - rng.uniform(0.0, 0.35) * iod
        x0, x1 = float(lm[0, 0] - 0.3 * iod), float(lm[16, 0] + 0.3 * iod)
        pts = np.array([[x0, brim], [x1, brim], [x1 - 0.2 * iod, brim - 2 * iod], [x0 + 0.2 * iod, brim - 2 * iod]])
        cv2.fillPoly(m, [pts.astype(np.int32)], 1)
        col = rng.uniform(0.03, 0.6, 3)
    from reflectmm_cli.shading import lambert_sh_coeffs, sh_basis

    A = np.repeat(lambert_sh_coeffs(8), 2 * np.arange(9) + 1)
    E = np.maximum(sh_basis(np.array([[0.0, 0.0, 1.0]]), 8) @ (sh * A[None, :]).T, 0.0)[0]
    img = np.broadcast_to(col / math.pi * E, (S, S, 3)).astype(np.float32)
    return m.astype(bool), img


def encode_codes(linear: np.ndarray, encoding: str) -> np.ndarray:
    """Linear [0,1] → uint8 codes: ``gamma1.2`` x^(1/1.2) or ``srgb`` (the sRGB OETF); clipped, rounded
    (:func:`reflectmm_cli.color.encode_display` in float64)."""
    if encoding not in ENCODINGS:
        raise ReflectmmError(f"unknown encoding {encoding!r} ({', '.join(ENCODINGS)})")
    return encode_display(linear, encoding, dtype=np.float64, uint8=True)


def compose_image(r: dict, sc: WildScene, cfg: WildConfig, env_scale: float, occ_mask, occ_img) -> np.ndarray:
    """Linear image = scale · (face ? diffuse + specular : background), occluder over it, then sensor noise."""
    face = r["face"]
    lin = np.where(face[..., None], r["diffuse"] + r["specular"], r["background"]) * env_scale
    if occ_mask is not None:
        lin = np.where(occ_mask[..., None], occ_img * env_scale, lin)
    rng = _rng(sc.seed, 9)
    if cfg.noise > 0:
        sig = np.sqrt(float(cfg.noise) ** 2 + 0.0004 * np.clip(lin, 0, 1))
        lin = lin + rng.normal(size=lin.shape) * sig
    return lin


# --------------------------------------------------------------------------- the data set

def identity_split(n_identities: int, seed: int, fractions=(0.8, 0.1, 0.1)) -> np.ndarray:
    """(n,) array of "train"/"val"/"test" per identity: a seeded permutation cut by ``fractions`` (with ≥ 3
    identities every split gets at least one)."""
    perm = _rng(seed, 0, 3).permutation(n_identities)
    f = np.asarray(fractions, np.float64) / sum(fractions)
    n_val = int(round(f[1] * n_identities))
    n_test = int(round(f[2] * n_identities))
    if n_identities >= 3:
        n_val, n_test = max(1, n_val), max(1, n_test)
    out = np.full(n_identities, "train", dtype="<U5")
    out[perm[:n_test]] = "test"
    out[perm[n_test:n_test + n_val]] = "val"
    return out


def _warn_empty_splits(cfg: WildConfig, n_id: int, splits: np.ndarray) -> None:
    """A split with a positive fraction that gets no identity (too few identities to cut): said before rendering,
    as what evaluates the test identities (build-baseline oracle, the evaluations) finds none later."""
    empty = [name for name, f in zip(("val", "test"), cfg.split) if f > 0 and name not in splits]
    if empty:
        ipi = int(cfg.images_per_identity)
        log.warning("synth wild: %d image(s) make %d identit%s, too few to split: no %s identity (-n %d or more, "
                    "with %d image(s) per identity, gives every split at least one)", cfg.count, n_id,
                    "y" if n_id == 1 else "ies", " or ".join(empty), 2 * ipi + 1, ipi)


def _thumb(img_u8: np.ndarray, w: int = 112) -> np.ndarray:
    import cv2

    return cv2.resize(img_u8, (w, w), interpolation=cv2.INTER_AREA)


def synth_wild(out_dir: str | Path, cfg: WildConfig, *, face_model=None, progress_fn: Callable | None = None,
               producer: dict | None = None, cache_key: str | None = None) -> dict:
    """Write the data set (layout in docs/wild.md) and return a summary dict (paths, timings).

    ``out_dir/``: ``images/NAME.png``, ``landmarks/NAME.pts``, ``truth/NAME.npz`` (kind ``wild-truth``),
    ``identities/ID.npz`` (kind ``wild-truth``, per-vertex reflectance), ``envmaps/env_*.exr``,
    ``face_model.npz``, ``manifest.npz`` (kind ``wild-manifest``), ``contact_sheet.png``.
    """
    from reflectmm_cli.artifacts import write_artifact, write_png
    from reflectmm_cli.geometry import procedural_face_model, save_face_model
    from reflectmm_cli.landmarks import write_pts
    from reflectmm_cli.progress import progress
    from reflectmm_cli.synth.envmaps import make_envmap, write_envmaps

    out = Path(out_dir)
    prog = progress_fn or (lambda it, **kw: progress(it, **kw))
    model = face_model if face_model is not None else procedural_face_model(n_vertices=cfg.face_vertices)
    fm_path = save_face_model(model, out / "face_model.npz", params={"face_vertices": cfg.face_vertices})
    params = cfg.to_params()
    prod = producer or {"stage": "synth-wild"}
    n_id = -(-cfg.count // cfg.images_per_identity)
    splits = identity_split(n_id, cfg.seed, cfg.split)
    _warn_empty_splits(cfg, n_id, splits)
    n_env = int(cfg.envmaps)   # images depend on (seed, index) only, not on --count
    write_envmaps(out / "envmaps", n_env, cfg.seed, cfg.envmap_width, contact_sheet=False)
    t_env = time.perf_counter()
    envs = [split_map(make_envmap(cfg.seed, i, cfg.envmap_width)[0], prefilter_width=cfg.prefilter_width)
            for i in prog(range(n_env), desc="prefilter maps", unit="map")]
    t_env = time.perf_counter() - t_env
    skins: dict[int, WildSkin] = {}
    geom: IdentityGeometry | None = None
    names, ids, spl, envi, poses, occl = [], [], [], [], [], []
    thumbs = []
    stats: dict = {}
    t_img = time.perf_counter()
    for i in prog(range(cfg.count), desc="synth wild", unit="img"):
        sc = sample_scene(model, cfg, i)
        sc.envmap = sc.envmap % n_env
        t_sk = time.perf_counter()
        if sc.identity not in skins:
            skins.clear()
            skins[sc.identity] = sk = sample_wild_skin(model, _rng(cfg.seed, sc.identity, 4), cfg.uv_size,
                                                       skin_model=cfg.skin or "single")
            two_lobe = {} if sk.lobe_mix is None else {"vertex_roughness_broad": sk.roughness_broad,
                                                       "vertex_lobe_mix": sk.lobe_mix}
            write_artifact(out / "identities" / f"id{sc.identity:05d}.npz", "wild-truth", {
                "vertex_albedo": sk.albedo, "vertex_roughness": sk.roughness,
                "vertex_spec_intensity": sk.spec_intensity, "vertex_spec_albedo": sk.spec_albedo,
                "vertex_weights": sk.weights, "vertex_skin": sk.skin, "shape": sc.shape.astype(np.float32),
                **two_lobe},
                params=params, producer=prod, cache_key=cache_key,
                extra_meta={"content": "identity", "identity": sc.identity, "skin_params": sk.params,
                            "exponents": list(DEFAULT_EXPONENTS), "split": str(splits[sc.identity])})
        sk = skins[sc.identity]
        stats["identity_s"] = stats.get("identity_s", 0) + time.perf_counter() - t_sk
        env = envs[sc.envmap]
        r = render_wild(model, sk, sc, env, cfg, stats=stats, geometry=geom)
        geom = r["geometry"]
        face = r["face"]
        lum = ((r["diffuse"] + r["specular"])[face] @ np.array([0.2126, 0.7152, 0.0722]))
        p90 = float(np.percentile(lum, 90)) if lum.size else 1.0
        scale = sc.env_factor * 0.6 / max(p90, 1e-12)
        occ_mask = occ_img = None
        orng = _rng(sc.seed, 11)
        if sc.occluder != "none":
            occ_mask, occ_img = draw_occluder(sc.occluder, orng, face, r["landmarks"], r["sh"])
        t_w = time.perf_counter()
        lin = compose_image(r, sc, cfg, scale, occ_mask, occ_img)
        img = encode_codes(lin, cfg.encoding)
        write_png(out / "images" / f"{sc.name}.png", img)
        lm = r["landmarks"] + _rng(sc.seed, 12).normal(0, cfg.landmark_noise, (68, 2))
        write_pts(out / "landmarks" / f"{sc.name}.pts", lm)
        gb = r["gbuffer"]
        vert_skin = np.zeros(face.shape, bool)
        vis = gb["visible"]
        yx = gb["pix_yx"][vis]
        vert_skin[yx[:, 0], yx[:, 1]] = (gb["bary"][vis] * sk.skin[gb["vert_ids"][vis]]).sum(1) > 0.5
        skin_mask = vert_skin & face & (True if occ_mask is None else ~occ_mask)
        write_artifact(out / "truth" / f"{sc.name}.npz", "wild-truth", {
            "shape": sc.shape.astype(np.float32), "expression": sc.expression.astype(np.float32),
            "pose_deg": sc.pose_deg, "R": sc.R, "t": sc.t, "K": sc.K,
            "envmap_rotation": sc.env_rotation, "sh": (r["sh"] * scale).astype(np.float32),
            "skin_mask": skin_mask, "face_mask": gb["face_mask"], "shaded_mask": face,
            "occluder_mask": np.zeros_like(face) if occ_mask is None else occ_mask,
            "diffuse": (r["diffuse"] * scale).astype(np.float16), "specular": (r["specular"] * scale).astype(np.float16),
            "landmarks_true": r["landmarks"].astype(np.float32)},
            params=params, producer=prod, cache_key=cache_key,
            extra_meta={"content": "image", "name": sc.name, "identity": sc.identity, "envmap": sc.envmap,
                        "envmap_scale": scale, "envmap_file": f"envmaps/env_{sc.envmap:04d}_"
                        f"{['sky', 'overcast', 'indoor', 'colored'][sc.envmap % 4]}.exr",
                        "occluder": sc.occluder, "encoding": cfg.encoding, "split": str(splits[sc.identity]),
                        "sh_frame": "light frame (+y up, camera looks down -z)",
                        "layers": "linear radiance, image = diffuse + specular on shaded_mask"})
        stats["compose_write_s"] = stats.get("compose_write_s", 0) + time.perf_counter() - t_w
        names.append(sc.name), ids.append(sc.identity), spl.append(str(splits[sc.identity]))
        envi.append(sc.envmap), poses.append(sc.pose_deg), occl.append(sc.occluder)
        if len(thumbs) < 24:
            thumbs.append(_thumb(img))
    t_img = time.perf_counter() - t_img
    write_artifact(out / "manifest.npz", "wild-manifest", {
        "names": np.array(names), "identity": np.array(ids, np.int64), "split": np.array(spl),
        "envmap": np.array(envi, np.int64), "pose_deg": np.array(poses), "occluder": np.array(occl)},
        params=params, producer=prod, cache_key=cache_key,
        extra_meta={"encoding": cfg.encoding, "image_size": cfg.size, "face_model": "face_model.npz",
                    "split_by": "identity"})
    cols = 6
    rows = -(-len(thumbs) // cols)
    tw = thumbs[0].shape[0]
    sheet = np.zeros((rows * tw, cols * tw, 3), np.uint8)
    for k, th in enumerate(thumbs):
        rr, cc = divmod(k, cols)
        sheet[rr * tw:(rr + 1) * tw, cc * tw:(cc + 1) * tw] = th
    write_png(out / "contact_sheet.png", sheet)
    return {"out": str(out), "count": cfg.count, "identities": n_id, "face_model": str(fm_path),
            "seconds_per_image": t_img / cfg.count, "envmap_setup_seconds": t_env, "stages": stats}
