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
"""

from __future__ import annotations

import logging
import math
import time
from dataclasses import dataclass, field

import numpy as np
import torch

from reflectmm_cli.errors import ReflectmmError
from reflectmm_cli.geometry.camera import axis_angle_to_matrix, camera_centers, project
from reflectmm_cli.geometry_fit.init import rigid_align
from reflectmm_cli.geometry_fit.landmarks import landmark_weights
from reflectmm_cli.geometry.face_model import vertex_normals
from reflectmm_cli.geometry_fit.model import ShapeModel
from reflectmm_cli.geometry_fit.photometric import (
    SH_ORDER,
    flash_loss,
    gather_bilinear,
    inside_image,
    photometric_loss,
    sample_images,
    sh_kernel,
    solve_albedo,
    solve_lighting,
)
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
    dtype: str = "float64"
    threads: int = 1                # torch intra-op threads during the fit (the tensors are small: one thread
                                    # is several times faster than two on a loaded 2-core machine)

    def as_dict(self) -> dict:
        d = dict(self.__dict__)
        d["photo_blur_px"] = list(self.photo_blur_px)
        return d


@dataclass
class ViewSet:
    """The views of one identity: names, intrinsics, initial poses, landmarks and (optional) images.

    K, R0: (V, 3, 3); t0: (V, 3); landmarks: (V, 68, 2) pixels, NaN where missing;
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

    @property
    def cam_centers(self) -> np.ndarray:
        return camera_centers(self.R, self.t)


def _blur(images: np.ndarray, sigma: float) -> np.ndarray:
    if sigma <= 0:
        return images
    import cv2

    return np.stack([cv2.GaussianBlur(im, (0, 0), sigma) for im in images])


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
    if cfg.albedo not in ("auto", "texture", "per-vertex", "constant"):
        raise ReflectmmError(f"albedo must be auto, texture, per-vertex or constant, got {cfg.albedo!r}")
    with torch_threads(cfg.threads):
        return _fit(model, views, cfg, device)


