"""Synthetic Multi-PIE: identities with known geometry and reflectance rendered on the rig (docs/synthetic.md).

Per identity: a random shape (and optionally a small expression) from the face model's prior, skin reflectance
maps in UV space (:mod:`reflectmm_cli.synth.skin`), and per camera

* shot ``00``: the room light only — a soft, low-order (SH order 2) environment, shaded with
  :func:`reflectmm_cli.shading.shade_env` (no occlusion of the room light);
* shots ``01``–``18``: room light + one flash, a point light of radiant intensity I at the flash position
  (irradiance ``E = I/d²``) with ray-traced cast shadows; shaded with GGX (``brdf="ggx"``,
  :func:`reflectmm_cli.synth.ggx.ggx_directional`) or the project's 3-lobe model (``brdf="model"``,
  :func:`reflectmm_cli.shading.shade_directional`, exact);

then ``clip(linear + noise, 0, 1) ** (1/1.2)`` quantised to 8-bit PNG in the exact Multi-PIE layout, with iBUG
landmark files.  Linear pixel value = radiance (no exposure factor).
"""

from __future__ import annotations

import math
from concurrent.futures import ThreadPoolExecutor
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Callable, Iterable

import numpy as np

from reflectmm_cli.color import encode_display, gamma_to_linear
from reflectmm_cli.errors import ReflectmmError
from reflectmm_cli.landmarks import format_pts as _format_pts
from reflectmm_cli.capture.layout import camera_code
from reflectmm_cli.rig import ALL_FLASHES, Rig, load_rig, rig_to_toml
from reflectmm_cli.shading.brdf import DEFAULT_EXPONENTS
from reflectmm_cli.synth.skin import FEATURES, SKIN_MODELS, SkinMaps, sample_skin_params, skin_maps

__all__ = ["SynthConfig", "room_light_sh", "encode_png_values", "decode_png_values", "image_path",
           "landmark_path", "Identity", "make_identity", "render_identity", "synth_multipie", "format_pts",
           "SESSION", "RECORDING"]

SESSION = "01"
RECORDING = "01"
ENCODE_GAMMA = 1.2


@dataclass
class SynthConfig:
    """Parameters of ``synth multipie`` (all recorded in the artifacts' meta)."""

    identities: int = 1
    seed: int = 0
    brdf: str = "ggx"                        # "ggx" or "model"
    image_size: tuple[int, int] = (640, 480)  # (W, H)
    uv_size: int = 256
    cameras: tuple[str, ...] | None = None   # None: every rig camera
    flashes: tuple[str, ...] | None = None   # None: every rig flash
    noise: float = 0.0                       # Gaussian sensor noise σ in linear units
    landmark_noise: float = 0.0              # Gaussian landmark noise σ in pixels
    expression: float = 0.0                  # expression coefficients ~ N(0, (expression·σ_e)²); 0 = neutral
    shape_scale: float = 1.0                 # identity coefficients ~ N(0, (shape_scale·σ_s)²), clipped at 3σ
    first_id: int = 1
    room_light: float = 0.15                 # mean radiance of the room light
    background: float = 0.02                 # linear value of the backdrop
    face_vertices: int = 35000               # resolution of the procedural face model (if none is given)
    supersample: int = 1                     # k×k rays per pixel, box-filtered in linear space
    exponents: tuple[float, ...] = field(default=DEFAULT_EXPONENTS)
    skin: str = "single"                     # "single" (one GGX lobe) or "two-lobe" (sharp + broad GGX)
    features: str = "plain"                  # "plain" (grey eyes) or "painted" (iris, lash lines, mouth line)

    def __post_init__(self) -> None:
        if self.brdf not in ("ggx", "model"):
            raise ReflectmmError(f"--brdf must be 'ggx' or 'model', got {self.brdf!r}")
        if self.skin not in SKIN_MODELS:
            raise ReflectmmError(f"--skin must be one of {', '.join(SKIN_MODELS)}, got {self.skin!r}")
        if self.features not in FEATURES:
            raise ReflectmmError(f"--features must be one of {', '.join(FEATURES)}, got {self.features!r}")
        if int(self.identities) < 1:
            raise ReflectmmError(f"--identities must be ≥ 1, got {self.identities}")
        if not (1 <= int(self.first_id) and int(self.first_id) + int(self.identities) - 1 <= 999):
            raise ReflectmmError(f"identity ids {self.first_id}..{self.first_id + self.identities - 1} do not fit "
                                 "the 3-digit Multi-PIE ids 001..999")
        w, h = (int(x) for x in self.image_size)
        if w < 16 or h < 16:
            raise ReflectmmError(f"--image-size must be at least 16x16, got {w}x{h}")
        self.image_size = (w, h)
        for name in ("noise", "landmark_noise", "expression", "shape_scale", "room_light", "background"):
            v = float(getattr(self, name))
            if not math.isfinite(v) or v < 0:
                raise ReflectmmError(f"--{name.replace('_', '-')} must be a finite number ≥ 0, got {v}")
        if self.uv_size < 16:
            raise ReflectmmError(f"--uv-size must be ≥ 16, got {self.uv_size}")
        if not 1 <= int(self.supersample) <= 8:
            raise ReflectmmError(f"--supersample must be 1..8, got {self.supersample}")

    def to_params(self) -> dict:
        d = asdict(self)
        d["image_size"] = list(self.image_size)
        d["cameras"] = None if self.cameras is None else list(self.cameras)
        d["flashes"] = None if self.flashes is None else list(self.flashes)
        d["exponents"] = list(self.exponents)
        if self.skin == "single":  # the default is not recorded: data sets made before --skin stay byte-identical
            d.pop("skin")
        if self.features == "plain":  # likewise for the features
            d.pop("features")
        return d


