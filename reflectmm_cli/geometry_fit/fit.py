"""Multi-view morphable-model fit: shared shape/expression, one pose per view, landmarks + photometric + priors.

Unknowns (optimised with L-BFGS, strong-Wolfe line search, in torch):

* ``zs`` (Ks,), ``ze`` (Ke,): shape and expression coefficients in units of their prior σ
  (``shape_coeffs = zs · shape_sigma``);
* per view ``δ_v`` (3,) and ``τ_v`` (3,): ``R_v = exp([δ_v]×) R0_v``, ``t_v = t0_v + τ_v · t_unit``
  (the pose of the head in camera ``v``, which is the camera's extrinsics in model space);
* photometric stage only: per-view SH lighting (V, 9, 3) and, without a model texture, a per-vertex albedo;
* flash stage only: one log-gain per flash (relative intensities); its per-vertex albedo is eliminated in closed
  form inside the loss (:func:`.photometric.flash_loss`).

Loss (docs/fit-geometry.md):
``w_lm · Σ w_i huber(‖π(R_v X_i + t_v) − x_vi‖, δ_px) / Σ w_i`` +
``w_photo · mean_visible Σ_c charbonnier((ρ_vm − I_v(π(X_m)))/s)`` + ``w_shape ‖zs‖² + w_exp ‖ze‖²``, and in the
flash stage ``w_flash · mean_lit,visible Σ_c charbonnier((c_m g_f I_f max(n·l, 0)/d² − O_vf(π(X_m)))/s)``.

Views without landmarks (NaN): placed by the rig prior under the head, out of the image terms, then registered by
the flash term with everything else held (:func:`_register_unmarked`), optionally refined with the room-light
images' agreement across views (``w_room``, :func:`_room_consistency`); per-view evidence and uncertainty:
:mod:`.placement`.
"""

from __future__ import annotations

import contextlib
import logging
import math
import time
from dataclasses import dataclass, field

import numpy as np
import torch

from reflectmm_cli.errors import ReflectmmError
from reflectmm_cli.geometry.camera import axis_angle_to_matrix, camera_centers, project
from reflectmm_cli.geometry.rotations import matrix_to_axis_angle, skew
from reflectmm_cli.geometry_fit.contour import CHIN, jaw_contour, slide
from reflectmm_cli.geometry_fit.init import rigid_align
from reflectmm_cli.geometry_fit.landmarks import landmark_weights
from reflectmm_cli.geometry.face_model import vertex_normals
from reflectmm_cli.geometry_fit.model import ShapeModel
from reflectmm_cli.geometry_fit.photometric import (
    SH_ORDER,
    charbonnier,
    flash_loss,
    gather_bilinear,
    inside_image,
    photometric_loss,
    sample_images,
    sh_kernel,
    solve_albedo,
    solve_lighting,
)
from reflectmm_cli.geometry_fit.placement import pose_curvature, pose_sigmas, rig_shift, view_evidence
from reflectmm_cli.geometry_fit.visibility import vertex_visibility
from reflectmm_cli.progress import progress
from reflectmm_cli.threads import torch_threads
from reflectmm_cli.shading import sh_basis

log = logging.getLogger("reflectmm")

#: Skin colour (linear RGB) used as the albedo when the model has no texture and a per-vertex estimate is off.
DEFAULT_SKIN = np.array([0.55, 0.38, 0.30])


def huber(x: torch.Tensor, delta: float) -> torch.Tensor:
    """Huber penalty of residual magnitudes ``x`` ≥ 0: ½x² for x ≤ δ, δ(x − ½δ) beyond (C¹)."""
    return torch.where(x <= delta, 0.5 * x * x, delta * (x - 0.5 * delta))


@dataclass
class FitConfig:
    """Weights and schedule of :func:`fit_geometry` (defaults measured on the synthetic Multi-PIE rig)."""

    landmark_iters: int = 400       # L-BFGS iterations (at most), landmarks + priors only
    photo_rounds: int = 2           # visibility refreshes in the photometric stage (0 = landmarks only)
    photo_iters: int = 40           # L-BFGS iterations per round
    landmark_sigma_px: float = 1.0  # assumed landmark noise (px): scales the landmark term against the priors
    huber_px: float = 3.0           # Huber threshold of the landmark residual (px)
    w_landmark: float = 1.0
    w_photo: float = 1.0
    w_shape: float = 1.0            # weight of ½‖shape/σ‖² (1 = Gaussian prior, MAP with landmark_sigma_px)
    w_exp: float = 1.0              # weight of ½‖exp/σ‖²
    rig_sigma_mm: float = 10.0      # soft rig constraint: camera centres within ~σ of the rig moved rigidly
                                    # (0 disables; needs rig_centers in the ViewSet)
    rig_rot_sigma_deg: float = 0.0  # soft rig constraint on the camera orientations: each view's rotation within
                                    # ~σ of the rig's, moved by the same head rotation (0 disables; needs
                                    # rig_R in the ViewSet and rig_sigma_mm > 0).  For a calibrated rig.
    head_sigma_mm: float = 25.0     # prior on where the head sits in the rig frame: the rig's look-at point
                                    # (its origin) within ~σ of the model origin.  Breaks the face-size /
                                    # distance ambiguity of a rig whose cameras all look from one side
                                    # (0 disables)
    unmarked_sigma_mm: float = 100.0  # soft rig constraint σ of a view without landmarks (0: rig_sigma_mm): wide,
                                      # a camera no identity annotates has only a nominal table's place; the flash
                                      # registration moves it (and is rejected beyond 3 σ)
    unmarked_rot_sigma_deg: float = 2.0  # prior on the orientation of a view without landmarks: the rig's,
                                         # moved by the head rotation, within ~σ
    register_blur_px: tuple[float, ...] = (4.0, 2.0, 0.0)  # views without landmarks, with flash images: one
                                    # round per blur (px) registering only their poses by the flash term (the
                                    # other views and the face held) after the joint stages; () = off
    register_iters: int = 40        # L-BFGS iterations per registration round
    register_room_blur_px: tuple[float, ...] = (2.0, 0.0)  # views registered by their flash images: then one
                                    # round per blur (px) with the room-light photo-consistency beside the flash
                                    # term (:func:`_room_consistency`; with w_room > 0)
    w_room: float = 0.0             # weight of the room-light photo-consistency, a mean relative Charbonnier
                                    # residual like the flash term (0 = off)
    joint_rounds: int = 0           # after the registration: rounds of the flash term over the views with
                                    # landmarks *and* the registered views without, these held to the head at
                                    # their registered places; face, head and the views with landmarks free
                                    # (0 = off; :func:`_joint_rounds`)
    joint_blur_px: float = 2.0      # Gaussian blur of the images in the joint rounds (px)
    joint_gate_mm: float = 25.0     # a registered view enters the joint rounds only if its registration left it
                                    # within this distance of the rig (mm): further, the rig and the images
                                    # disagree, and a misplaced view would pull the face
    joint_register: bool = False    # register the views without landmarks again after each joint round (finest
                                    # blur only): a little closer on the demo, about 2 s more per round and identity
    joint_unmarked_weight: float = 1.0  # weight of the images of the views without landmarks in the joint rounds,
                                        # relative to the others' (their flashes count in full); below 1 a view a
                                        # few mm off its true place bends the face less
    joint_max_landmark_rise: float = 1.4  # the joint rounds are undone when they raise the median landmark RMS of
                                          # the views with landmarks by more than this factor (a view that the
                                          # gate let in pulled the face off its landmarks)
    uncertainty: str = "unmarked"   # per-view pose uncertainty from the curvature of the last stage's objective:
                                    # "unmarked" (the views without landmarks), "all" or "none"
    fit_expression: bool = True
    photo_vertices: int = 2000      # at most this many skin vertices in the photometric term
    photo_min_cos: float = 0.5      # a vertex enters a view's photometric term only if n·v exceeds this
                                    # (grazing vertices sample the silhouette, where the background bleeds in)
    photo_blur_px: tuple[float, ...] = (1.5, 0.0)  # Gaussian blur of the images per photometric round
    flash_rounds: int = 0           # rounds of the flash (point-light) photometric term after the room-light
                                    # rounds (0 = off; needs flash images in the ViewSet)
    flash_iters: int = 60           # L-BFGS iterations per flash round
    w_flash: float = 30.0           # the flash term is a mean relative (Charbonnier) residual over ~10⁵ samples,
                                    # the landmark term a mean squared pixel residual over ~700; 30 holds on
                                    # every synthetic setup measured (docs/benchmarks.md, "The flash term")
    flash_highlight_deg: float = 40.0  # a (view, flash) sample whose normal is within this angle of the half
                                       # vector is left out (the specular highlight is not Lambertian)
    flash_min_cos: float = 0.2      # a vertex enters a flash's term only if n·l exceeds this
    flash_gains: bool = True        # fit one relative intensity per flash (the table's intensities are nominal)
    albedo: str = "auto"            # "auto": model texture if any else per-vertex estimate; "texture",
                                    # "per-vertex", "constant"
    group_weights: dict[str, float] | None = None
    jaw_contour: bool = False       # the cheek points 0–4 and 12–16 slide along the model's contour lines to each
                                    # view's outline, 5–11 are left out (a detector's jaw follows the silhouette;
                                    # :mod:`.contour`)
    contour_rounds: int = 2         # landmark fits after the first with the jaw vertices slid to the outline
    contour_behind_mm: float = 70.0  # the contour lines reach this far behind the model's jaw ends (0, 16)
    contour_gate_px: float = 0.0    # a sliding point further than this across the outline after a slide is left
                                    # out until the next slide (0 = keep every point)
    dtype: str = "float64"
    threads: int = 1                # torch intra-op threads during the fit (the tensors are small: one thread
                                    # is several times faster than two on a loaded 2-core machine)

    def as_dict(self) -> dict:
        return {k: list(v) if isinstance(v, tuple) else v for k, v in self.__dict__.items()}