def _fit(model: ShapeModel, views: ViewSet, cfg: FitConfig, device: str) -> GeometryFit:
    t_start = time.perf_counter()
    dtype = {"float64": torch.float64, "float32": torch.float32}[cfg.dtype]
    V = len(views.names)

    def tt(a):
        return torch.as_tensor(np.ascontiguousarray(a), dtype=dtype, device=device)

    ts = model.torch_parts(dtype, device)
    lm_obs = views.landmarks
    valid = np.isfinite(lm_obs).all(-1)
    for v in range(V):
        if valid[v].sum() < 6:
            raise ReflectmmError(f"view {views.names[v]}: only {int(valid[v].sum())} valid landmarks "
                                 "(at least 6 needed)")
    wl = landmark_weights(cfg.group_weights)[None, :] * valid
    wl_t = tt(wl)
    wsum = float(wl.sum())
    obs_t = tt(np.where(valid[..., None], lm_obs, 0.0))
    K_t, R0_t, t0_t = tt(views.K), tt(views.R0), tt(views.t0)

    # parameter scaling: one unit of τ moves a point ≈ 10 px sideways, one unit of δ is 0.1 rad
    depth = np.abs(views.t0[:, 2]).mean()
    f = float(views.K[:, 0, 0].mean())
    t_unit = 10.0 * depth / f
    # depth moves the landmarks only through the scale of the face: ≈ f·r·Δz/Z² for a face of radius r
    lm0 = model.mean[model.landmarks]
    radius = float(np.sqrt(((lm0 - lm0.mean(0)) ** 2).sum(-1).mean()))
    tv_unit = torch.tensor([t_unit, t_unit, t_unit * depth / max(radius, 1e-6)], dtype=dtype, device=device)
    r_unit = 0.1

    zs = torch.zeros(model.n_shape, dtype=dtype, device=device, requires_grad=True)
    ze = torch.zeros(model.n_exp if cfg.fit_expression else 0, dtype=dtype, device=device, requires_grad=True)
    dw = torch.zeros(V, 3, dtype=dtype, device=device, requires_grad=True)
    dtr = torch.zeros(V, 3, dtype=dtype, device=device, requires_grad=True)
    # rigid rig → model transform (the head pose in the rig frame), for the soft rig constraint
    use_rig = views.rig_centers is not None and cfg.rig_sigma_mm > 0 and V >= 3
    if use_rig:
        Rh0, th0, _ = rigid_align(views.rig_centers, camera_centers(views.R0, views.t0))
    else:
        Rh0, th0 = np.eye(3), np.zeros(3)
    Rh0_t, th0_t = tt(Rh0), tt(th0)
    rig_t = tt(views.rig_centers) if use_rig else None
    use_rot = use_rig and views.rig_R is not None and cfg.rig_rot_sigma_deg > 0
    rigR_t = tt(views.rig_R) if use_rot else None
    rot_sigma = math.radians(cfg.rig_rot_sigma_deg) if use_rot else 1.0
    dwh = torch.zeros(3, dtype=dtype, device=device, requires_grad=use_rig)
    dth = torch.zeros(3, dtype=dtype, device=device, requires_grad=use_rig)
    pose_params = [dw, dtr] + ([dwh, dth] if use_rig else [])

    def poses():
        R = axis_angle_to_matrix(dw * r_unit) @ R0_t
        return R, t0_t + dtr * tv_unit

    def verts():
        return ts.vertices(zs, ze)

    def lm_loss(X, R, t, landmarks_only=False):
        L = X if landmarks_only else X[ts.landmarks]
        uv, _ = project(L[None].expand(V, -1, -1), K_t, R, t)
        d = uv - obs_t
        r = torch.sqrt((d * d).sum(-1) + 1e-12)
        return (wl_t * huber(r, cfg.huber_px)).sum() / (wsum * cfg.landmark_sigma_px ** 2), uv

    def head():
        """The rig → model rigid transform (Rh, th): a rig-frame point x sits at ``Rh x + th`` in model space."""
        return axis_angle_to_matrix(dwh * r_unit) @ Rh0_t, th0_t + dth * t_unit

    def prior(R, t):
        """Negative log priors (½‖z‖², rig), divided by the landmark weight sum like the landmark term."""
        p = 0.5 * cfg.w_shape * (zs * zs).sum() + 0.5 * cfg.w_exp * (ze * ze).sum()
        if use_rig:
            c = camera_centers(R, t)
            Rh, th = head()
            ch = rig_t @ Rh.T + th
            p = p + 0.5 * ((c - ch) ** 2).sum() / cfg.rig_sigma_mm ** 2
            if use_rot:
                # model → camera of view v is R_rig,v · Rhᵀ when the head pose (rig → model) is (Rh, th);
                # ‖ΔR‖²_F = 2·(2 − 2cos θ) ≈ 2θ² for a rotation error θ, so ¼‖ΔR‖²/σ² ≈ ½θ²/σ²
                p = p + 0.25 * ((R - rigR_t @ Rh.T) ** 2).sum() / rot_sigma ** 2
            if cfg.head_sigma_mm > 0:
                p = p + 0.5 * (th * th).sum() / cfg.head_sigma_mm ** 2
        return p / wsum

    history: list[dict] = []
    n_photo = cfg.photo_rounds if (views.images is not None and cfg.w_photo > 0) else 0
    n_flash = cfg.flash_rounds if (views.flash_images is not None and cfg.w_flash > 0) else 0
    bar = progress(range(1 + n_photo + n_flash), desc="fit-geometry", unit="stage")

    def run_lbfgs(params, closure_loss, iters, stage):
        if iters <= 0:
            return
        opt = torch.optim.LBFGS(params, lr=1.0, max_iter=iters, history_size=30, tolerance_grad=1e-9,
                                tolerance_change=1e-10, line_search_fn="strong_wolfe")

        def closure():
            opt.zero_grad()
            loss = closure_loss()
            loss.backward()
            return loss

        opt.step(closure)
        with torch.no_grad():
            final = float(closure_loss())
        history.append({"stage": stage, "loss": final, "evals": int(opt.state[opt._params[0]]["func_evals"])})
        next(bar, None)
        log.debug("fit-geometry: %s loss %.6g after %d evaluations", stage, final, history[-1]["evals"])

    # ---- stage 1: landmarks + priors
    def stage1():
        R, t = poses()
        return cfg.w_landmark * lm_loss(ts.landmark_vertices(zs, ze), R, t, True)[0] + prior(R, t)

    run_lbfgs([zs, ze] + pose_params, stage1, cfg.landmark_iters, "landmarks")

    # ---- stage 2: + photometric
    sh = albedo = sample = None
    photo_res = np.full(V, np.nan)
    flash_res = flash_gain = None
    vis_count = np.zeros(V, dtype=np.int64)
    if n_photo or n_flash:
        Kimg = views.image_K()
        Kimg_t = tt(Kimg)
        skin = model.skin_mask if model.skin_mask is not None else np.ones(model.n_vertices, dtype=bool)
        sample = np.nonzero(skin)[0]
        if len(sample) > cfg.photo_vertices:
            sample = sample[np.linspace(0, len(sample) - 1, cfg.photo_vertices).round().astype(np.int64)]
        # the photometric closures only need the sampled vertices and the triangles around them (their normals
        # are then exactly the full mesh's): evaluate that sub-mesh only
        touch = np.isin(model.triangles, sample).any(1)
        sub_ids = np.unique(model.triangles[touch])
        sub_ids = np.union1d(sub_ids, sample)
        sub_tri_t = torch.as_tensor(np.searchsorted(sub_ids, model.triangles[touch]), dtype=torch.long,
                                    device=device)
        sub = ts.subset(sub_ids)
        sample_t = torch.as_tensor(np.searchsorted(sub_ids, sample), dtype=torch.long, device=device)

        def sub_surface():
            """(vertices, vertex normals) of the sub-mesh at the current coefficients."""
            Xs = sub.vertices(zs, ze)
            return Xs, vertex_normals(Xs, sub_tri_t)
    if n_photo:
        Hc, Wc = views.images.shape[1:3]
        kernel = sh_kernel(dtype, device)
        kernel_np = kernel.cpu().numpy()
        mode = cfg.albedo
        if mode == "auto":
            mode = "texture" if model.mean_tex is not None else "per-vertex"
        if mode == "texture" and model.mean_tex is None:
            raise ReflectmmError("--albedo texture: the face model has no mean texture")
        base_albedo = model.mean_tex[sample] if mode == "texture" else np.broadcast_to(DEFAULT_SKIN,
                                                                                      (len(sample), 3)).copy()
        blurs = list(cfg.photo_blur_px) + [cfg.photo_blur_px[-1] if cfg.photo_blur_px else 0.0] * cfg.photo_rounds
        for rnd in range(cfg.photo_rounds):
            imgs_np = _blur(np.asarray(views.images, dtype=np.float32), blurs[rnd])
            images_t = tt(np.ascontiguousarray(imgs_np.transpose(0, 3, 1, 2)))
            with torch.no_grad():
                X = verts()
                R, t = poses()
                Xn, Rn, tn = X.cpu().numpy().astype(np.float64), R.cpu().numpy(), t.cpu().numpy()
            nrm = vertex_normals(Xn, model.triangles, dtype=np.float64)
            centers = camera_centers(Rn, tn)
            vis = vertex_visibility(Xn, model.triangles, nrm, centers, sample=sample, cos_cutoff=cfg.photo_min_cos)
            uv, _ = project(Xn[sample][None].repeat(V, 0), Kimg, Rn, tn)
            vis &= inside_image(uv, Wc, Hc)
            vis_t = tt(vis.astype(np.float64))
            # closed-form lighting/albedo at the current geometry
            obs = sample_images(images_t, tt(uv)).cpu().numpy().astype(np.float64)
            Y = sh_basis(nrm[sample], SH_ORDER)
            alb = base_albedo.copy() if albedo is None else albedo
            for _ in range(3):
                L = solve_lighting(Y, alb, obs, vis, kernel_np)
                if mode == "per-vertex":
                    alb = solve_albedo(Y, L, obs, vis, kernel_np, base_albedo)
            seen = obs[vis]
            scale = float(np.median(seen)) if seen.size else 1.0
            scale = max(scale, 1e-3)
            sh_t = tt(L).requires_grad_(True)
            alb_t = tt(alb).requires_grad_(mode == "per-vertex")

            def stage2():
                Xs, nv = sub_surface()
                R, t = poses()
                lp, _ = photometric_loss(Xs, nv, sample_t, vis_t, Kimg_t, R, t, images_t, alb_t, sh_t, kernel, scale)
                lml = lm_loss(ts.landmark_vertices(zs, ze), R, t, True)[0]
                return cfg.w_landmark * lml + cfg.w_photo * lp + prior(R, t)

            params = [zs, ze] + pose_params + [sh_t] + ([alb_t] if mode == "per-vertex" else [])
            run_lbfgs(params, stage2, cfg.photo_iters, f"photometric round {rnd + 1}")
            sh = sh_t.detach().cpu().numpy()
            albedo = alb_t.detach().cpu().numpy()
            # residuals on the unblurred images at the final estimate of this round
            with torch.no_grad():
                Xs, nv = sub_surface()
                R, t = poses()
                raw_t = tt(np.ascontiguousarray(np.asarray(views.images, dtype=np.float32).transpose(0, 3, 1, 2)))
                _, r = photometric_loss(Xs, nv, sample_t, vis_t, Kimg_t, R, t, raw_t, alb_t, sh_t, kernel, scale)
                r = r.cpu().numpy()
            vis_count = vis.sum(1)
            for v in range(V):
                photo_res[v] = float(np.sqrt((r[v][vis[v]] ** 2).mean())) if vis[v].any() else np.nan

    # ---- stage 3: + flash images (point lights at the flashes; docs/fit-geometry.md)
    if n_flash:
        flash_res, flash_gain = _flash_rounds(cfg, views, model, ts, sub_surface, sample, sample_t, Kimg, Kimg_t,
                                              tt, poses, head, use_rig, lm_loss, prior, zs, ze, pose_params,
                                              run_lbfgs, dtype, device)

    for _ in bar:  # close the progress bar
        pass
    with torch.no_grad():
        X = verts()
        R, t = poses()
        _, uv = lm_loss(X, R, t)
    uv = uv.cpu().numpy().astype(np.float64)
    err = np.linalg.norm(uv - lm_obs, axis=-1)
    rmse = np.array([math.sqrt(np.mean(err[v][valid[v]] ** 2)) for v in range(V)])
    zs_np = zs.detach().cpu().numpy().astype(np.float64)
    ze_np = ze.detach().cpu().numpy().astype(np.float64)
    shape_coeffs = zs_np * model.shape_sigma
    exp_coeffs = ze_np * model.exp_sigma[:len(ze_np)] if cfg.fit_expression else np.zeros(model.n_exp)
    return GeometryFit(shape_coeffs=shape_coeffs, exp_coeffs=exp_coeffs,
                       vertices=model.vertices(shape_coeffs, exp_coeffs),
                       R=R.cpu().numpy().astype(np.float64), t=t.cpu().numpy().astype(np.float64),
                       K=views.K.copy(), landmark_rmse_px=rmse, landmark_px=uv, photo_residual=photo_res,
                       visible_count=vis_count, sh=sh, albedo=albedo, photo_sample=sample, history=history,
                       flash_residual=flash_res, flash_gain=flash_gain,
                       seconds=time.perf_counter() - t_start)