# --------------------------------------------------------------------------- lighting, encoding, layout

def room_light_sh(level: float = 0.15, order: int = 2) -> np.ndarray:
    """(3, (order+1)²) SH radiance coefficients of the studio's room light.

    A soft environment of mean radiance ``level``: brighter from above and slightly in front (ceiling lights),
    darker below, very slightly warm; ``L(d) = level · tint · (1 + 0.6 d·a + 0.25 (3 (d·a)² − 1)/2)`` with
    ``a = normalize(0, 1, 0.5)`` — exactly band-limited to order 2, projected with
    :func:`reflectmm_cli.shading.project_envmap`.
    """
    from reflectmm_cli.shading import equirect_directions, project_envmap

    a = np.array([0.0, 1.0, 0.5]) / math.sqrt(1.25)
    d = equirect_directions(256, 128)
    c = d @ a
    rad = level * (1 + 0.6 * c + 0.25 * 0.5 * (3 * c * c - 1))
    img = rad[..., None] * np.array([1.03, 1.0, 0.95])
    return project_envmap(img, order)


def encode_png_values(linear: np.ndarray) -> np.ndarray:
    """Linear values → uint8 pixel codes ``round(255 · clip(x, 0, 1) ** (1/1.2))``."""
    return encode_display(linear, "gamma", gamma=ENCODE_GAMMA, uint8=True)


def decode_png_values(codes: np.ndarray) -> np.ndarray:
    """uint8 codes → linear ``(p/255) ** 1.2`` (what ``preprocess-multipie`` does by default)."""
    return gamma_to_linear(np.asarray(codes, np.float64) / 255.0, ENCODE_GAMMA)


def identity_code(i: int) -> str:
    return f"{int(i):03d}"


def image_path(root: Path, identity: str, camera: str, shot: str, session: str = SESSION,
               recording: str = RECORDING) -> Path:
    """``root/data/sessionNN/multiview/SSS/RR/CC_C/SSS_NN_RR_CCC_II.png``."""
    return (Path(root) / "data" / f"session{session}" / "multiview" / identity / recording / camera
            / f"{identity}_{session}_{recording}_{camera_code(camera)}_{shot}.png")