@dataclass
class ViewSet:
    """The views of one identity: names, intrinsics, initial poses, landmarks and (optional) images.

    K, R0: (V, 3, 3); t0: (V, 3); landmarks: (V, 68, 2) pixels, NaN where missing (a view without any is placed
    by the rig and the image terms: it needs rig_centers and rig_R, and at least one view with landmarks);
    images: (V, h, w, 3) linear room-light images or None; image_size (W, H) of the full frame;
    rig_centers: (V, 3) nominal camera positions in the rig frame (soft rig constraint) or None;
    rig_R: (V, 3, 3) the rig's world-to-camera rotations (soft orientation constraint) or None;
    image_origin: (V, 2) full-frame pixel (x0, y0) of each image's top-left pixel when the images are crops
    (capture ``crop_origin``); landmarks and K are always in full-frame pixels.
    Flash images (optional, the flash term): flash_images (V, F, h, w, 3) linear, one flash each, same crops as
    ``images``; flash_view (F,) index of the view whose camera carries the flash (its fitted centre is the
    flash position) or −1; flash_rig_pos (F, 3) rig-frame positions of the flashes with flash_view −1 (mapped by
    the fitted head pose; needs rig_centers); flash_intensity (F,); flash_saturated (V, F, h, w) bool or None.
    """

    names: list[str]
    K: np.ndarray
    R0: np.ndarray
    t0: np.ndarray
    landmarks: np.ndarray
    image_size: tuple[int, int]
    images: np.ndarray | None = None
    rig_centers: np.ndarray | None = None
    image_origin: np.ndarray | None = None
    rig_R: np.ndarray | None = None
    flash_images: np.ndarray | None = None
    flash_view: np.ndarray | None = None
    flash_rig_pos: np.ndarray | None = None
    flash_intensity: np.ndarray | None = None
    flash_saturated: np.ndarray | None = None

    def __post_init__(self) -> None:
        V = len(self.names)
        if self.rig_centers is not None:
            self.rig_centers = np.asarray(self.rig_centers, dtype=np.float64).reshape(V, 3)
        if self.rig_R is not None:
            self.rig_R = np.asarray(self.rig_R, dtype=np.float64).reshape(V, 3, 3)
        self.K = np.asarray(self.K, dtype=np.float64).reshape(V, 3, 3)
        self.R0 = np.asarray(self.R0, dtype=np.float64).reshape(V, 3, 3)
        self.t0 = np.asarray(self.t0, dtype=np.float64).reshape(V, 3)
        self.landmarks = np.asarray(self.landmarks, dtype=np.float64)
        if self.landmarks.shape != (V, 68, 2):
            raise ReflectmmError(f"landmarks must be (V, 68, 2) with V = {V} views, got {self.landmarks.shape}")
        if self.images is not None and self.images.shape[0] != V:
            raise ReflectmmError(f"{self.images.shape[0]} images for {V} views")
        self.image_origin = (np.zeros((V, 2)) if self.image_origin is None
                             else np.asarray(self.image_origin, dtype=np.float64).reshape(V, 2))
        if self.flash_images is not None:
            fi = self.flash_images
            if fi.ndim != 5 or fi.shape[0] != V or fi.shape[-1] != 3:
                raise ReflectmmError(f"flash images must be (V, F, h, w, 3) with V = {V}, got {fi.shape}")
            F = fi.shape[1]
            self.flash_view = np.asarray(self.flash_view, dtype=np.int64).reshape(F)
            self.flash_intensity = np.asarray(self.flash_intensity, dtype=np.float64).reshape(F)
            self.flash_rig_pos = (np.full((F, 3), np.nan) if self.flash_rig_pos is None
                                  else np.asarray(self.flash_rig_pos, dtype=np.float64).reshape(F, 3))
            if self.flash_saturated is not None and self.flash_saturated.shape != fi.shape[:4]:
                raise ReflectmmError(f"flash saturation masks {self.flash_saturated.shape} do not match the flash "
                                     f"images {fi.shape[:4]}")

    def image_K(self) -> np.ndarray:
        """(V, 3, 3) intrinsics in the pixel frame of the stored (possibly cropped) images."""
        K = self.K.copy()
        K[:, 0, 2] -= self.image_origin[:, 0]
        K[:, 1, 2] -= self.image_origin[:, 1]
        return K


@dataclass
class GeometryFit:
    """Result of :func:`fit_geometry` (numpy, float64)."""

    shape_coeffs: np.ndarray
    exp_coeffs: np.ndarray
    vertices: np.ndarray
    R: np.ndarray
    t: np.ndarray
    K: np.ndarray
    landmark_rmse_px: np.ndarray
    landmark_px: np.ndarray          # (V, 68, 2) fitted landmark projections
    photo_residual: np.ndarray       # (V,) RMS linear residual over visible skin vertices (NaN if no images)
    visible_count: np.ndarray        # (V,) visible photometric samples
    sh: np.ndarray | None = None     # (V, 9, 3)
    albedo: np.ndarray | None = None  # (M, 3) at ``photo_sample``
    photo_sample: np.ndarray | None = None
    flash_residual: np.ndarray | None = None  # (V,) RMS linear residual of the flash term per view (or None)
    flash_gain: np.ndarray | None = None  # (F,) fitted relative flash intensities (geometric mean 1; NaN = unused)
    history: list[dict] = field(default_factory=list)
    seconds: float = 0.0
    evidence: list[str] = field(default_factory=list)  # (V,) what placed each view: "landmarks" or "rig", and
                                                       # "+photo" / "+flash" for the image terms it entered
    center_sigma_mm: np.ndarray | None = None    # (V,) 1-σ of each camera centre (the others held), mm
    rotation_sigma_deg: np.ndarray | None = None  # (V,) 1-σ of each camera orientation (largest axis), degrees
    rig_shift_mm: np.ndarray | None = None       # (V,) fitted centre − the rig's centre under the fitted head, mm
    registered: np.ndarray | None = None         # (V,) bool: a view without landmarks whose registration by the
                                                 # flash images was kept (False: rejected or not run)
    joined: np.ndarray | None = None             # (V,) bool: a view without landmarks whose images shaped the face
                                                 # in the joint rounds (False: left out or not run)
    room_refined: np.ndarray | None = None       # (V,) bool: ... and then refined with the room-light
                                                 # photo-consistency (False: undone or not run)

    @property
    def cam_centers(self) -> np.ndarray:
        return camera_centers(self.R, self.t)


def _blur(images: np.ndarray, sigma: float) -> np.ndarray:
    if sigma <= 0:
        return images
    import cv2

    return np.stack([cv2.GaussianBlur(im, (0, 0), sigma) for im in images])


def _room_images(prob: "_FitProblem", blur: float) -> torch.Tensor:
    """The room-light images blurred by ``blur`` px as a (V, 3, h, w) tensor of the fit's dtype."""
    imgs = _blur(np.asarray(prob.views.images, dtype=np.float32), blur)
    return prob.tt(np.ascontiguousarray(imgs.transpose(0, 3, 1, 2)))


def fit_geometry(model: ShapeModel, views: ViewSet, config: FitConfig | None = None, device: str = "cpu"
                 ) -> GeometryFit:
    """Fit shape, expression and per-view poses to landmarks (and images) of one identity.

    Args:
        model: the linear face model; views: landmarks, intrinsics, initial poses and images of each view.
        config: weights and schedule; device: torch device.
    Returns:
        A :class:`GeometryFit` (coefficients, vertices, per-view R, t, residuals).
    """
    cfg = config or FitConfig()
    if cfg.uncertainty not in ("none", "unmarked", "all"):
        raise ReflectmmError(f"uncertainty must be none, unmarked or all, got {cfg.uncertainty!r}")
    if cfg.albedo not in ("auto", "texture", "per-vertex", "constant"):
        raise ReflectmmError(f"albedo must be auto, texture, per-vertex or constant, got {cfg.albedo!r}")
    with torch_threads(cfg.threads):
        return _fit(model, views, cfg, device)


def lbfgs_minimise(params, loss_fn, iters: int) -> "torch.optim.LBFGS":
    """One L-BFGS run (at most ``iters`` iterations, strong Wolfe line search, history 30) of the scalar
    ``loss_fn()`` over the tensors ``params``, in place; returns the optimiser (its state counts the evaluations)."""
    opt = torch.optim.LBFGS(params, lr=1.0, max_iter=iters, history_size=30, tolerance_grad=1e-9,
                            tolerance_change=1e-10, line_search_fn="strong_wolfe")

    def closure():
        opt.zero_grad()
        loss = loss_fn()
        loss.backward()
        return loss

    opt.step(closure)
    return opt