def _flash_rounds(cfg, views, model, ts, sub_surface, sample, sample_t, Kimg, Kimg_t, tt, poses, head, use_rig,
                  lm_loss, prior, zs, ze, pose_params, run_lbfgs, dtype, device) -> tuple:
    """The flash stage of :func:`_fit`: ``flash_rounds`` L-BFGS rounds of landmarks + priors + the point-light
    term (:func:`.photometric.flash_loss`), visibility, shadows and highlight masks refreshed each round.
    Returns the (V,) RMS residual per view of the last round and the (F,) relative flash gains."""
    V = len(views.names)
    fimg = views.flash_images
    F = fimg.shape[1]
    h, w = fimg.shape[2:4]
    fv = views.flash_view
    rig_ok = np.isfinite(views.flash_rig_pos).all(-1) & use_rig
    usable = np.nonzero((fv >= 0) | rig_ok)[0]
    if len(usable) == 0:
        log.warning("fit-geometry: no flash has a fitted camera or a rig position: the flash term is skipped")
        return np.full(V, np.nan), np.full(F, np.nan)
    if len(usable) < F:
        log.warning("fit-geometry: %d flash(es) have no fitted camera and no rig position: left out of the flash "
                    "term", F - len(usable))
    pv = np.repeat(np.arange(V), len(usable))
    pf = np.tile(usable, V)
    pv_t = torch.as_tensor(pv, dtype=torch.long, device=device)
    fv_t = torch.as_tensor(np.maximum(fv, 0), dtype=torch.long, device=device)
    rigpos_t = tt(np.nan_to_num(views.flash_rig_pos))
    from_view_t = torch.as_tensor(fv >= 0, device=device)[:, None]
    lint_t = tt(views.flash_intensity[pf])
    pf_t = torch.as_tensor(pf, dtype=torch.long, device=device)
    use_t = torch.as_tensor(usable, dtype=torch.long, device=device)
    log_gain = torch.zeros(F, dtype=dtype, device=device, requires_grad=cfg.flash_gains)

    def log_gains():
        """(F,) log relative flash gains, geometric mean 1 over the flashes in the term."""
        return log_gain - log_gain[use_t].mean()

    def intensities():
        """(P,) flash intensity of each pair: the table's, times the fitted relative gain."""
        return lint_t * torch.exp(log_gains()[pf_t])

    def flash_positions_t(R, t):
        c = camera_centers(R, t)[fv_t]
        if use_rig:
            Rh, th = head()
            return torch.where(from_view_t, c, rigpos_t @ Rh.T + th)
        return c

    blurs = list(cfg.photo_blur_px) + [cfg.photo_blur_px[-1] if cfg.photo_blur_px else 0.0] * cfg.flash_rounds
    raw = np.asarray(fimg[pv, pf], dtype=np.float32)  # (P, h, w, 3)
    sat = None if views.flash_saturated is None else np.asarray(views.flash_saturated[pv, pf], dtype=bool)
    cos_hl = math.cos(math.radians(cfg.flash_highlight_deg))
    res = np.full(V, np.nan)
    for rnd in range(cfg.flash_rounds):
        images_t = torch.as_tensor(_blur(raw, blurs[rnd]), device=device)  # (P, h, w, 3) channels last
        with torch.no_grad():
            X = ts.vertices(zs, ze)
            R, t = poses()
            lpos = flash_positions_t(R, t)
            Xn, Rn, tn = X.cpu().numpy().astype(np.float64), R.cpu().numpy(), t.cpu().numpy()
            lpos_np = lpos.cpu().numpy().astype(np.float64)
        nrm = vertex_normals(Xn, model.triangles, dtype=np.float64)
        centers = camera_centers(Rn, tn)
        cam_vis = vertex_visibility(Xn, model.triangles, nrm, centers, sample=sample, cos_cutoff=cfg.photo_min_cos)
        fl_vis = vertex_visibility(Xn, model.triangles, nrm, lpos_np, sample=sample, cos_cutoff=cfg.flash_min_cos)
        uv, _ = project(Xn[sample][None].repeat(V, 0), Kimg, Rn, tn)
        inside = inside_image(uv, w, h)
        p, n = Xn[sample], nrm[sample]
        vdir = centers[pv][:, None] - p[None]
        ldir = lpos_np[pf][:, None] - p[None]
        hvec = vdir / np.linalg.norm(vdir, axis=-1, keepdims=True) + ldir / np.linalg.norm(ldir, axis=-1,
                                                                                          keepdims=True)
        hvec /= np.linalg.norm(hvec, axis=-1, keepdims=True)
        highlight = (hvec * n[None]).sum(-1) > cos_hl
        weight = cam_vis[pv] & fl_vis[pf] & inside[pv] & ~highlight
        if sat is not None:
            px = np.clip(np.rint(uv[pv]).astype(np.int64), 0, [w - 1, h - 1])
            weight &= ~sat[np.arange(len(pv))[:, None], px[..., 1], px[..., 0]]
        sp, sm = np.nonzero(weight)
        seen = gather_bilinear(images_t, torch.as_tensor(sp, device=device),
                               torch.as_tensor(uv[pv[sp], sm], device=device)).cpu().numpy()
        scale = max(float(np.median(seen)) if seen.size else 1.0, 1e-3)
        weight_t = tt(weight.astype(np.float64))

        def stage3():
            Xs, nv = sub_surface()
            R, t = poses()
            lf, _, _ = flash_loss(Xs, nv, sample_t, weight_t, Kimg_t, R, t, images_t, pv_t,
                                  flash_positions_t(R, t)[pf_t], intensities(), scale, residual=False)
            lml = lm_loss(ts.landmark_vertices(zs, ze), R, t, True)[0]
            return cfg.w_landmark * lml + cfg.w_flash * lf + prior(R, t)

        gains = [log_gain] if cfg.flash_gains else []
        run_lbfgs([zs, ze] + pose_params + gains, stage3, cfg.flash_iters, f"flash round {rnd + 1}")
        with torch.no_grad():
            Xs, nv = sub_surface()
            R, t = poses()
            raw_t = torch.as_tensor(raw, device=device)
            _, r, _ = flash_loss(Xs, nv, sample_t, weight_t, Kimg_t, R, t, raw_t, pv_t,
                                 flash_positions_t(R, t)[pf_t], intensities(), scale)
            r = r.cpu().numpy()
        for v in range(V):
            m = weight[pv == v]
            res[v] = float(np.sqrt((r[pv == v][m] ** 2).mean())) if m.any() else np.nan
    with torch.no_grad():
        g = torch.exp(log_gains()).cpu().numpy().astype(np.float64)
    gain = np.full(F, np.nan)
    gain[usable] = g[usable]
    return res, gain