def landmark_path(root: Path, identity: str, camera: str, session: str = SESSION, recording: str = RECORDING) -> Path:
    p = image_path(root, identity, camera, "00", session, recording)
    return p.with_name(p.stem + "_lm.pts")


def format_pts(points: np.ndarray) -> str:
    """iBUG .pts text (``version: 1``, ``n_points: 68``, ``{ x y ... }``), 3 decimals."""
    return _format_pts(points, decimals=3)


# --------------------------------------------------------------------------- identities

@dataclass
class Identity:
    code: str
    shape: np.ndarray
    exp: np.ndarray
    vertices: np.ndarray
    normals: np.ndarray
    maps: SkinMaps


def _identity_rng(seed: int, index: int, stream: int) -> np.random.Generator:
    return np.random.default_rng([int(seed) & 0xFFFFFFFF, int(index), int(stream), 0x4D50])


def make_identity(model, cfg: SynthConfig, index: int) -> Identity:
    """Identity number ``index`` (1-based id): shape, expression and skin maps; depends on (seed, index) only."""
    from reflectmm_cli.geometry import vertex_normals

    rng = _identity_rng(cfg.seed, index, 0)
    ks, ke = model.n_shape, model.n_exp
    shape = np.clip(rng.normal(size=ks), -3, 3) * model.shape_sigma.astype(np.float64) * cfg.shape_scale
    exp = np.clip(rng.normal(size=ke), -3, 3) * model.exp_sigma.astype(np.float64) * cfg.expression
    verts = model.vertices(shape, exp).astype(np.float64)
    normals = vertex_normals(verts, model.triangles).astype(np.float64)
    lm_uv = model.uv[model.landmarks].astype(np.float64)
    maps = skin_maps(lm_uv, sample_skin_params(rng), cfg.uv_size, exponents=cfg.exponents, brdf=cfg.brdf,
                     skin=cfg.skin, features=cfg.features)
    return Identity(identity_code(index), shape, exp, verts, normals, maps)


# --------------------------------------------------------------------------- rendering

def _camera(rc):
    from reflectmm_cli.geometry import Camera

    return Camera(rc.K, rc.R, rc.t, rc.width, rc.height, rc.name)