class _FitProblem:
    """The unknowns, fixed tensors and loss terms of one :func:`fit_geometry` run (the record every stage takes).

    Unknowns (torch leaves): ``zs`` (Ks,), ``ze`` (Ke,), per-view ``dw``/``dtr`` (V, 3) and, with the soft rig
    constraint, the head's ``dwh``/``dth`` (3,).  Parameter scaling: one unit of τ moves a point ≈ 10 px sideways
    (depth: ≈ f·r·Δz/Z² for a face of radius r), one unit of δ is 0.1 rad.  ``history`` collects one entry per
    L-BFGS run and ``bar`` ticks once per stage.
    """

    #: The names of the unknowns (torch leaves), for the code that holds, saves or restores all of them.
    UNKNOWNS = ("zs", "ze", "dw", "dtr", "dwh", "dth")

    def __init__(self, model: ShapeModel, views: ViewSet, cfg: FitConfig, device: str):
        self.model, self.views, self.cfg, self.device = model, views, cfg, device
        self.dtype = dtype = {"float64": torch.float64, "float32": torch.float32}[cfg.dtype]
        self.V = V = len(views.names)
        tt = self.tt
        self.ts = model.torch_parts(dtype, device)
        lm_obs = views.landmarks
        self.valid = valid = np.isfinite(lm_obs).all(-1)
        for v in range(V):
            if 0 < valid[v].sum() < 6:
                raise ReflectmmError(f"view {views.names[v]}: only {int(valid[v].sum())} valid landmarks "
                                     "(at least 6 needed)")
        self.marked = marked = valid.any(1)
        if not marked.any():
            raise ReflectmmError("no view has landmarks: at least one view needs them to place the face")
        wl = landmark_weights(cfg.group_weights)[None, :] * valid
        if cfg.jaw_contour:  # the chin follows the jaw line above the neck: left out (:mod:`.contour`)
            wl[:, list(CHIN)] = 0.0
        self.used = wl > 0  # (V, 68): the landmarks the fit weighs (a group of weight 0 is not reported either)
        self.wl_t = self.wl_all_t = tt(wl)
        self.wsum = float(wl.sum())
        self.obs_t = tt(np.where(valid[..., None], lm_obs, 0.0))
        self.K_t, self.R0_t, self.t0_t = tt(views.K), tt(views.R0), tt(views.t0)
        self.jaw = (jaw_contour(model.mean, model.triangles, model.landmarks, behind_mm=cfg.contour_behind_mm)
                    if cfg.jaw_contour else None)
        self.lm_ids = np.tile(model.landmarks, (V, 1))  # (V, 68) each view's landmark vertices
        self.lm_normals = np.zeros((V, 68, 2))  # sliding points: the outline's image normal (residual along it)
        self._set_lm_ids(self.lm_ids, self.lm_normals)
        depth = np.abs(views.t0[:, 2]).mean()
        f = float(views.K[:, 0, 0].mean())
        self.t_unit = 10.0 * depth / f
        lm0 = model.mean[model.landmarks]
        radius = float(np.sqrt(((lm0 - lm0.mean(0)) ** 2).sum(-1).mean()))
        self.tv_unit = torch.tensor([self.t_unit, self.t_unit, self.t_unit * depth / max(radius, 1e-6)],
                                    dtype=dtype, device=device)
        self.r_unit = 0.1
        self.zs = torch.zeros(model.n_shape, dtype=dtype, device=device, requires_grad=True)
        self.ze = torch.zeros(model.n_exp if cfg.fit_expression else 0, dtype=dtype, device=device,
                              requires_grad=True)
        self.dw = torch.zeros(V, 3, dtype=dtype, device=device, requires_grad=True)
        self.dtr = torch.zeros(V, 3, dtype=dtype, device=device, requires_grad=True)
        self._init_rig()
        self._check_unmarked()
        self.probe: torch.Tensor | None = None
        self.pose_fn = None  # optional (R, t) -> (R, t) applied to the poses (the joint camera registration)
        self.registered = np.zeros(V, dtype=bool)  # views without landmarks registered by the flash images
        self.room_refined = np.zeros(V, dtype=bool)  # ... and then refined with the room-light photo-consistency
        self.joined = np.zeros(V, dtype=bool)  # ... whose images shaped the face in the joint rounds
        self.last_loss = None
        self.history: list[dict] = []
        self.n_photo = cfg.photo_rounds if (views.images is not None and cfg.w_photo > 0) else 0
        self.n_flash = cfg.flash_rounds if (views.flash_images is not None and cfg.w_flash > 0) else 0
        self.bar = progress(range(1 + self.n_photo + self.n_flash), desc="fit-geometry", unit="stage")

    def _init_rig(self) -> None:
        """The rigid rig → model transform (the head pose in the rig frame) of the soft rig constraint."""
        views, cfg, tt, V = self.views, self.cfg, self.tt, self.V
        self.use_rig = use_rig = views.rig_centers is not None and cfg.rig_sigma_mm > 0 and V >= 3
        if use_rig:
            Rh0, th0, _ = rigid_align(views.rig_centers, camera_centers(views.R0, views.t0))
        else:
            Rh0, th0 = np.eye(3), np.zeros(3)
        self.Rh0_t, self.th0_t = tt(Rh0), tt(th0)
        self.rig_t = tt(views.rig_centers) if use_rig else None
        self.use_rot = use_rot = use_rig and views.rig_R is not None and cfg.rig_rot_sigma_deg > 0
        self.rigR_t = tt(views.rig_R) if use_rot else None
        self.rot_sigma = math.radians(cfg.rig_rot_sigma_deg) if use_rot else 1.0
        self.dwh = torch.zeros(3, dtype=self.dtype, device=self.device, requires_grad=use_rig)
        self.dth = torch.zeros(3, dtype=self.dtype, device=self.device, requires_grad=use_rig)
        self.pose_params = [self.dw, self.dtr] + ([self.dwh, self.dth] if use_rig else [])

    def _check_unmarked(self) -> None:
        """Priors of the views without landmarks: their centre (σ ``unmarked_sigma_mm``) and orientation (σ
        ``unmarked_rot_sigma_deg``) follow the rig under the fitted head; refused when there is no rig to follow."""
        views, cfg, V = self.views, self.cfg, self.V
        um = ~self.marked
        self.unmarked_sigma = cfg.unmarked_sigma_mm or cfg.rig_sigma_mm  # mm; 0 falls back to the rig's σ
        self.rig_w_t = self.tt(np.where(um, 1.0 / self.unmarked_sigma ** 2
                                        if cfg.rig_sigma_mm > 0 else 0.0, 1.0 / max(cfg.rig_sigma_mm, 1e-12) ** 2))
        self.unmarked_rot_w_t = None
        if not um.any():
            return
        names = ", ".join(n for n, u in zip(views.names, um) if u)
        if not self.use_rig or views.rig_R is None or cfg.unmarked_rot_sigma_deg <= 0:
            raise ReflectmmError(f"view(s) {names} have no landmarks and nothing else places them: they need the "
                                 "rig (rig centres and orientations, rig_sigma_mm > 0, unmarked_rot_sigma_deg > 0, "
                                 f"at least 3 views; here {V})")
        self.rigR_t = self.tt(views.rig_R)
        self.unmarked_rot_w_t = self.tt(um / math.radians(cfg.unmarked_rot_sigma_deg) ** 2)

    def tt(self, a) -> torch.Tensor:
        return torch.as_tensor(np.ascontiguousarray(a), dtype=self.dtype, device=self.device)

    def _set_lm_ids(self, ids: np.ndarray, normals: np.ndarray) -> None:
        """Per-view landmark vertices (V, 68) and outline normals (V, 68, 2): the model restricted to the vertices'
        union, each view's rows in it, and which residuals are measured across the outline only."""
        self.lm_ids, self.lm_normals = np.asarray(ids, dtype=np.int64), np.asarray(normals, dtype=np.float64)
        if self.jaw is None:
            return
        u, inv = np.unique(self.lm_ids, return_inverse=True)
        self.lm_sub = self.ts.subset(u)
        self.lm_rows_t = torch.as_tensor(inv.reshape(self.lm_ids.shape), dtype=torch.long, device=self.device)
        self.lm_normals_t = self.tt(self.lm_normals)
        self.lm_across_t = torch.as_tensor((self.lm_normals ** 2).sum(-1) > 0, device=self.device)[..., None]

    def slide_jaw(self) -> None:
        """Move each view's sliding jaw points to the outline of the current fit (:func:`.contour.slide`)."""
        if self.jaw is None:
            return
        X, R, t = self.numpy_geometry()
        ids, normals = self.lm_ids.copy(), self.lm_normals.copy()
        pts = self.jaw.points
        gate = np.ones((self.V, 68))
        for v in np.nonzero(self.marked)[0]:
            ids[v, pts], normals[v, pts], across = slide(self.jaw, X, self.views.K[v], R[v], t[v],
                                                         self.views.landmarks[v, pts], self.model.landmarks[pts])
            if self.cfg.contour_gate_px > 0:
                gate[v, pts] = ~(across > self.cfg.contour_gate_px)  # (NaN: a point that keeps its vertex stays)
        self._set_lm_ids(ids, normals)
        self.wl_t = self.wl_all_t * self.tt(gate)

    def poses(self):
        """Per-view world-to-camera (R (V, 3, 3), t (V, 3)) at the current unknowns."""
        R = axis_angle_to_matrix(self.dw * self.r_unit) @ self.R0_t
        t = self.t0_t + self.dtr * self.tv_unit
        if self.pose_fn is not None:
            R, t = self.pose_fn(R, t)
        if self.probe is not None:
            R, t = self._probed(R, t)
        return R, t

    def _probed(self, R, t):
        """Poses moved by ``probe`` (V, 6): a centre shift δc (mm) that keeps the model origin on the same pixel
        (the camera turns to keep aiming at it), then a turn ω in units of 1 / distance (rad), so that both
        halves move the image by similar amounts (:mod:`.placement`)."""
        c = camera_centers(R, t)
        c2 = c + self.probe[:, 3:]
        a = -c2 / torch.linalg.norm(c2, dim=-1, keepdim=True)          # new direction to the origin
        b = -c / torch.linalg.norm(c, dim=-1, keepdim=True)            # old one
        v = torch.cross(a, b, dim=-1)
        vx = skew(v)
        Q = torch.eye(3, dtype=self.dtype, device=self.device) + vx + vx @ vx / (1 + (a * b).sum(-1))[:, None, None]
        dist = torch.linalg.norm(c, dim=-1, keepdim=True).detach()
        R = axis_angle_to_matrix(self.probe[:, :3] / dist) @ R @ Q      # Q a = b: the origin stays on its ray
        return R, -(R @ c2[..., None])[..., 0]

    def verts(self) -> torch.Tensor:
        return self.ts.vertices(self.zs, self.ze)

    def lm_loss(self, X, R, t, landmarks_only=False):
        """Weighted Huber landmark term (divided by the weight sum and σ_lm²) and the projections (V, 68, 2).
        ``X``: the full mesh, or with ``landmarks_only`` the (68, 3) landmark vertices (or (V, 68, 3) per view)."""
        if not landmarks_only:
            L = X[self.ts.landmarks] if self.jaw is None else X[torch.as_tensor(self.lm_ids, device=X.device)]
        else:
            L = X
        if L.dim() == 2:
            L = L[None].expand(self.V, -1, -1)
        uv, _ = project(L, self.K_t, R, t)
        d = uv - self.obs_t
        if self.jaw is not None:  # a point on the outline: only its distance across the outline counts
            d = torch.where(self.lm_across_t, (d * self.lm_normals_t).sum(-1, keepdim=True) * self.lm_normals_t, d)
        r = torch.sqrt((d * d).sum(-1) + 1e-12)
        return (self.wl_t * huber(r, self.cfg.huber_px)).sum() / (self.wsum * self.cfg.landmark_sigma_px ** 2), uv

    def landmark_term(self, R, t) -> torch.Tensor:
        if self.jaw is not None:
            return self.lm_loss(self.lm_sub.vertices(self.zs, self.ze)[self.lm_rows_t], R, t, True)[0]
        return self.lm_loss(self.ts.landmark_vertices(self.zs, self.ze), R, t, True)[0]

    def head(self):
        """The rig → model rigid transform (Rh, th): a rig-frame point x sits at ``Rh x + th`` in model space."""
        return axis_angle_to_matrix(self.dwh * self.r_unit) @ self.Rh0_t, self.th0_t + self.dth * self.t_unit

    def prior(self, R, t):
        """Negative log priors (½‖z‖², rig), divided by the landmark weight sum like the landmark term."""
        cfg, zs, ze = self.cfg, self.zs, self.ze
        p = 0.5 * cfg.w_shape * (zs * zs).sum() + 0.5 * cfg.w_exp * (ze * ze).sum()
        if self.use_rig:
            c = camera_centers(R, t)
            Rh, th = self.head()
            ch = self.rig_t @ Rh.T + th
            if self.marked.all():  # one σ for every view: the sum in the order it always had
                p = p + 0.5 * ((c - ch) ** 2).sum() / cfg.rig_sigma_mm ** 2
            else:
                p = p + 0.5 * (((c - ch) ** 2).sum(-1) * self.rig_w_t).sum()
            if self.unmarked_rot_w_t is not None:  # views without landmarks follow the rig's aim
                p = p + 0.25 * (((R - self.rigR_t @ Rh.T) ** 2).sum((1, 2)) * self.unmarked_rot_w_t).sum()
            if self.use_rot:
                # model → camera of view v is R_rig,v · Rhᵀ when the head pose (rig → model) is (Rh, th);
                # ‖ΔR‖²_F = 2·(2 − 2cos θ) ≈ 2θ² for a rotation error θ, so ¼‖ΔR‖²/σ² ≈ ½θ²/σ²
                p = p + 0.25 * ((R - self.rigR_t @ Rh.T) ** 2).sum() / self.rot_sigma ** 2
            if cfg.head_sigma_mm > 0:
                p = p + 0.5 * (th * th).sum() / cfg.head_sigma_mm ** 2
        return p / self.wsum

    def run_lbfgs(self, params, closure_loss, iters: int, stage: str, tick: bool = True) -> None:
        """Minimise ``closure_loss()`` over ``params`` (at most ``iters`` L-BFGS iterations, strong Wolfe) and
        record the final loss in ``history`` (``tick``: one step of the progress bar)."""
        if iters <= 0:
            return
        with self.held_out_of(params):
            opt = lbfgs_minimise(params, closure_loss, iters)
        self.last_loss = closure_loss
        with torch.no_grad():
            final = float(closure_loss())
        self.history.append({"stage": stage, "loss": final, "evals": int(opt.state[opt._params[0]]["func_evals"])})
        if tick:
            next(self.bar, None)
        log.debug("fit-geometry: %s loss %.6g after %d evaluations", stage, final, self.history[-1]["evals"])

    @contextlib.contextmanager
    def held_out_of(self, params=()):
        """The problem's unknowns that are not in ``params`` taken out of autograd for the run (a registration
        moves only the views' poses: the face and the head are then constants, the backward pass does not go
        through the mesh and :meth:`_SubMesh.surface` computes the surface once).  The gradients of ``params``
        are the same, so the run is too, to the bit."""
        held = [p for p in (getattr(self, k) for k in self.UNKNOWNS)
                if p.requires_grad and not any(p is q for q in params)]
        for p in held:
            p.requires_grad_(False)
        try:
            yield
        finally:
            for p in held:
                p.requires_grad_(True)

    def numpy_geometry(self):
        """Current vertices (n, 3) float64 and poses R (V, 3, 3), t (V, 3) as numpy (no gradient)."""
        with torch.no_grad():
            X = self.verts()
            R, t = self.poses()
            return X.cpu().numpy().astype(np.float64), R.cpu().numpy(), t.cpu().numpy()