def render_identity(model, ident: Identity, rig: Rig, cfg: SynthConfig, room_sh: np.ndarray, *,
                    cameras: Iterable[str], flashes: Iterable[str],
                    on_camera: Callable[[str, dict[str, np.ndarray], np.ndarray], None],
                    progress_fn: Callable = lambda it, **kw: it, stats: dict | None = None) -> None:
    """Render every (camera, shot) of one identity; ``on_camera(name, {shot: uint8 H×W×3}, landmarks (68,2))``.

    The linear image is ``room + flash`` (+ noise) on the face, ``background`` elsewhere (flashes do not light
    the backdrop).  Shadow rays are cast only for face pixels with n·l > 0.
    """
    import time

    from reflectmm_cli.geometry.raycast import RayScene, rasterize, shadow_mask
    from reflectmm_cli.geometry.uv import sample_uv_map
    from reflectmm_cli.shading import shade_directional, shade_env
    from reflectmm_cli.synth.ggx import ggx_directional, ggx_two_lobe_directional

    scene = RayScene(ident.vertices, model.triangles, ident.normals)
    maps = ident.maps
    exps = np.asarray(cfg.exponents, np.float64)
    flashes = list(flashes)
    cam_list = list(cameras)
    idx = int(ident.code)
    st = stats if stats is not None else {}
    st.setdefault("primary_rays", 0)
    st.setdefault("shadow_rays", 0)
    st.setdefault("ray_seconds", 0.0)
    for ci, cname in enumerate(progress_fn(cam_list, desc=f"identity {ident.code}", unit="view")):
        cam0 = _camera(rig.camera(cname))
        ss = int(cfg.supersample)
        cam = cam0 if ss == 1 else cam0.with_size(cam0.width * ss, cam0.height * ss)
        t0 = time.perf_counter()
        ras = rasterize(scene, cam)
        st["primary_rays"] += cam.width * cam.height
        st["embree_seconds"] = st.get("embree_seconds", 0.0) + scene.stats.seconds
        st["ray_seconds"] += time.perf_counter() - t0
        m = ras.mask.copy()
        tri = model.triangles[ras.tri_id[m]]
        vv = ident.vertices
        tri_n = np.cross(vv[tri[:, 1]] - vv[tri[:, 0]], vv[tri[:, 2]] - vv[tri[:, 0]])
        # rays that hit the inside of the open face shell (seen from above or behind) show the backdrop: a real
        # head has hair there, and no stage may treat those pixels as skin
        front = (tri_n * (cam.center[None, :] - vv[tri[:, 0]])).sum(1) > 0
        m[m] = front
        p = ras.position[m].astype(np.float64)
        n = ras.normal[m].astype(np.float64)
        uv = ras.interpolate(model.uv.astype(np.float64), model.triangles)[m]
        alb = sample_uv_map(maps.albedo, uv)
        w = sample_uv_map(maps.weights, uv)
        if cfg.brdf == "ggx":
            rough = sample_uv_map(maps.roughness, uv)
            rho = sample_uv_map(maps.spec_intensity, uv)
            if maps.skin == "two-lobe":
                rough_b = sample_uv_map(maps.roughness_broad, uv)
                mix = sample_uv_map(maps.lobe_mix, uv)
        vdir = cam.center[None, :] - p
        vdir /= np.linalg.norm(vdir, axis=1, keepdims=True)
        # room light: SH environment (GGX mode: its specular part through the 3-lobe fit of the GGX lobe)
        rd, rs = shade_env(alb, w, exps, n, vdir, room_sh)
        room = rd + rs
        shots: dict[str, np.ndarray] = {}
        H, W = cam0.height, cam0.width
        nrng = _identity_rng(cfg.seed, idx, 1000 + ci)

        backdrop = encode_png_values(np.full((1, 1, 3), cfg.background))[0, 0]

        def finish(face_linear: np.ndarray) -> np.ndarray:
            if ss > 1:  # box filter of the k×k sub-pixel samples, in linear space
                hi = np.full((H * ss, W * ss, 3), cfg.background, np.float64)
                hi[m] = face_linear
                img = hi.reshape(H, ss, W, ss, 3).mean(axis=(1, 3))
                if cfg.noise > 0:
                    img += nrng.normal(0.0, cfg.noise, img.shape)
                return encode_png_values(img)
            if cfg.noise > 0:
                img = np.full((H, W, 3), cfg.background, np.float64)
                img[m] = face_linear
                img += nrng.normal(0.0, cfg.noise, img.shape)
                return encode_png_values(img)
            out = np.empty((H, W, 3), np.uint8)
            out[...] = backdrop
            out[m] = encode_png_values(face_linear)
            return out

        shots["00"] = finish(room)
        for fid in flashes:
            fl = rig.flash(fid)
            ldir = fl.position[None, :] - p
            d2 = (ldir * ldir).sum(1)
            E = fl.intensity / d2
            t0 = time.perf_counter()
            lit = shadow_mask(scene, p, n, fl.position)
            st["shadow_rays"] += scene.stats.cast
            st["embree_seconds"] = st.get("embree_seconds", 0.0) + scene.stats.seconds
            st["ray_seconds"] += time.perf_counter() - t0
            s = np.zeros_like(room)
            if lit.any():
                if cfg.brdf == "model":
                    s[lit] = shade_directional(alb[lit], w[lit], exps, n[lit], ldir[lit], vdir[lit],
                                               E[lit, None] * np.ones(3))
                elif maps.skin == "two-lobe":
                    s[lit] = ggx_two_lobe_directional(alb[lit], rho[lit], rough[lit], rough_b[lit], mix[lit], n[lit],
                                                      ldir[lit], vdir[lit], E[lit, None] * np.ones(3))
                else:
                    s[lit] = ggx_directional(alb[lit], rho[lit], rough[lit], n[lit], ldir[lit], vdir[lit],
                                             E[lit, None] * np.ones(3))
            shots[fid] = finish(room + s)
        lm2d, _ = cam0.project(ident.vertices[model.landmarks])
        if cfg.landmark_noise > 0:
            lm2d = lm2d + _identity_rng(cfg.seed, idx, 2000 + ci).normal(0.0, cfg.landmark_noise, lm2d.shape)
        on_camera(cname, shots, lm2d)