@dataclass
class _SubMesh:
    """The photometric vertex sample (M,) (skin, at most ``photo_vertices``), its indices in the sub-mesh of the
    triangles around it (``sample_t``), the sub-mesh model parts and triangles, and the image-frame intrinsics."""

    sample: np.ndarray
    sample_t: torch.Tensor
    sub: object
    sub_tri_t: torch.Tensor
    Kimg: np.ndarray
    Kimg_t: torch.Tensor

    _held: tuple | None = field(default=None, repr=False, compare=False)  # a held face's surface, see surface()

    def surface(self, prob: _FitProblem):
        """(vertices, vertex normals) of the sub-mesh at the current coefficients (exactly the full mesh's).

        While the face is held (its coefficients out of autograd, as in a registration or the pose curvature)
        the surface is a constant: it is computed once and given again until the coefficients change."""
        zs, ze = prob.zs, prob.ze
        if zs.requires_grad or ze.requires_grad:
            self._held = None
            return self._surface(zs, ze)
        # the same tensors (kept alive here, so never another's address) at the same in-place version
        held = self._held
        if held is None or held[0] is not zs or held[1] is not ze or held[2] != (zs._version, ze._version):
            self._held = held = (zs, ze, (zs._version, ze._version), *self._surface(zs, ze))
        return held[3], held[4]

    def _surface(self, zs: torch.Tensor, ze: torch.Tensor):
        Xs = self.sub.vertices(zs, ze)
        return Xs, vertex_normals(Xs, self.sub_tri_t)


def _sub_mesh(prob: _FitProblem) -> _SubMesh:
    """The photometric terms only need the sampled vertices and the triangles around them: that sub-mesh."""
    model, cfg, device = prob.model, prob.cfg, prob.device
    Kimg = prob.views.image_K()
    skin = model.skin_mask if model.skin_mask is not None else np.ones(model.n_vertices, dtype=bool)
    sample = np.nonzero(skin)[0]
    if len(sample) > cfg.photo_vertices:
        sample = sample[np.linspace(0, len(sample) - 1, cfg.photo_vertices).round().astype(np.int64)]
    touch = np.isin(model.triangles, sample).any(1)
    sub_ids = np.unique(model.triangles[touch])
    sub_ids = np.union1d(sub_ids, sample)
    sub_tri_t = torch.as_tensor(np.searchsorted(sub_ids, model.triangles[touch]), dtype=torch.long, device=device)
    sub = prob.ts.subset(sub_ids)
    sample_t = torch.as_tensor(np.searchsorted(sub_ids, sample), dtype=torch.long, device=device)
    return _SubMesh(sample, sample_t, sub, sub_tri_t, Kimg, prob.tt(Kimg))


def _landmark_stage(prob: _FitProblem) -> None:
    """Stage 1: landmarks + priors over the coefficients and poses.  With the sliding jaw: first without the
    sliding points, then ``contour_rounds`` fits, each after sliding them to the outline of the fit before."""
    def stage1():
        R, t = prob.poses()
        return prob.cfg.w_landmark * prob.landmark_term(R, t) + prob.prior(R, t)

    params = [prob.zs, prob.ze] + prob.pose_params
    if prob.jaw is None:
        prob.run_lbfgs(params, stage1, prob.cfg.landmark_iters, "landmarks")
        return
    off = torch.ones(68, dtype=prob.dtype, device=prob.device)
    off[torch.as_tensor(prob.jaw.points, device=prob.device)] = 0.0
    prob.wl_t = prob.wl_all_t * off  # the model's own jaw vertices are not where a detector puts the jaw
    prob.run_lbfgs(params, stage1, prob.cfg.landmark_iters, "landmarks without the sliding jaw", tick=False)
    rounds = max(prob.cfg.contour_rounds, 1)
    for rnd in range(rounds):
        prob.slide_jaw()
        prob.run_lbfgs(params, stage1, prob.cfg.landmark_iters, f"landmarks, jaw on the outline {rnd + 1}",
                       tick=rnd == rounds - 1)


@dataclass
class _PhotoResult:
    """Output of the photometric stage: SH lighting (V, 9, 3), albedo (M, 3), RMS residual (V,) and visible
    sample count (V,) of the last round."""

    sh: np.ndarray | None
    albedo: np.ndarray | None
    residual: np.ndarray
    visible: np.ndarray