# --------------------------------------------------------------------------- the whole data set

def _resolve_selection(rig: Rig, cfg: SynthConfig) -> tuple[list[str], list[str]]:
    cams = list(cfg.cameras) if cfg.cameras else rig.camera_names
    fls = list(cfg.flashes) if cfg.flashes else rig.flash_ids
    for c in cams:
        rig.camera(c)
    for f in fls:
        rig.flash(f)
        if f not in ALL_FLASHES:
            raise ReflectmmError(f"flash id '{f}' is not a Multi-PIE flash (01..18)")
    if len(set(cams)) != len(cams) or len(set(fls)) != len(fls):
        raise ReflectmmError("--cameras / --flashes list a name twice")
    return cams, fls


def truth_arrays(model, ident: Identity, rig: Rig, cfg: SynthConfig, room_sh: np.ndarray,
                 landmarks: dict[str, np.ndarray], uv_mask: np.ndarray) -> dict[str, np.ndarray]:
    from reflectmm_cli.geometry.uv import sample_uv_map

    mp = ident.maps
    uv = model.uv.astype(np.float64)
    names = rig.camera_names
    arrays = {
        "shape_coeffs": ident.shape.astype(np.float64), "exp_coeffs": ident.exp.astype(np.float64),
        "vertices": ident.vertices.astype(np.float32), "normals": ident.normals.astype(np.float32),
        "camera_names": np.array(names, dtype=str),
        "K": np.stack([c.K for c in rig.cameras]), "R": np.stack([c.R for c in rig.cameras]),
        "t": np.stack([c.t for c in rig.cameras]), "cam_centers": np.stack([c.center for c in rig.cameras]),
        "image_size": np.array(cfg.image_size, np.int64),
        "flash_ids": np.array(rig.flash_ids, dtype=str),
        "flash_pos": np.stack([f.position for f in rig.flashes]),
        "flash_intensity": np.array([f.intensity for f in rig.flashes]),
        "albedo": mp.albedo, "weights": mp.weights, "exponents": np.asarray(cfg.exponents, np.float64),
        "spec_albedo": mp.spec_albedo, "uv_mask": uv_mask,
        "vertex_albedo": sample_uv_map(mp.albedo, uv).astype(np.float32),
        "vertex_weights": sample_uv_map(mp.weights, uv).astype(np.float32),
        "vertex_spec_albedo": sample_uv_map(mp.spec_albedo, uv).astype(np.float32),
        "brdf": np.array(cfg.brdf), "room_sh": room_sh.astype(np.float64),
        "pixel_scale": np.array(1.0), "encode_gamma": np.array(ENCODE_GAMMA),
        "landmark_views": np.array(list(landmarks), dtype=str),
        "landmarks_2d": np.stack([landmarks[k] for k in landmarks]).astype(np.float64),
    }
    if cfg.brdf == "ggx":
        arrays["roughness"] = mp.roughness
        arrays["spec_intensity"] = mp.spec_intensity
        arrays["vertex_roughness"] = sample_uv_map(mp.roughness, uv).astype(np.float32)
        arrays["vertex_spec_intensity"] = sample_uv_map(mp.spec_intensity, uv).astype(np.float32)
        arrays["f0"] = np.array(0.028)
        if mp.skin == "two-lobe":
            arrays["roughness_broad"] = mp.roughness_broad
            arrays["lobe_mix"] = mp.lobe_mix
            arrays["vertex_roughness_broad"] = sample_uv_map(mp.roughness_broad, uv).astype(np.float32)
            arrays["vertex_lobe_mix"] = sample_uv_map(mp.lobe_mix, uv).astype(np.float32)
    return arrays