def _albedo_mode(model: ShapeModel, cfg: FitConfig) -> str:
    """The albedo of the photometric term: ``texture``, ``per-vertex`` or ``constant`` (``auto`` resolved)."""
    mode = cfg.albedo
    if mode == "auto":
        mode = "texture" if model.mean_tex is not None else "per-vertex"
    if mode == "texture" and model.mean_tex is None:
        raise ReflectmmError("--albedo texture: the face model has no mean texture")
    return mode


def _round_blurs(cfg: FitConfig, rounds: int) -> list[float]:
    """Blur σ (px) of each round: ``photo_blur_px``, its last value repeated."""
    return list(cfg.photo_blur_px) + [cfg.photo_blur_px[-1] if cfg.photo_blur_px else 0.0] * rounds


def _photo_visibility(prob: _FitProblem, sm: _SubMesh, Wc: int, Hc: int):
    """Visibility (V, M) of the sample (ray cast, n·v > photo_min_cos, inside the image), its projections
    (V, M, 2) in image pixels and the vertex normals (n, 3), at the current geometry."""
    Xn, Rn, tn = prob.numpy_geometry()
    nrm = vertex_normals(Xn, prob.model.triangles, dtype=np.float64)
    centers = camera_centers(Rn, tn)
    vis = vertex_visibility(Xn, prob.model.triangles, nrm, centers, sample=sm.sample,
                            cos_cutoff=prob.cfg.photo_min_cos)
    uv, _ = project(Xn[sm.sample][None].repeat(prob.V, 0), sm.Kimg, Rn, tn)
    vis &= inside_image(uv, Wc, Hc)
    return vis, uv, nrm


def _photometric_stage(prob: _FitProblem, sm: _SubMesh) -> _PhotoResult:
    """Stage 2: ``photo_rounds`` rounds of landmarks + priors + the room-light term; each round refreshes the
    visibility, solves lighting (and albedo) in closed form, then runs L-BFGS with them as unknowns."""
    cfg, views, V, tt = prob.cfg, prob.views, prob.V, prob.tt
    Hc, Wc = views.images.shape[1:3]
    kernel = sh_kernel(prob.dtype, prob.device)
    kernel_np = kernel.cpu().numpy()
    mode = _albedo_mode(prob.model, cfg)
    sample = sm.sample
    base_albedo = prob.model.mean_tex[sample] if mode == "texture" else np.broadcast_to(DEFAULT_SKIN,
                                                                                       (len(sample), 3)).copy()
    blurs = _round_blurs(cfg, cfg.photo_rounds)
    out = _PhotoResult(None, None, np.full(V, np.nan), np.zeros(V, dtype=np.int64))
    for rnd in range(cfg.photo_rounds):
        prob.slide_jaw()  # the outline of the fit so far (no-op without the sliding jaw)
        images_t = _room_images(prob, blurs[rnd])
        vis, uv, nrm = _photo_visibility(prob, sm, Wc, Hc)
        vis[~prob.marked] = False  # views without landmarks: the room light does not register them (benchmarks)
        vis_t = tt(vis.astype(np.float64))
        # closed-form lighting/albedo at the current geometry
        obs = sample_images(images_t, tt(uv)).cpu().numpy().astype(np.float64)
        Y = sh_basis(nrm[sample], SH_ORDER)
        alb = base_albedo.copy() if out.albedo is None else out.albedo
        for _ in range(3):
            L = solve_lighting(Y, alb, obs, vis, kernel_np)
            if mode == "per-vertex":
                alb = solve_albedo(Y, L, obs, vis, kernel_np, base_albedo)
        seen = obs[vis]
        scale = float(np.median(seen)) if seen.size else 1.0
        scale = max(scale, 1e-3)
        sh_t = tt(L).requires_grad_(True)
        alb_t = tt(alb).requires_grad_(mode == "per-vertex")

        def photo(images):
            Xs, nv = sm.surface(prob)
            R, t = prob.poses()
            return photometric_loss(Xs, nv, sm.sample_t, vis_t, sm.Kimg_t, R, t, images, alb_t, sh_t, kernel,
                                    scale), R, t

        def stage2():
            (lp, _), R, t = photo(images_t)
            return cfg.w_landmark * prob.landmark_term(R, t) + cfg.w_photo * lp + prob.prior(R, t)

        params = [prob.zs, prob.ze] + prob.pose_params + [sh_t] + ([alb_t] if mode == "per-vertex" else [])
        prob.run_lbfgs(params, stage2, cfg.photo_iters, f"photometric round {rnd + 1}")
        out.sh = sh_t.detach().cpu().numpy()
        out.albedo = alb_t.detach().cpu().numpy()
        # residuals on the unblurred images at the final estimate of this round
        with torch.no_grad():
            r = photo(_room_images(prob, 0.0))[0][1].cpu().numpy()
        out.visible = vis.sum(1)
        for v in range(V):
            out.residual[v] = float(np.sqrt((r[v][vis[v]] ** 2).mean())) if vis[v].any() else np.nan
    return out


def _fit(model: ShapeModel, views: ViewSet, cfg: FitConfig, device: str) -> GeometryFit:
    """Stages of :func:`fit_geometry`: :func:`_landmark_stage`, then with images :func:`_photometric_stage` and
    with flash images :func:`_flash_stage`, then :func:`_fit_result`."""
    t_start = time.perf_counter()
    prob = _FitProblem(model, views, cfg, device)
    _landmark_stage(prob)
    place_unmarked_by_rig(prob)  # after each stage that moved the head without them
    photo = _PhotoResult(None, None, np.full(prob.V, np.nan), np.zeros(prob.V, dtype=np.int64))
    flash_res = flash_gain = None
    sm = _sub_mesh(prob) if (prob.n_photo or prob.n_flash) else None
    if prob.n_photo:
        photo = _photometric_stage(prob, sm)
        place_unmarked_by_rig(prob)
    if prob.n_flash:  # point lights at the flashes (docs/fit-geometry.md)
        flash_res, flash_gain = _flash_stage(prob, sm)
        place_unmarked_by_rig(prob)
        if not prob.marked.all() and cfg.register_blur_px:
            reg = _register_unmarked(prob, sm)
            if reg is not None:
                flash_res[~prob.marked] = reg[~prob.marked]
                if cfg.joint_rounds > 0:
                    joint = _joint_rounds(prob, sm)
                    if joint is not None:
                        flash_res, flash_gain = joint
    for _ in prob.bar:  # close the progress bar
        pass
    return _fit_result(prob, photo, sm, flash_res, flash_gain, t_start)


def _landmark_rmse(prob: _FitProblem) -> tuple[np.ndarray, np.ndarray]:
    """(V,) RMS landmark error per view (px; NaN for a view without a landmark the fit weighs) and the (V, 68, 2)
    projections, at the current unknowns; a point on the outline (``jaw_contour``) counts its distance across it,
    as the fit measures it."""
    views = prob.views
    with torch.no_grad():
        R, t = prob.poses()
        _, uv = prob.lm_loss(prob.verts(), R, t)
    uv = uv.cpu().numpy().astype(np.float64)
    err = np.linalg.norm(uv - views.landmarks, axis=-1)
    if prob.jaw is not None:
        across = (prob.lm_normals ** 2).sum(-1) > 0
        err[across] = np.abs(((uv - views.landmarks) * prob.lm_normals).sum(-1))[across]
    used = prob.valid & prob.used
    rmse = np.array([math.sqrt(np.mean(err[v][used[v]] ** 2)) if used[v].any() else math.nan
                     for v in range(prob.V)])
    return rmse, uv


def _fit_result(prob: _FitProblem, photo: _PhotoResult, sm: _SubMesh | None, flash_res, flash_gain,
                t_start: float) -> GeometryFit:
    """Gather the :class:`GeometryFit` at the final unknowns (landmark RMSE per view, coefficients, vertices)."""
    model, cfg, views, V = prob.model, prob.cfg, prob.views, prob.V
    which = {"all": np.arange(V), "unmarked": np.nonzero(~prob.marked)[0]}.get(cfg.uncertainty, [])
    with torch.no_grad():
        dist = np.linalg.norm(camera_centers(*prob.poses()).cpu().numpy(), axis=-1)
    c_sig, r_sig = pose_sigmas(pose_curvature(prob, which), dist)
    rmse, uv = _landmark_rmse(prob)
    with torch.no_grad():
        R, t = prob.poses()
    zs_np = prob.zs.detach().cpu().numpy().astype(np.float64)
    ze_np = prob.ze.detach().cpu().numpy().astype(np.float64)
    shape_coeffs = zs_np * model.shape_sigma
    exp_coeffs = ze_np * model.exp_sigma[:len(ze_np)] if cfg.fit_expression else np.zeros(model.n_exp)
    return GeometryFit(shape_coeffs=shape_coeffs, exp_coeffs=exp_coeffs,
                       vertices=model.vertices(shape_coeffs, exp_coeffs),
                       R=R.cpu().numpy().astype(np.float64), t=t.cpu().numpy().astype(np.float64),
                       K=views.K.copy(), landmark_rmse_px=rmse, landmark_px=uv, photo_residual=photo.residual,
                       visible_count=photo.visible, sh=photo.sh, albedo=photo.albedo,
                       photo_sample=None if sm is None else sm.sample, history=prob.history,
                       flash_residual=flash_res, flash_gain=flash_gain,
                       seconds=time.perf_counter() - t_start,
                       evidence=view_evidence(prob.marked, photo.visible if prob.n_photo else None, None
                                              if flash_res is None else  # unregistered: the rig placed it
                                              np.where(~prob.marked & ~prob.registered, np.nan, flash_res),
                                              room=prob.room_refined),
                       center_sigma_mm=c_sig, rotation_sigma_deg=r_sig, rig_shift_mm=rig_shift(prob),
                       registered=prob.registered.copy(), room_refined=prob.room_refined.copy(),
                       joined=prob.joined.copy())


class _FlashPairs:
    """The (view, flash) pairs of the flash term and the fitted relative flash gains.

    ``usable`` (U,): flashes with a fitted camera or a rig position; pairs ``pv``/``pf`` (P = V'·U,) view and flash
    of each pair over the views ``seen_by`` (V,) bool (default all); ``log_gain`` (F,) the torch unknown (a leaf
    that needs gradients only with ``flash_gains``).
    """

    def __init__(self, prob: _FitProblem, usable: np.ndarray, seen_by: np.ndarray | None = None):
        views, device, tt = prob.views, prob.device, prob.tt
        self.prob, self.usable = prob, usable
        fv = views.flash_view
        self.F = views.flash_images.shape[1]
        cams = np.arange(prob.V) if seen_by is None else np.nonzero(seen_by)[0]  # the views whose images enter
        self.pv = pv = np.repeat(cams, len(usable))
        self.pf = pf = np.tile(usable, len(cams))
        self.pv_t = torch.as_tensor(pv, dtype=torch.long, device=device)
        self.fv_t = torch.as_tensor(np.maximum(fv, 0), dtype=torch.long, device=device)
        self.rigpos_t = tt(np.nan_to_num(views.flash_rig_pos))
        self.from_view_t = torch.as_tensor(fv >= 0, device=device)[:, None]
        self.lint_t = tt(views.flash_intensity[pf])
        self.pf_t = torch.as_tensor(pf, dtype=torch.long, device=device)
        self.use_t = torch.as_tensor(usable, dtype=torch.long, device=device)
        self.log_gain = torch.zeros(self.F, dtype=prob.dtype, device=device, requires_grad=prob.cfg.flash_gains)

    def images(self) -> tuple[np.ndarray, np.ndarray | None]:
        """The pairs' flash images (P, h, w, 3) float32 and saturation masks (P, h, w) bool (None without them)."""
        views = self.prob.views
        raw = np.asarray(views.flash_images[self.pv, self.pf], dtype=np.float32)
        sat = None if views.flash_saturated is None else np.asarray(views.flash_saturated[self.pv, self.pf],
                                                                      dtype=bool)
        return raw, sat

    def log_gains(self) -> torch.Tensor:
        """(F,) log relative flash gains, geometric mean 1 over the flashes in the term."""
        return self.log_gain - self.log_gain[self.use_t].mean()

    def intensities(self) -> torch.Tensor:
        """(P,) flash intensity of each pair: the table's, times the fitted relative gain."""
        return self.lint_t * torch.exp(self.log_gains()[self.pf_t])

    def positions(self, R, t) -> torch.Tensor:
        """(F, 3) flash positions in model space: the fitted camera centre, or the rig position under the head."""
        c = camera_centers(R, t)[self.fv_t]
        if self.prob.use_rig:
            Rh, th = self.prob.head()
            return torch.where(self.from_view_t, c, self.rigpos_t @ Rh.T + th)
        return c

    def gains(self) -> np.ndarray:
        """(F,) fitted relative gains (NaN for flashes left out of the term)."""
        with torch.no_grad():
            g = torch.exp(self.log_gains()).cpu().numpy().astype(np.float64)
        gain = np.full(self.F, np.nan)
        gain[self.usable] = g[self.usable]
        return gain


def _usable_flashes(prob: _FitProblem, on_unmarked_too: bool = False) -> np.ndarray:
    """Indices of the flashes with a fitted camera or (with the rig constraint) a rig position, those on cameras
    without landmarks only with ``on_unmarked_too``; warns otherwise."""
    views = prob.views
    F = views.flash_images.shape[1]
    rig_ok = np.isfinite(views.flash_rig_pos).all(-1) & prob.use_rig
    fv = views.flash_view
    on_unmarked = (fv >= 0) & ~prob.marked[np.maximum(fv, 0)] & (not on_unmarked_too)
    if on_unmarked.any():
        log.info("fit-geometry: %d flash(es) sit on cameras without landmarks: left out of the flash term (their "
                 "places are the rig's guess)", int(on_unmarked.sum()))
    usable = np.nonzero(((fv >= 0) | rig_ok) & ~on_unmarked)[0]
    if len(usable) == 0:
        log.warning("fit-geometry: no flash has a fitted camera or a rig position: the flash term is skipped")
    elif len(usable) < F - int(on_unmarked.sum()):
        log.warning("fit-geometry: %d flash(es) have no fitted camera and no rig position: left out of the flash "
                    "term", F - int(on_unmarked.sum()) - len(usable))
    return usable


def _flash_weights(prob: _FitProblem, sm: _SubMesh, fp: _FlashPairs, sat: np.ndarray | None) -> tuple:
    """(P, M) bool weights of the flash term at the current geometry — seen by the pair's camera (n·v >
    photo_min_cos), lit by its flash (n·l > flash_min_cos), inside the image, outside the specular highlight
    (normal within ``flash_highlight_deg`` of the half vector) and not saturated — and the projections (V, M, 2)."""
    cfg, model, V, sample = prob.cfg, prob.model, prob.V, sm.sample
    h, w = prob.views.flash_images.shape[2:4]
    pv, pf = fp.pv, fp.pf
    with torch.no_grad():
        X = prob.verts()
        R, t = prob.poses()
        lpos = fp.positions(R, t)
        Xn, Rn, tn = X.cpu().numpy().astype(np.float64), R.cpu().numpy(), t.cpu().numpy()
        lpos_np = lpos.cpu().numpy().astype(np.float64)
    nrm = vertex_normals(Xn, model.triangles, dtype=np.float64)
    centers = camera_centers(Rn, tn)
    # one ray scene for the cameras and the flashes; a flash on a camera shares that camera's rays
    vis = vertex_visibility(Xn, model.triangles, nrm, np.concatenate([centers, lpos_np]), sample=sample,
                            cos_cutoff=np.r_[np.full(len(centers), cfg.photo_min_cos),
                                             np.full(len(lpos_np), cfg.flash_min_cos)])
    cam_vis, fl_vis = vis[:len(centers)], vis[len(centers):]
    uv, _ = project(Xn[sample][None].repeat(V, 0), sm.Kimg, Rn, tn)
    inside = inside_image(uv, w, h)
    p, n = Xn[sample], nrm[sample]
    vdir = centers[pv][:, None] - p[None]
    ldir = lpos_np[pf][:, None] - p[None]
    hvec = vdir / np.linalg.norm(vdir, axis=-1, keepdims=True) + ldir / np.linalg.norm(ldir, axis=-1,
                                                                                      keepdims=True)
    hvec /= np.linalg.norm(hvec, axis=-1, keepdims=True)
    highlight = (hvec * n[None]).sum(-1) > math.cos(math.radians(cfg.flash_highlight_deg))
    weight = cam_vis[pv] & fl_vis[pf] & inside[pv] & ~highlight
    if sat is not None:
        px = np.clip(np.rint(uv[pv]).astype(np.int64), 0, [w - 1, h - 1])
        weight &= ~sat[np.arange(len(pv))[:, None], px[..., 1], px[..., 0]]
    return weight, uv


def _flash_objective(prob: _FitProblem, sm: _SubMesh, fp: "_FlashPairs", raw: np.ndarray, blur: float,
                     sat: np.ndarray | None, view_weight: np.ndarray | None = None):
    """The flash term of one round at the current geometry: (loss(images, residual) closure, blurred images
    (P, h, w, 3) tensor, the (P, M) bool sample mask); weights, visibility and the residual scale fixed at the
    round's start.  ``view_weight`` (V,): each view's images weighted by it (default 1 for all)."""
    images_t = torch.as_tensor(_blur(raw, blur), device=prob.device)  # (P, h, w, 3) channels last
    weight, uv = _flash_weights(prob, sm, fp, sat)
    sp, sm_ = np.nonzero(weight)
    seen = gather_bilinear(images_t, torch.as_tensor(sp, device=prob.device),
                           torch.as_tensor(uv[fp.pv[sp], sm_], device=prob.device)).cpu().numpy()
    scale = max(float(np.median(seen)) if seen.size else 1.0, 1e-3)
    w = weight.astype(np.float64)
    if view_weight is not None:
        w *= np.asarray(view_weight, dtype=np.float64)[fp.pv][:, None]
    weight_t = prob.tt(w)
    index = torch.nonzero(weight_t > 0, as_tuple=True)  # fixed for the round

    def flash(images, residual=True):
        Xs, nv = sm.surface(prob)
        R, t = prob.poses()
        return flash_loss(Xs, nv, sm.sample_t, weight_t, sm.Kimg_t, R, t, images, fp.pv_t,
                          fp.positions(R, t)[fp.pf_t], fp.intensities(), scale, residual=residual,
                          index=index), R, t

    return flash, images_t, weight