def contact_sheet(thumbs: list[list[np.ndarray]], labels: list[str] | None = None) -> np.ndarray:
    """Rows of equally sized uint8 thumbnails → one uint8 RGB sheet with 2-px gaps."""
    th, tw = thumbs[0][0].shape[:2]
    cols = max(len(r) for r in thumbs)
    sheet = np.full((len(thumbs) * (th + 2) + 2, cols * (tw + 2) + 2, 3), 40, np.uint8)
    for r, row in enumerate(thumbs):
        for c, im in enumerate(row):
            sheet[2 + r * (th + 2): 2 + r * (th + 2) + th, 2 + c * (tw + 2): 2 + c * (tw + 2) + tw] = im
    return sheet


def _write_png_codes(path: Path, img: np.ndarray) -> Path:
    """Encode uint8 RGB codes as PNG (cv2, no colour management) and write it atomically."""
    import cv2

    from reflectmm_cli.artifacts import atomic_write_bytes

    ok, buf = cv2.imencode(".png", np.ascontiguousarray(img[..., ::-1]))
    if not ok:
        raise ReflectmmError("cannot encode PNG", path)
    return atomic_write_bytes(path, buf.tobytes())


def _refuse_stale(out: Path, cfg: SynthConfig, cams, fls) -> None:
    """Refuse an output folder that holds images, landmarks or truth this run would not overwrite (an earlier
    run's other identities, cameras or flashes): preprocess-multipie would read them as part of this data set,
    and one capture was built from two different faces.  Nothing is deleted: the folder may be a real data set.
    Hidden files and folders are not data set files and are not looked at: a killed run leaves the temporary
    ``.NAME.*.tmp`` file of its last atomic write, and the rerun must still resume."""
    from reflectmm_cli.workspace import walk_files

    have = [p for d in ("data", "truth") if (out / d).is_dir() for p in walk_files(out / d)]
    if not have:
        return
    mine: set[Path] = set()
    for k in range(cfg.identities):
        code = identity_code(cfg.first_id + k)
        mine.add(out / "truth" / f"{code}.npz")
        for c in cams:
            mine.add(landmark_path(out, code, c))
            mine.update(image_path(out, code, c, shot) for shot in ("00", *fls))
    stale = sorted(p for p in have if p not in mine)
    if stale:
        raise ReflectmmError(f"holds {len(stale)} file(s) that this run would not overwrite (e.g. "
                             f"{stale[0].relative_to(out)}: an earlier run's identities, cameras or flashes); give "
                             "an empty --out, or remove them", out)


def synth_multipie(out_dir: str | Path, cfg: SynthConfig, *, face_model=None, rig: Rig | str | Path | None = None,
                   meta_params: dict | None = None, producer: dict | None = None, cache_key: str | None = None,
                   inputs: list | None = None, progress_fn: Callable | None = None,
                   stats: dict | None = None) -> list[Path]:
    """Generate the synthetic Multi-PIE data set into ``out_dir``; returns the paths written (truth files,
    rig.toml, face_model.npz, contact_sheet.png — images and landmark files are not listed).

    ``face_model``: a FaceModel, a path to a ``face-model`` artifact, or None (procedural, ``cfg.face_vertices``).
    ``rig``: a Rig, a rig TOML path, or None (the packaged default); resized to ``cfg.image_size`` keeping the
    framing (focal length scales with the image height).
    """
    import cv2

    from reflectmm_cli.artifacts import atomic_write_text, write_artifact, write_png
    from reflectmm_cli.geometry import load_face_model, procedural_face_model, save_face_model
    from reflectmm_cli.geometry.uv import rasterize_uv
    from reflectmm_cli.progress import log, progress

    out = Path(out_dir)
    prog = progress_fn or (lambda it, **kw: progress(it, **kw))
    base_rig = rig if isinstance(rig, Rig) else load_rig(rig)
    W, H = cfg.image_size
    the_rig = base_rig.resized(W, H)
    cams, fls = _resolve_selection(the_rig, cfg)
    if face_model is None:
        model = procedural_face_model(n_vertices=int(cfg.face_vertices))
    elif isinstance(face_model, (str, Path)):
        model = load_face_model(face_model)
    else:
        model = face_model
    if model.landmarks.shape != (68,):
        raise ReflectmmError(f"face model has {model.landmarks.shape[0]} landmarks; synth multipie needs the 68 "
                             "iBUG landmarks")
    _refuse_stale(out, cfg, cams, fls)
    params = dict(meta_params or cfg.to_params())
    written: list[Path] = []
    written.append(atomic_write_text(out / "rig.toml", rig_to_toml(the_rig, "Rig of this synthetic data set "
                                                                   "(reflectmm synth multipie); see docs/pipeline.md")))
    written.append(save_face_model(model, out / "face_model.npz", params=params, producer=producer,
                                   cache_key=cache_key, inputs=inputs))
    room_sh = room_light_sh(cfg.room_light)
    uv_mask = rasterize_uv(model.uv, model.triangles, cfg.uv_size).mask
    sheet_rows: list[list[np.ndarray]] = []
    thumb_w = 128
    thumb_h = max(1, int(round(thumb_w * H / W)))
    sheet_flash = "07" if "07" in fls else (fls[0] if fls else None)
    for k in range(cfg.identities):
        index = cfg.first_id + k
        ident = make_identity(model, cfg, index)
        landmarks: dict[str, np.ndarray] = {}
        row_room: list[np.ndarray] = []
        row_flash: list[np.ndarray] = []

        def on_camera(cname, shots, lm2d, ident=ident, landmarks=landmarks, row_room=row_room,
                      row_flash=row_flash):
            for shot, img in shots.items():
                pending.append(pool.submit(_write_png_codes, image_path(out, ident.code, cname, shot), img))
            while len(pending) > 48:  # bound the memory held by queued images
                pending.pop(0).result()
            atomic_write_text(landmark_path(out, ident.code, cname), format_pts(lm2d))
            landmarks[cname] = lm2d
            if k < 4:
                row_room.append(cv2.resize(shots["00"], (thumb_w, thumb_h), interpolation=cv2.INTER_AREA))
                if sheet_flash:
                    row_flash.append(cv2.resize(shots[sheet_flash], (thumb_w, thumb_h),
                                                interpolation=cv2.INTER_AREA))

        pending: list = []
        with ThreadPoolExecutor(max_workers=3) as pool:  # PNG deflate and fsync release the GIL
            render_identity(model, ident, the_rig, cfg, room_sh, cameras=cams, flashes=fls, on_camera=on_camera,
                            progress_fn=prog, stats=stats)
            for fut in pending:
                fut.result()
        tpath = out / "truth" / f"{ident.code}.npz"
        write_artifact(tpath, "synth-truth", truth_arrays(model, ident, the_rig, cfg, room_sh, landmarks, uv_mask),
                       params=params, producer=producer, cache_key=cache_key, inputs=inputs,
                       extra_meta={"identity": ident.code, "skin": ident.maps.params.to_dict(),
                                   **({"skin_model": "two-lobe", "skin_two_lobe": ident.maps.two_lobe.to_dict()}
                                      if cfg.skin == "two-lobe" else {}),
                                   **({"features": cfg.features} if cfg.features != "plain" else {}),
                                   "views": cams, "flashes": fls, "session": SESSION, "recording": RECORDING,
                                   "units": "mm; linear pixel value = radiance; PNG = clip(x,0,1)**(1/1.2)",
                                   "weights_note": ("exact rendering BRDF" if cfg.brdf == "model" else
                                                    "3-lobe NNLS fit of the GGX lobe at normal view "
                                                    "(reference only; rendering used GGX)")})
        written.append(tpath)
        if row_room:
            sheet_rows.append(row_room)
            if row_flash:
                sheet_rows.append(row_flash)
        log.debug(f"synth multipie: identity {ident.code} done")
    if sheet_rows:
        written.append(write_png(out / "contact_sheet.png", contact_sheet(sheet_rows)))
    return written