def _register_unmarked(prob: _FitProblem, sm: _SubMesh, again: bool = False) -> np.ndarray | None:
    """Registration of the views without landmarks by the flash term, after the joint stages, coarse to fine
    (``register_blur_px``): only their poses move; the face, the head and the views with landmarks are held (the
    flashes on cameras without landmarks are left out of every flash round, :func:`_usable_flashes`).  A view
    whose flash residual does not fall, or that moves more than 3 σ from the rig, goes back where the rig puts
    it (``prob.registered`` False).  The views kept are then refined with the room-light photo-consistency beside
    the flash term (``register_room_blur_px``, :func:`_refine_by_room`).  Returns the (V,) RMS flash residual at
    the final poses (None: not run).  ``again``: a registration after a joint round, whose rejected views stay
    where that round left them."""
    cfg, views = prob.cfg, prob.views
    um = ~prob.marked
    usable = _usable_flashes(prob, on_unmarked_too=True)  # a camera's own flash lights the others: its place
    if len(usable) == 0:
        log.warning("fit-geometry: no flash on a camera with landmarks or on a stand: the views without landmarks "
                    "are not registered by the flash images")
        return None
    fp = _FlashPairs(prob, usable)  # every view: the per-vertex albedo comes mostly from the views with landmarks
    raw, sat = fp.images()
    before = _view_flash_rms(prob, sm, fp, raw, sat)
    saved = prob.dw.detach().clone(), prob.dtr.detach().clone()
    # after a joint round the views start next to their places: the finest blur alone
    blurs = cfg.register_blur_px[-1:] if again else cfg.register_blur_px
    _registration_rounds(prob, sm, fp, raw, sat, um, blurs, room=False)
    after = _view_flash_rms(prob, sm, fp, raw, sat)
    with np.errstate(invalid="ignore"):
        bad = um & ~((after <= before) & (rig_shift(prob) <= 3.0 * prob.unmarked_sigma))
    if bad.any():
        (log.info if again else log.warning)(
            "fit-geometry: registration of view(s) %s by the flash images rejected (residual not lower, or moved "
            "more than 3 sigma from the rig): kept %s", ", ".join(n for n, b in zip(views.names, bad) if b),
            "where the joint round left them" if again else "where the rig puts them")
        _restore_poses(prob, saved, bad)
    prob.registered = um & ~bad
    res = np.where(bad, before, after)
    if cfg.register_room_blur_px and cfg.w_room > 0 and prob.registered.any():
        res = _refine_by_room(prob, sm, fp, raw, sat, res)
    return res


def _joint_rounds(prob: _FitProblem, sm: _SubMesh) -> tuple[np.ndarray, np.ndarray] | None:
    """Rounds of the flash term over every placed view (``joint_rounds``, after :func:`_register_unmarked`).

    The views without landmarks that their flash images registered to within ``joint_gate_mm`` of the rig are held
    to the head at their registered places (:func:`_held_to_head`): the head, the face and the views with landmarks
    move, and those views follow the head rigidly, their images (weighted by ``joint_unmarked_weight``) and
    flashes in the term beside the others' (:func:`joint_flash_term`).  A head turned in the rig (a pitch that
    near-frontal landmarks leave loose) then moves every view's image of the face, not only the landmarked ones'.
    With ``joint_register`` the views without landmarks are registered again after each round from where the head
    took them; otherwise they stay held.  The rounds are undone when they
    raise the landmark RMS of the views with landmarks more than ``joint_max_landmark_rise``.  Returns the (V,) RMS
    flash residual per view and the (F,) flash gains at the end, or None when no round ran or the rounds were
    undone (the fit is then the one without them)."""
    cfg = prob.cfg
    um = ~prob.marked
    gains = None
    lm_before = float(np.nanmedian(_landmark_rmse(prob)[0]))
    saved = _snapshot(prob)
    for rnd in range(cfg.joint_rounds):
        with np.errstate(invalid="ignore"):
            joined = um & prob.registered & (rig_shift(prob) <= cfg.joint_gate_mm)
        if not joined.any():
            log.info("fit-geometry: no registered view without landmarks within %.0f mm of the rig: %s",
                     cfg.joint_gate_mm, "no joint round" if rnd == 0 else f"joint rounds stop after {rnd}")
            break
        prob.joined |= joined
        with _held_to_head(prob, um):
            fp, flash, images_t = joint_flash_term(prob, sm, prob.marked | joined)

            def joint():
                (lf, _, _), R, t = flash(images_t, residual=False)
                return cfg.w_landmark * prob.landmark_term(R, t) + cfg.w_flash * lf + prob.prior(R, t)

            extra = [fp.log_gain] if cfg.flash_gains else []
            prob.run_lbfgs([prob.zs, prob.ze] + prob.pose_params + extra, joint, cfg.flash_iters,
                           f"joint round {rnd + 1}", tick=False)
        gains = fp.gains()
        if cfg.joint_register:
            before = prob.registered.copy()
            _register_unmarked(prob, sm, again=True)
            # a view registered before whose new registration was undone stays where the head took it: registered
            prob.registered |= before
    if gains is None:
        return None
    lm_after = float(np.nanmedian(_landmark_rmse(prob)[0]))
    if lm_after > cfg.joint_max_landmark_rise * lm_before:
        log.warning("fit-geometry: joint rounds undone: they raised the landmark RMS of the views with landmarks from "
                    "%.2f to %.2f px (more than %.2gx): a view without landmarks pulled the face", lm_before, lm_after,
                    cfg.joint_max_landmark_rise)
        _restore(prob, saved)
        return None
    # the residuals at the end, each view by its own images (the views without landmarks with every flash)
    fp_m = _FlashPairs(prob, _usable_flashes(prob), seen_by=prob.marked)
    res = _view_flash_rms(prob, sm, fp_m, *fp_m.images())
    fp_u = _FlashPairs(prob, _usable_flashes(prob, on_unmarked_too=True))
    res_u = _view_flash_rms(prob, sm, fp_u, *fp_u.images())
    res[um] = res_u[um]
    return res, gains


def joint_flash_term(prob: _FitProblem, sm: _SubMesh, placed: np.ndarray):
    """The flash term of a joint round over the views ``placed`` (V,) bool: their images, lit by the flashes on
    them and on stands, the images of the views without landmarks weighted by ``joint_unmarked_weight``, blurred by
    ``joint_blur_px``; sample weights and scale fixed at the current geometry.  Returns (the flash pairs, the
    loss closure of :func:`_flash_objective`, the blurred images).  Called where the rounds hold the views without
    landmarks to the head (:class:`_held_to_head`), as they are evaluated."""
    cfg, fv = prob.cfg, prob.views.flash_view
    usable = np.array([f for f in _usable_flashes(prob, on_unmarked_too=True) if fv[f] < 0 or placed[fv[f]]],
                      dtype=np.int64)
    fp = _FlashPairs(prob, usable, seen_by=placed)
    raw, sat = fp.images()
    flash, images_t, _ = _flash_objective(prob, sm, fp, raw, cfg.joint_blur_px, sat,
                                          view_weight=np.where(prob.marked, 1.0, cfg.joint_unmarked_weight))
    return fp, flash, images_t


def write_poses(prob: _FitProblem, R: torch.Tensor, t: torch.Tensor, which) -> None:
    """Set the pose unknowns of the views ``which`` (V,) bool so that :meth:`_FitProblem.poses` gives (R, t) for
    them (without a ``pose_fn``)."""
    w = torch.as_tensor(which, device=prob.device)
    with torch.no_grad():
        prob.dw[w] = (matrix_to_axis_angle(R @ prob.R0_t.transpose(-1, -2)) / prob.r_unit)[w]
        prob.dtr[w] = ((t - prob.t0_t) / prob.tv_unit)[w]


def place_unmarked_by_rig(prob: _FitProblem) -> None:
    """Put each view without landmarks where the rig puts it under the current head: centre ``Rh c_rig + th``,
    orientation ``R_rig Rhᵀ`` (the minimum of its rig prior).

    The views start where the head of the initial landmark poses put them (:func:`.init.place_by_rig`).  The
    landmark and flash stages then move the head, often by tens of millimetres, while nothing but a wide prior
    (``unmarked_sigma_mm``) draws those views along, too weakly for the optimiser to take them there: on a
    benchmark world they were left 93–158 mm from their rig places.  :func:`_fit` calls this after the landmark,
    photometric and flash stages: the registration starts from here, a view whose registration is rejected
    comes back here, and without flash images the fit leaves them here."""
    um = ~prob.marked
    if not um.any() or not prob.use_rig:
        return
    with torch.no_grad():
        R, t = pose_under_head(prob.rigR_t, prob.rig_t, *prob.head())
    write_poses(prob, R, t, um)


def _snapshot(prob: _FitProblem) -> dict:
    """The unknowns and the views' placement flags, to undo the joint rounds."""
    tensors = {k: getattr(prob, k).detach().clone() for k in prob.UNKNOWNS}
    flags = {k: getattr(prob, k).copy() for k in ("registered", "room_refined", "joined")}
    return {"tensors": tensors, "flags": flags}


def _restore(prob: _FitProblem, saved: dict) -> None:
    with torch.no_grad():
        for k, v in saved["tensors"].items():
            getattr(prob, k).copy_(v)
    for k, v in saved["flags"].items():
        setattr(prob, k, v.copy())


def pose_under_head(R_rig: torch.Tensor, c_rig: torch.Tensor, Rh: torch.Tensor, th: torch.Tensor):
    """Model → camera poses (R (..., 3, 3), t (..., 3)) of cameras given in the rig frame — orientations ``R_rig``
    (rig → camera) and centres ``c_rig`` (..., 3) — with the head at (Rh, th) (rig → model: ``x = Rh x_rig + th``)."""
    R = R_rig @ Rh.transpose(-1, -2)
    c = c_rig @ Rh.transpose(-1, -2) + th
    return R, -(R @ c[..., None])[..., 0]


class _held_to_head:
    """Context: the views ``which`` (V,) follow the head rigidly at their current places in the rig frame (through
    ``prob.pose_fn``); on exit their poses at the final head are written back into their unknowns."""

    def __init__(self, prob: _FitProblem, which: np.ndarray):
        self.prob, self.which = prob, torch.as_tensor(which, device=prob.device)

    def __enter__(self):
        prob = self.prob
        with torch.no_grad():
            Rh, th = prob.head()
            R, t = prob.poses()
            c = camera_centers(R, t)
            self.R_rig = R @ Rh                # rig frame → camera
            self.c_rig = (c - th) @ Rh         # the centres in the rig frame

        def follow(R, t):
            Rf, tf = pose_under_head(self.R_rig, self.c_rig, *prob.head())
            return (torch.where(self.which[:, None, None], Rf, R), torch.where(self.which[:, None], tf, t))

        prob.pose_fn = follow
        return self

    def __exit__(self, *exc):
        prob = self.prob
        with torch.no_grad():
            R, t = prob.poses()
        prob.pose_fn = None
        write_poses(prob, R, t, self.which)
        return False


def _restore_poses(prob: _FitProblem, saved, which: np.ndarray) -> None:
    """Put the poses of the views ``which`` (V,) back to ``saved`` (dw, dtr)."""
    b = torch.as_tensor(which, device=prob.device)
    with torch.no_grad():
        prob.dw[b] = saved[0][b]
        prob.dtr[b] = saved[1][b]


def _registration_rounds(prob: _FitProblem, sm: _SubMesh, fp: "_FlashPairs", raw: np.ndarray,
                         sat: np.ndarray | None, which: np.ndarray, blurs, room: bool) -> None:
    """L-BFGS rounds, one per blur, over the poses of the views ``which`` (V,) alone: the flash term, with
    ``room`` also the room-light photo-consistency of those views, and the priors."""
    cfg = prob.cfg
    mask = prob.tt(which.astype(np.float64))[:, None]
    hooks = [p.register_hook(lambda g: g * mask) for p in (prob.dw, prob.dtr)]
    try:
        for rnd, blur in enumerate(blurs):
            flash, images_t, _ = _flash_objective(prob, sm, fp, raw, blur, sat)
            consistency = _room_consistency(prob, sm, blur, which)[0] if room else None

            def reg():
                (lf, _, _), R, t = flash(images_t, residual=False)
                loss = cfg.w_flash * lf + prob.prior(R, t)
                return loss if consistency is None else loss + cfg.w_room * consistency()[0]

            prob.run_lbfgs([prob.dw, prob.dtr], reg, cfg.register_iters,
                           f"registration round {rnd + 1}" + (" with the room light" if room else ""), tick=False)
    finally:
        for h in hooks:
            h.remove()


def _refine_by_room(prob: _FitProblem, sm: _SubMesh, fp: "_FlashPairs", raw: np.ndarray, sat: np.ndarray | None,
                    flash_res: np.ndarray) -> np.ndarray:
    """The views that their flash images registered, refined with the room-light photo-consistency beside the flash
    term (``register_room_blur_px``).  A view keeps the refinement when neither its flash nor its room residual
    rose and it stays within 3 σ of the rig; otherwise it goes back to its flash registration
    (``prob.room_refined`` False).  Returns the (V,) flash residuals."""
    cfg, views = prob.cfg, prob.views
    which = prob.registered.copy()
    room_before = _view_room_rms(prob, sm, which)
    saved = prob.dw.detach().clone(), prob.dtr.detach().clone()
    _registration_rounds(prob, sm, fp, raw, sat, which, cfg.register_room_blur_px, room=True)
    flash_after = _view_flash_rms(prob, sm, fp, raw, sat)
    room_after = _view_room_rms(prob, sm, which)
    with np.errstate(invalid="ignore"):
        ok = which & (flash_after <= flash_res) & (room_after <= room_before) \
            & (rig_shift(prob) <= 3.0 * prob.unmarked_sigma)
    undone = which & ~ok
    if undone.any():
        log.info("fit-geometry: the room-light refinement of view(s) %s undone (residuals not lower, or moved more "
                 "than 3 sigma from the rig): their flash registration is kept",
                 ", ".join(n for n, b in zip(views.names, undone) if b))
        _restore_poses(prob, saved, undone)
    prob.room_refined = ok
    return np.where(ok, flash_after, flash_res)


def _room_consistency(prob: _FitProblem, sm: _SubMesh, blur: float, which: np.ndarray, eps: float = 0.02):
    """Multi-view photo-consistency of the room-light images for the views ``which`` (V,): (loss closure returning
    (loss, residual (V, M, 3)), weights (V, M) bool).

    Under the room light a Lambertian point has the same radiance from every view, so the colour that the views
    with landmarks see at a sample vertex (their mean, at the current face and poses) is what another view must see
    there: ``r = g_v · I_v(π_v(X_m)) − ref_m``, relative to the median reference colour, Charbonnier, over the
    samples that view sees (ray cast, n·v > photo_min_cos, inside its image) and a view with landmarks sees too.
    No lighting model and no albedo.  ``g_v`` (one gain per channel: exposure, white balance) is solved at the
    call and then held; a gain free inside the loss lets a camera zoom out until the face is a few pixels of one
    colour (docs/benchmarks.md).  The reference, the visibility and the gains are fixed at the call."""
    V = prob.V
    Hc, Wc = prob.views.images.shape[1:3]
    images_t = _room_images(prob, blur)
    vis, uv, _ = _photo_visibility(prob, sm, Wc, Hc)
    with torch.no_grad():
        obs = sample_images(images_t, prob.tt(uv)).cpu().numpy().astype(np.float64)   # (V, M, 3)
    seen = vis & prob.marked[:, None]
    count = seen.sum(0)
    ref = (obs * seen[..., None]).sum(0) / np.maximum(count, 1)[:, None]             # (M, 3)
    weight = vis & np.asarray(which, dtype=bool)[:, None] & (count > 0)[None]
    wo = weight[..., None] * obs
    gain = (wo * ref[None]).sum(1) / np.maximum((wo * obs).sum(1), 1e-12)            # (V, 3)
    scale = max(float(np.median(ref[count > 0])) if (count > 0).any() else 1.0, 1e-3)
    w_t, ref_t, gain_t = prob.tt(weight.astype(np.float64)), prob.tt(ref), prob.tt(gain)

    def consistency():
        Xs, _ = sm.surface(prob)
        R, t = prob.poses()
        uvp, _ = project(Xs[sm.sample_t][None].expand(V, -1, -1), sm.Kimg_t, R, t)
        r = gain_t[:, None] * sample_images(images_t, uvp) - ref_t
        return (charbonnier(r / scale, eps).sum(-1) * w_t).sum() / w_t.sum().clamp_min(1.0), r

    return consistency, weight


def _view_room_rms(prob: _FitProblem, sm: _SubMesh, which: np.ndarray) -> np.ndarray:
    """(V,) RMS room-light consistency residual of the views ``which`` at the current poses (unblurred, their own
    visibility and gains; NaN elsewhere or without a shared sample)."""
    consistency, weight = _room_consistency(prob, sm, 0.0, which)
    with torch.no_grad():
        r = consistency()[1].cpu().numpy()
    return _rms_per_view(r, weight, np.arange(prob.V), prob.V)


def _view_flash_rms(prob: _FitProblem, sm: _SubMesh, fp: "_FlashPairs", raw: np.ndarray,
                    sat: np.ndarray | None) -> np.ndarray:
    """(V,) RMS flash residual per view at the current geometry (unblurred, its own visibility; NaN: no sample)."""
    flash, images_t, weight = _flash_objective(prob, sm, fp, raw, 0.0, sat)
    with torch.no_grad():
        r = flash(images_t)[0][1].cpu().numpy()
    return _rms_per_view(r, weight, fp.pv, prob.V)


def _rms_per_view(r: np.ndarray, weight: np.ndarray, pv: np.ndarray, V: int) -> np.ndarray:
    """(V,) RMS of the residuals ``r`` (P, S) over each view's weighted samples (``weight`` (P, S), pairs of view
    ``pv`` (P,)); NaN for a view without one."""
    out = np.full(V, np.nan)
    for v in range(V):
        m = weight[pv == v]
        out[v] = float(np.sqrt((r[pv == v][m] ** 2).mean())) if m.any() else np.nan
    return out


def _flash_stage(prob: _FitProblem, sm: _SubMesh) -> tuple[np.ndarray, np.ndarray]:
    """Stage 3: ``flash_rounds`` L-BFGS rounds of landmarks + priors + the point-light term
    (:func:`.photometric.flash_loss`), visibility, shadows and highlight masks refreshed each round.
    Returns the (V,) RMS residual per view of the last round and the (F,) relative flash gains."""
    cfg, views, V, device = prob.cfg, prob.views, prob.V, prob.device
    fimg = views.flash_images
    usable = _usable_flashes(prob)
    if len(usable) == 0:
        return np.full(V, np.nan), np.full(fimg.shape[1], np.nan)
    # the views without landmarks are out of the term (a view far from its place would pull the face and the other
    # views): they follow the rig under the head; :func:`_register_unmarked` places them afterwards
    held = ~prob.marked
    fp = _FlashPairs(prob, usable, seen_by=~held)
    blurs = _round_blurs(cfg, cfg.flash_rounds)
    raw, sat = fp.images()  # (P, h, w, 3), (P, h, w)
    res = np.full(V, np.nan)
    for rnd in range(cfg.flash_rounds):
        prob.slide_jaw()  # the outline of the fit so far (no-op without the sliding jaw)
        flash, images_t, weight = _flash_objective(prob, sm, fp, raw, blurs[rnd], sat)

        def stage3():
            (lf, _, _), R, t = flash(images_t, residual=False)
            return cfg.w_landmark * prob.landmark_term(R, t) + cfg.w_flash * lf + prob.prior(R, t)

        gains = [fp.log_gain] if cfg.flash_gains else []
        prob.run_lbfgs([prob.zs, prob.ze] + prob.pose_params + gains, stage3, cfg.flash_iters,
                       f"flash round {rnd + 1}")
        with torch.no_grad():
            r = flash(torch.as_tensor(raw, device=device))[0][1].cpu().numpy()
        res = _rms_per_view(r, weight, fp.pv, V)
    return res, fp.gains()
