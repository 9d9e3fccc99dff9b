"""One rig for all identities: bundle adjustment over the landmarks of every identity of a capture (docs/capture.md).

Multi-PIE's cameras and flashes are fixed in the room while the subjects change, so one rig is estimated
jointly from the 68 landmarks of every (identity, view):

* per identity i: shape and expression coefficients (in units of their prior σ) and a head pose
  ``X_rig = R_h,i · X_model + t_h,i``;
* per camera k: orientation ``R_k = exp([ω_k]) · R_k,nominal`` and centre ``c_k`` (mm, rig frame), so that a
  rig point projects with ``x_cam = R_k (X_rig − c_k)``, ``u = f_k x/z + c_x`` (OpenCV pinhole, principal point
  at the image centre as in :mod:`reflectmm_cli.rig`);
* the focal length: ``fixed`` (given), ``shared`` (one value, estimated) or ``per-camera`` (estimated);
* flashes attached to a camera sit at its fitted centre plus a fixed offset in that camera's frame
  (landmarks cannot see a flash: a non-zero offset comes from the user's table); free-standing flashes are
  carried from the nominal table by the rigid transform that best aligns the nominal camera centres to the
  fitted ones.  Raised flashes 14/18 follow the raised cameras 08_1/19_1 when their landmarks are given.

Cost: ``Σ ρ(‖π − u‖ / σ_lm) · w_l + ½‖z_s‖² + ½‖z_e‖² + weak camera prior`` with a robust ρ (Cauchy or
Huber), minimised by Levenberg–Marquardt with analytic Jacobians, the per-identity blocks eliminated by a Schur
complement (a (6C + focal)-sized camera system whatever the number of identities) and the robust (IRLS) weights
refreshed every iteration.  The global rigid motion of the whole scene (every head and every camera) is a gauge
freedom of the landmarks; the weak camera prior towards the nominal table fixes it, and the reported camera
uncertainties have that gauge projected out.  The overall scale is fixed by the face model's size: the MAP
optimum shrinks every face a little (a few per cent), so the scene is finally scaled so that the identities'
mean landmark size equals the model's expected size (exact: a similarity of the whole scene leaves every
projection unchanged).  It averages over the identities (a per-identity fit has its own face size ↔ distance
ambiguity; a shared rig has one).

Library entry points: :func:`calibrate_rig` (landmarks → :class:`RigCalibration`), :func:`calibrate_from_captures`
(capture artifacts → the same), :func:`write_rig_calibration` (NPZ ``rig`` artifact + the rig TOML
:func:`reflectmm_cli.rig.load_rig` reads), :func:`simulate_landmarks` and
:func:`perturb_rig` (synthetic landmarks and a deliberately wrong nominal rig for tests and benchmarks).
"""

from __future__ import annotations

import logging
import math
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any, Sequence

import numpy as np

from reflectmm_cli.errors import ReflectmmError
from reflectmm_cli.geometry import align
from reflectmm_cli.geometry.rotations import nearest_rotation, rodrigues, rotation_angle, skew
from reflectmm_cli.geometry_fit.init import rigid_align
from reflectmm_cli.geometry_fit.landmarks import landmark_weights
from reflectmm_cli.geometry_fit.model import ShapeModel
from reflectmm_cli.rig import RAISED_CAMERAS, Rig, RigCamera, RigFlash

log = logging.getLogger("reflectmm")

__all__ = ["CalibrationConfig", "RigCalibration", "calibrate_rig", "calibrate_from_captures", "landmarks_from_captures",
           "write_rig_calibration", "read_rig_calibration", "rig_calibration_arrays", "expected_face_size",
           "simulate_landmarks", "perturb_rig", "table_distance_ratio", "rodrigues", "LMOptions", "RIG_KIND"]

RIG_KIND = "rig"
FOCAL_MODES = ("fixed", "shared", "per-camera")
LOSSES = ("cauchy", "huber", "l2")


@dataclass
class CalibrationConfig:
    """Parameters of :func:`calibrate_rig`.

    focal: ``fixed`` (the nominal focal, or ``focal_px``), ``shared`` or ``per-camera`` (estimated).
    loss / loss_scale_px: robust loss of the landmark distance (Cauchy ρ(s) = c² log(1 + s²/c²), Huber).
    landmark_sigma_px: assumed landmark noise; balances landmarks against the shape/expression prior.
    camera_sigma_mm / camera_sigma_deg: weak prior towards the nominal camera centres / orientations (it fixes
        the global rigid gauge; it should be much wider than the nominal table's error).
    focal_sigma_rel: prior on log focal around the nominal (wide by default: the nominal focal may be a guess).
    outlier_px: a landmark whose final distance exceeds this is reported as an outlier.
    max_iters / tol: Levenberg–Marquardt iterations (each with refreshed robust weights) and the relative cost
        decrease below which it stops.
    n_shape / n_exp: number of model components used (None: all).
    anchor_scale / distance_sigma_rel: fix the scene's scale by the model's mean face size, fused with the nominal
        table's camera distances from the head (:func:`table_distance_ratio`) of relative uncertainty
        ``distance_sigma_rel`` (0: the faces only).
    carry: how the nominal table's cameras that no identity annotates are moved onto the calibrated rig: by the
        similarity of the annotated cameras' ``centres`` or of their ``poses`` (centres and orientations,
        :func:`carry_similarity`; better with a guessed table, worse with an exact one: docs/benchmarks.md).
    """

    focal: str = "shared"
    focal_px: float | None = None
    loss: str = "cauchy"
    loss_scale_px: float = 3.0
    landmark_sigma_px: float = 1.0
    fit_expression: bool = True
    w_shape: float = 1.0
    w_exp: float = 1.0
    camera_sigma_mm: float = 300.0
    camera_sigma_deg: float = 20.0
    focal_sigma_rel: float = 0.5
    outlier_px: float = 6.0
    max_iters: int = 60
    anchor_scale: bool = True
    tol: float = 1e-6
    distance_sigma_rel: float = 0.1
    n_shape: int | None = None
    n_exp: int | None = None
    group_weights: dict[str, float] | None = None
    carry: str = "centres"
    carry_scale: str = "fit"

    def __post_init__(self) -> None:
        if self.carry not in ("centres", "poses"):
            raise ReflectmmError(f"carry must be 'centres' or 'poses', got {self.carry!r}")
        if self.carry_scale not in ("fit", "distances"):
            raise ReflectmmError(f"carry_scale must be 'fit' or 'distances', got {self.carry_scale!r}")
        if self.focal not in FOCAL_MODES:
            raise ReflectmmError(f"focal must be one of {', '.join(FOCAL_MODES)}, got {self.focal!r}")
        if self.loss not in LOSSES:
            raise ReflectmmError(f"loss must be one of {', '.join(LOSSES)}, got {self.loss!r}")
        for name in ("loss_scale_px", "landmark_sigma_px", "camera_sigma_mm", "camera_sigma_deg", "focal_sigma_rel",
                     "outlier_px"):
            v = float(getattr(self, name))
            if not (math.isfinite(v) and v > 0):
                raise ReflectmmError(f"calibrate-rig: {name} must be a finite number > 0, got {v}")
        if self.focal_px is not None and not (math.isfinite(self.focal_px) and self.focal_px > 0):
            raise ReflectmmError(f"calibrate-rig: focal_px must be > 0, got {self.focal_px}")

    def as_dict(self) -> dict:
        return asdict(self)


@dataclass
class RigCalibration:
    """Result of :func:`calibrate_rig` (float64; mm, px; rig frame = the nominal table's frame up to the fit).

    camera_names (C,); R (C,3,3) world→camera; centers (C,3); focal (C,); image_size (C,2) (W, H);
    center_sigma_mm (C,3) 1-σ of each centre with the global rigid gauge removed; focal_sigma_px (C,);
    rotation_sigma_deg (C,); flash_ids (F,); flash_pos (F,3); flash_camera (F,) ('' = free-standing);
    flash_sigma_mm (F,) (NaN: carried from the nominal table, not measured); identities (N,); head_R (N,3,3),
    head_t (N,3); shape_coeffs (N,Ks), exp_coeffs (N,Ke) (model units, not σ units); landmark_rmse_px (N,C)
    (NaN where a view has no landmarks); outliers (N,C,68) bool; nominal (the nominal Rig); assumptions (list
    of strings: what was assumed); report (dict).
    """

    camera_names: list[str]
    R: np.ndarray
    centers: np.ndarray
    focal: np.ndarray
    image_size: np.ndarray
    center_sigma_mm: np.ndarray
    focal_sigma_px: np.ndarray
    rotation_sigma_deg: np.ndarray
    flash_ids: list[str]
    flash_pos: np.ndarray
    flash_camera: list[str]
    flash_offset: np.ndarray
    flash_intensity: np.ndarray
    flash_sigma_mm: np.ndarray
    identities: list[str]
    head_R: np.ndarray
    head_t: np.ndarray
    shape_coeffs: np.ndarray
    exp_coeffs: np.ndarray
    landmark_rmse_px: np.ndarray
    outliers: np.ndarray
    nominal: Rig
    assumptions: list[str] = field(default_factory=list)
    report: dict = field(default_factory=dict)

    @property
    def t(self) -> np.ndarray:
        return -np.einsum("cij,cj->ci", self.R, self.centers)

    @property
    def K(self) -> np.ndarray:
        K = np.zeros((len(self.camera_names), 3, 3))
        K[:, 0, 0] = K[:, 1, 1] = self.focal
        K[:, 0, 2] = (self.image_size[:, 0] - 1) / 2.0
        K[:, 1, 2] = (self.image_size[:, 1] - 1) / 2.0
        K[:, 2, 2] = 1.0
        return K

    def to_rig(self) -> Rig:
        """The calibrated rig as a :class:`reflectmm_cli.rig.Rig` (cameras look along their fitted axis)."""
        cams = []
        for k, name in enumerate(self.camera_names):
            c = self.centers[k]
            z, y = self.R[k, 2], self.R[k, 1]
            cams.append(RigCamera(name, c.copy(), c + z * max(np.linalg.norm(c), 1.0), -y.copy(),
                                  float(self.focal[k]), int(self.image_size[k, 0]), int(self.image_size[k, 1])))
        # a flash at a calibrated camera's centre stays attached; any other (an offset, a camera that was not
        # calibrated, a stand) is written with its position
        fls = []
        for i, fid in enumerate(self.flash_ids):
            cam = self.flash_camera[i]
            attached = cam in self.camera_names and not np.any(self.flash_offset[i])
            fls.append(RigFlash(fid, self.flash_pos[i].copy(), float(self.flash_intensity[i]),
                                cam if attached else None))
        return Rig(cams, fls)


# --------------------------------------------------------------------------- the problem

class _State:
    """Current estimate: cameras (R, c, log f), heads (R_h, t_h), σ-unit shape/expression coefficients z."""

    def __init__(self, R, c, logf, Rh, th, z):
        self.R, self.c, self.logf, self.Rh, self.th, self.z = R, c, logf, Rh, th, z

    def copy(self) -> "_State":
        return _State(self.R.copy(), self.c.copy(), self.logf.copy(), self.Rh.copy(), self.th.copy(), self.z.copy())


class _Problem:
    """Residuals, analytic Jacobian blocks and the Schur-complement Levenberg–Marquardt step.

    Local parameterisation: a step is (δω_k, δc_k) per camera, δ log f (1 or C), (δω_h, δt_h, δz) per identity;
    rotations are updated multiplicatively (``R ← exp([δω]) R``).  Step units: 0.01 rad, 10 mm, 1 % focal.
    """

    ROT_UNIT = 0.01
    POS_UNIT = 10.0
    F_UNIT = 0.01

    def __init__(self, model: ShapeModel, landmarks: np.ndarray, R0: np.ndarray, c0: np.ndarray,
                 focal0: np.ndarray, pp: np.ndarray, cfg: CalibrationConfig, n_shape: int, n_exp: int):
        self.N, self.C = landmarks.shape[:2]
        self.Ks, self.Ke = n_shape, n_exp
        self.cfg = cfg
        self.obs = np.where(np.isfinite(landmarks), landmarks, 0.0)
        self.valid = np.isfinite(landmarks).all(-1)                      # (N, C, 68)
        self.wl = landmark_weights(cfg.group_weights)[None, None, :] * self.valid
        lm = model.landmarks
        self.mean = model.mean[lm]                                        # (68, 3)
        B = np.concatenate([model.shape_basis[:n_shape, lm] * model.shape_sigma[:n_shape, None, None],
                            model.exp_basis[:n_exp, lm] * model.exp_sigma[:n_exp, None, None]], axis=0)
        self.B = B                                                        # (K, 68, 3)
        self.Bl = np.ascontiguousarray(np.moveaxis(B, 0, -1))             # (68, 3, K)
        self.zw = np.concatenate([np.full(n_shape, cfg.w_shape), np.full(n_exp, cfg.w_exp)])
        self.R0, self.c0 = R0, c0
        self.logf0 = np.log(focal0)                                       # (C,)
        self.pp = pp                                                      # (C, 2)
        self.nf = {"fixed": 0, "shared": 1, "per-camera": self.C}[cfg.focal]
        self.K = n_shape + n_exp
        self.n_id = 6 + self.K
        self.Pc = 6 * self.C + self.nf

    def focal(self, s: _State) -> np.ndarray:
        return np.exp(self.logf0 + (np.broadcast_to(s.logf, (self.C,)) if self.nf else 0.0))

    def geometry(self, s: _State, sl=slice(None)):
        L = self.mean[None] + np.einsum("nk,klj->nlj", s.z[sl], self.B)                  # (n, 68, 3)
        RhL = np.einsum("nij,nlj->nli", s.Rh[sl], L)
        Xw = RhL + s.th[sl, None, :]
        Xc = np.einsum("cij,nclj->ncli", s.R, Xw[:, None] - s.c[None, :, None, :])     # (n, C, 68, 3)
        return RhL, Xc

    def project(self, s: _State, sl=slice(None)):
        _, Xc = self.geometry(s, sl)
        z = Xc[..., 2]
        zs = np.where(np.abs(z) > 1e-6, z, 1e-6)
        uv = self.focal(s)[None, :, None, None] * Xc[..., :2] / zs[..., None] + self.pp[None, :, None, :]
        return uv, z

    def distances(self, s: _State) -> np.ndarray:
        """(N, C, 68) landmark distances in units of σ_lm (0 where missing)."""
        uv, _ = self.project(s)
        return np.where(self.valid, np.linalg.norm(uv - self.obs, axis=-1), 0.0) / self.cfg.landmark_sigma_px

    def rho(self, d2: np.ndarray, c: float) -> tuple[np.ndarray, np.ndarray]:
        """Robust ρ(d²) and its derivative (the IRLS weight)."""
        if self.cfg.loss == "cauchy":
            return c * c * np.log1p(d2 / (c * c)), 1.0 / (1.0 + d2 / (c * c))
        if self.cfg.loss == "huber":
            d = np.sqrt(d2)
            return np.where(d <= c, d2, 2 * c * d - c * c), np.where(d <= c, 1.0, c / np.maximum(d, 1e-300))
        return d2, np.ones_like(d2)

    def prior_terms(self, s: _State):
        """Prior residuals: camera rotation, camera centre, focal; shape/expression."""
        cfg = self.cfg
        dR = np.einsum("cij,ckj->cik", s.R, self.R0)
        ang = np.stack([dR[:, 2, 1] - dR[:, 1, 2], dR[:, 0, 2] - dR[:, 2, 0], dR[:, 1, 0] - dR[:, 0, 1]], -1) / 2
        r_rot = ang / math.radians(cfg.camera_sigma_deg)
        r_c = (s.c - self.c0) / cfg.camera_sigma_mm
        r_f = (s.logf / cfg.focal_sigma_rel) if self.nf else np.zeros(0)
        r_z = np.sqrt(self.zw) * s.z
        return r_rot, r_c, r_f, r_z

    def cost(self, s: _State, c: float) -> float:
        d = self.distances(s)
        rho, _ = self.rho(d * d, c)
        r_rot, r_c, r_f, r_z = self.prior_terms(s)
        return 0.5 * float((self.wl * rho).sum()) + 0.5 * float((r_rot ** 2).sum() + (r_c ** 2).sum()
                                                                  + (r_f ** 2).sum() + (r_z ** 2).sum())

    def cam_cols(self, k: int) -> np.ndarray:
        cols = list(range(6 * k, 6 * k + 6))
        if self.nf:
            cols.append(6 * self.C + (0 if self.nf == 1 else k))
        return np.array(cols)

    def normal_equations(self, s: _State, c: float, chunk: int = 16):
        """Gauss–Newton blocks with IRLS weights at ``s``: H_cc (Pc, Pc), g_c (Pc,), H_ic (N, n_id, Pc),
        H_ii (N, n_id, n_id), g_i (N, n_id) (g = −Jᵀr)."""
        N, C, Pc, n_id = self.N, self.C, self.Pc, self.n_id
        nl = 7 if self.nf else 6
        Hcc_loc = np.zeros((C, nl, nl))
        gc_loc = np.zeros((C, nl))
        Hic = np.zeros((N, n_id, Pc))
        Hii = np.zeros((N, n_id, n_id))
        gi = np.zeros((N, n_id))
        f = self.focal(s)
        for a in range(0, N, chunk):
            sl = slice(a, min(a + chunk, N))
            RhL, Xc = self.geometry(s, sl)
            x, y, z = Xc[..., 0], Xc[..., 1], Xc[..., 2]
            iz = 1.0 / np.where(np.abs(z) > 1e-6, z, 1e-6)
            fz = f[None, :, None] * iz
            uvn = np.stack([x * iz, y * iz], -1)                                       # (n, C, 68, 2)
            uv = f[None, :, None, None] * uvn + self.pp[None, :, None, :]
            D = np.zeros(Xc.shape[:3] + (2, 3))
            D[..., 0, 0] = fz
            D[..., 1, 1] = fz
            D[..., 0, 2] = -fz * uvn[..., 0]
            D[..., 1, 2] = -fz * uvn[..., 1]
            d2 = ((uv - self.obs[sl]) ** 2).sum(-1) / self.cfg.landmark_sigma_px ** 2
            _, w_r = self.rho(d2, c)
            sw = np.sqrt(self.wl[sl] * w_r) / self.cfg.landmark_sigma_px                 # (n, C, 68)
            r = sw[..., None] * (uv - self.obs[sl])                                     # (n, C, 68, 2)
            Ds = D * sw[..., None, None]
            # camera blocks
            Jc_rot = -np.einsum("nclab,nclbd->nclad", Ds, skew(Xc)) * self.ROT_UNIT
            Jc_pos = -np.einsum("nclab,cbd->nclad", Ds, s.R) * self.POS_UNIT
            parts = [Jc_rot, Jc_pos]
            if self.nf:
                parts.append((sw[..., None] * (uv - self.pp[None, :, None, :]) * self.F_UNIT)[..., None])
            Jc = np.concatenate(parts, -1)                                              # (n, C, 68, 2, nl)
            DR = np.einsum("nclab,cbd->nclad", Ds, s.R)                                  # (n, C, 68, 2, 3)
            Jh_rot = -np.einsum("nclab,nlbd->nclad", DR, skew(RhL)) * self.ROT_UNIT
            Jh_pos = DR * self.POS_UNIT
            DRR = np.einsum("nclab,nbd->nclad", DR, s.Rh[sl])
            Jz = np.einsum("nclab,lbk->nclak", DRR, self.Bl)
            Ji = np.concatenate([Jh_rot, Jh_pos, Jz], -1)                               # (n, C, 68, 2, n_id)
            Hcc_loc += np.einsum("nclai,nclaj->cij", Jc, Jc)
            gc_loc -= np.einsum("nclai,ncla->ci", Jc, r)
            Hii[sl] = np.einsum("nclai,nclaj->nij", Ji, Ji)
            gi[sl] = -np.einsum("nclai,ncla->ni", Ji, r)
            hic = np.einsum("nclai,nclaj->ncij", Ji, Jc)                                # (n, C, n_id, nl)
            for k in range(C):
                Hic[sl][:, :, self.cam_cols(k)] += hic[:, k]
        Hcc = np.zeros((Pc, Pc))
        gc = np.zeros(Pc)
        for k in range(C):
            cols = self.cam_cols(k)
            Hcc[np.ix_(cols, cols)] += Hcc_loc[k]
            gc[cols] += gc_loc[k]
        # priors (first-order Jacobians in step units)
        r_rot, r_c, r_f, r_z = self.prior_terms(s)
        sr = self.ROT_UNIT / math.radians(self.cfg.camera_sigma_deg)
        sp = self.POS_UNIT / self.cfg.camera_sigma_mm
        for k in range(C):
            for j in range(3):
                Hcc[6 * k + j, 6 * k + j] += sr * sr
                gc[6 * k + j] -= sr * r_rot[k, j]
                Hcc[6 * k + 3 + j, 6 * k + 3 + j] += sp * sp
                gc[6 * k + 3 + j] -= sp * r_c[k, j]
        if self.nf:
            sf = self.F_UNIT / self.cfg.focal_sigma_rel
            for j in range(self.nf):
                Hcc[6 * C + j, 6 * C + j] += sf * sf
                gc[6 * C + j] -= sf * r_f[j]
        dz = np.arange(6, n_id)
        Hii[:, dz, dz] += self.zw[None]
        gi[:, 6:] -= np.sqrt(self.zw)[None] * r_z
        return Hcc, gc, Hic, Hii, gi

    def solve_step(self, eq, lam: float):
        """Damped Schur-complement solve: returns (δ_cam (Pc,), δ_id (N, n_id)), and the undamped Schur
        complement is not formed here (see :meth:`schur`)."""
        Hcc, gc, Hic, Hii, gi = eq
        dH = Hii + lam * (np.einsum("nii->ni", Hii)[..., None] * np.eye(self.n_id) + 1e-9 * np.eye(self.n_id))
        rhs = np.concatenate([Hic, gi[..., None]], -1)
        sol = np.linalg.solve(dH, rhs)                                                   # (N, n_id, Pc+1)
        S = Hcc + lam * np.diag(np.diag(Hcc)) + 1e-9 * np.eye(self.Pc) - np.einsum("nia,nib->ab", Hic, sol[..., :-1])
        b = gc - np.einsum("nia,ni->a", Hic, sol[..., -1])
        dc = np.linalg.solve(S, b)
        di = sol[..., -1] - np.einsum("nia,a->ni", sol[..., :-1], dc)
        return dc, di

    def schur(self, eq) -> np.ndarray:
        Hcc, _, Hic, Hii, _ = eq
        sol = np.linalg.solve(Hii + 1e-12 * np.eye(self.n_id), Hic)
        return Hcc - np.einsum("nia,nib->ab", Hic, sol)

    def apply(self, s: _State, dc: np.ndarray, di: np.ndarray) -> _State:
        t = s.copy()
        C = self.C
        cam = dc[:6 * C].reshape(C, 6)
        t.R = rodrigues(cam[:, :3] * self.ROT_UNIT) @ s.R
        t.c = s.c + cam[:, 3:] * self.POS_UNIT
        if self.nf:
            t.logf = s.logf + dc[6 * C:] * self.F_UNIT
        t.Rh = rodrigues(di[:, :3] * self.ROT_UNIT) @ s.Rh
        t.th = s.th + di[:, 3:6] * self.POS_UNIT
        t.z = s.z + di[:, 6:]
        return t


# --------------------------------------------------------------------------- main entry

def _nominal_cameras(nominal: Rig, names: Sequence[str], image_size: np.ndarray, cfg: CalibrationConfig
                     ) -> tuple[np.ndarray, np.ndarray, np.ndarray, list[str]]:
    """Nominal R, centres, focal (C,) of the named cameras; refuses a table whose image size differs."""
    missing = [n for n in names if n not in nominal.camera_names]
    if missing:
        raise ReflectmmError(f"view(s) {', '.join(missing)} are not cameras of the nominal rig "
                             f"(rig cameras: {', '.join(nominal.camera_names)})", nominal.source)
    notes = []
    R, c, f = [], [], []
    for k, n in enumerate(names):
        cam = nominal.camera(n)
        W, H = (int(v) for v in image_size[k])
        if (cam.width, cam.height) != (W, H):
            raise ReflectmmError(f"nominal rig camera {n} is {cam.width}x{cam.height} but its images are {W}x{H}: "
                                 "give a rig table for this image size (its focal in pixels depends on it)",
                                 nominal.source)
        if not np.linalg.norm(cam.center) > 0:
            raise ReflectmmError(f"nominal rig camera {n} sits at the origin of model space, where the head is "
                                 "(the table's positions are relative to the head)", nominal.source)
        R.append(cam.R)
        c.append(cam.center)
        f.append(cam.focal_px if cfg.focal_px is None else cfg.focal_px)
    if cfg.focal_px is not None:
        notes.append(f"initial focal {cfg.focal_px:g} px given by the user")
    else:
        notes.append("initial focal from the nominal rig table")
    return np.array(R), np.array(c), np.array(f, np.float64), notes


def _face_size(L: np.ndarray) -> np.ndarray:
    """RMS distance (mm) of the 68 landmarks from their centroid: (..., 68, 3) → (...)."""
    return np.sqrt(((L - L.mean(-2, keepdims=True)) ** 2).sum(-1).mean(-1))


def expected_face_size(model: ShapeModel, n_shape: int | None = None, samples: int = 4096, seed: int = 0,
                       return_std: bool = False):
    """Monte-Carlo mean (and with ``return_std`` the standard deviation) of :func:`_face_size` of the landmarks
    over the shape prior (expression neutral), mm."""
    k = model.n_shape if n_shape is None else n_shape
    rng = np.random.default_rng(seed)
    z = rng.normal(size=(samples, k))
    lm = model.landmarks
    B = (model.shape_basis[:k, lm] * model.shape_sigma[:k, None, None]).reshape(k, -1)
    L = (model.mean[lm].reshape(1, -1) + z @ B).reshape(samples, 68, 3)
    sz = _face_size(L)
    return (float(sz.mean()), float(sz.std())) if return_std else float(sz.mean())


def _gauge_free_cov(cov_c: np.ndarray, centers: np.ndarray) -> np.ndarray:
    """Project the infinitesimal rigid motions of all centres (3C-dim) out of their covariance (3C, 3C)."""
    C = len(centers)
    B = np.zeros((3 * C, 6))
    for k in range(C):
        B[3 * k:3 * k + 3, :3] = np.eye(3)
        x, y, z = centers[k]
        B[3 * k:3 * k + 3, 3:] = np.array([[0, z, -y], [-z, 0, x], [y, -x, 0]])
    P = np.eye(3 * C) - B @ np.linalg.pinv(B)
    return P @ cov_c @ P.T


@dataclass
class _RigSetup:
    """The checked inputs of one calibration: landmarks (N, C, 68, 2) float64 (NaN missing), camera names (C,),
    identity ids (N,), image sizes (C, 2), the nominal cameras R0 (C, 3, 3) / c0 (C, 3) mm / f0 (C,) px, the
    principal points pp (C, 2) px, the model components used (Ks shape, Ke expression) and the assumptions so far."""

    lm: np.ndarray
    names: list[str]
    ids: list[str]
    image_size: np.ndarray
    R0: np.ndarray
    c0: np.ndarray
    f0: np.ndarray
    pp: np.ndarray
    Ks: int
    Ke: int
    assumptions: list[str]

    @property
    def N(self) -> int:
        return self.lm.shape[0]

    @property
    def C(self) -> int:
        return self.lm.shape[1]


@dataclass
class LMOptions:
    """Levenberg–Marquardt schedule of :func:`_levenberg_marquardt` (pycolmap-style solver options).

    max_iters / tol: outer iterations (robust weights refreshed in each) and the relative cost decrease that stops
    them once the robust scale is steady; loss_scale: final robust scale in units of σ_lm; lam0: initial damping;
    tries: damping increases (×4) tried per iteration before giving up on it.
    """

    max_iters: int = 60
    tol: float = 1e-6
    loss_scale: float = 3.0
    lam0: float = 1e-3
    tries: int = 12

    @classmethod
    def from_config(cls, cfg: CalibrationConfig) -> "LMOptions":
        return cls(max_iters=max(int(cfg.max_iters), 1), tol=cfg.tol,
                   loss_scale=cfg.loss_scale_px / cfg.landmark_sigma_px)


@dataclass
class _LMResult:
    """Output of :func:`_levenberg_marquardt`: the state, per-iteration history and whether it converged."""

    state: _State
    history: list[dict]
    converged: bool


@dataclass
class _Residuals:
    """Final landmark distances d (N, C, 68) px (NaN missing), their validity, depths z, per-view RMSE (N, C)
    and the outlier mask (N, C, 68)."""

    d: np.ndarray
    valid: np.ndarray
    z: np.ndarray
    rmse: np.ndarray
    outliers: np.ndarray


@dataclass
class _Uncertainty:
    """Laplace-approximation σ of the cameras: centres (C, 3) mm (gauge-free), rotations (C,) deg, focal (C,) px,
    and the noise variance factor s2."""

    center_mm: np.ndarray
    rotation_deg: np.ndarray
    focal_px: np.ndarray
    s2: float


@dataclass
class _Flashes:
    """Placed flashes: ids (F,), positions (F, 3) mm, camera names ('' free-standing), offsets in their camera
    frame (F, 3) mm, intensities (F,), σ (F,) mm (NaN: carried from the nominal table)."""

    ids: list[str]
    pos: np.ndarray
    camera: list[str]
    offset: np.ndarray
    intensity: np.ndarray
    sigma_mm: np.ndarray


def _annotated(lm: np.ndarray) -> np.ndarray:
    """(C,) bool: the cameras that at least one identity annotates (≥ 6 landmarks) in lm (N, C, 68, 2)."""
    return (np.isfinite(lm).all(-1).sum(-1) >= 6).any(0)


def _setup(model: ShapeModel, landmarks, camera_names: Sequence[str], image_size, nominal: Rig,
           cfg: CalibrationConfig, identities: Sequence[str] | None) -> _RigSetup:
    """Check the inputs of :func:`calibrate_rig` and gather them with the nominal cameras and first assumptions."""
    lm = np.asarray(landmarks, np.float64)
    names = list(camera_names)
    if lm.ndim != 4 or lm.shape[1:] != (len(names), 68, 2):
        raise ReflectmmError(f"landmarks must be (N, {len(names)}, 68, 2), got {lm.shape}")
    N, C = lm.shape[:2]
    ids = [f"{i:03d}" for i in range(N)] if identities is None else [str(i) for i in identities]
    isz = np.asarray(image_size, np.int64).reshape(-1, 2)
    isz = np.broadcast_to(isz, (C, 2)).copy()
    R0, c0, f0, notes = _nominal_cameras(nominal, names, isz, cfg)
    if N < 1:
        raise ReflectmmError("calibrate-rig needs at least one identity")
    seen = _annotated(lm)
    if seen.sum() < 3 and not seen.all():
        raise ReflectmmError("no landmarks at all for camera(s) " + ", ".join(n for n, s in zip(names, seen) if not s)
                             + f" and only {int(seen.sum())} camera(s) with landmarks: at least 3 are needed "
                             "to carry the nominal table to the others")
    Ks = model.n_shape if cfg.n_shape is None else min(cfg.n_shape, model.n_shape)
    Ke = 0 if not cfg.fit_expression else (model.n_exp if cfg.n_exp is None else min(cfg.n_exp, model.n_exp))
    pp = np.stack([(isz[:, 0] - 1) / 2.0, (isz[:, 1] - 1) / 2.0], axis=1)
    assumptions = list(notes)
    table = Path(nominal.source).name if nominal.source else "the given table"  # no workspace path in the artifact
    assumptions.append(f"nominal camera orientations and centres from {table}; "
                       f"weak prior σ = {cfg.camera_sigma_mm:g} mm / {cfg.camera_sigma_deg:g}° fixes the global "
                       "rigid gauge only")
    assumptions.append({"fixed": "focal fixed (not estimated)", "shared": "one focal shared by every camera "
                        "(estimated)", "per-camera": "one focal per camera (estimated)"}[cfg.focal])
    assumptions.append("principal point at the image centre, no lens distortion")
    assumptions.append("scale from the face model's mean face size (shape prior, averaged over identities)")
    return _RigSetup(lm, names, ids, isz, R0, c0, f0, pp, Ks, Ke, assumptions)


def _rig_target(R0: np.ndarray, c0: np.ndarray) -> np.ndarray:
    """The point (3,) closest, in least squares, to every camera's optical axis (R0 (C, 3, 3), centres c0 (C, 3));
    the origin for fewer than two cameras."""
    A = np.zeros((3, 3))
    b = np.zeros(3)
    for k in range(len(R0)):
        d = R0[k, 2]
        P = np.eye(3) - np.outer(d, d)
        A += P
        b += P @ c0[k]
    return np.linalg.lstsq(A, b, rcond=None)[0] if len(R0) >= 2 else np.zeros(3)


def _initial_state(prob: _Problem, R0: np.ndarray, c0: np.ndarray) -> _State:
    """Nominal cameras, nominal focal, every head unrotated at the point where the rig looks, mean faces."""
    N = prob.N
    target = _rig_target(R0, c0)
    return _State(R0.copy(), c0.copy(), np.zeros(prob.nf), np.broadcast_to(np.eye(3), (N, 3, 3)).copy(),
                  np.broadcast_to(target, (N, 3)).copy(), np.zeros((N, prob.K)))


def _levenberg_marquardt(prob: _Problem, st: _State, opts: LMOptions, progress_fn=None) -> _LMResult:
    """Robust Levenberg–Marquardt on ``prob`` from ``st`` (not modified).

    The robust scale is annealed from 3× the median landmark distance down to ``opts.loss_scale`` (a wrong
    nominal rig starts with residuals of tens of pixels, which a Cauchy loss at 3 px would treat as outliers);
    each iteration refreshes the IRLS weights, then tries damped Schur steps until the cost decreases.
    """
    lam = opts.lam0
    it_max = opts.max_iters
    bar = progress_fn(range(it_max), desc="calibrate-rig", unit="iter") if progress_fn else range(it_max)
    history: list[dict] = []
    converged = False
    c_prev = np.inf
    for it in bar:
        if converged:
            continue
        d = prob.distances(st)
        med = float(np.median(d[prob.valid])) if prob.valid.any() else 0.0
        c_now = min(c_prev, max(opts.loss_scale, 3.0 * med))
        steady = c_now >= 0.99 * c_prev
        c_prev = c_now
        eq = prob.normal_equations(st, c_now)
        cost0 = prob.cost(st, c_now)
        for _ in range(opts.tries):
            dc, di = prob.solve_step(eq, lam)
            trial = prob.apply(st, dc, di)
            cost1 = prob.cost(trial, c_now)
            if np.isfinite(cost1) and cost1 < cost0:
                st = trial
                lam = max(lam / 3.0, 1e-7)
                break
            lam *= 4.0
        else:
            cost1 = cost0
        history.append({"iter": it, "cost": round(cost1, 6), "scale": round(c_now, 4), "lambda": lam})
        log.debug("calibrate-rig iteration %d: cost %.6g (robust scale %.2f, lambda %.2g)", it, cost1, c_now, lam)
        if steady and cost0 - cost1 <= opts.tol * max(cost0, 1e-300):
            converged = True
    return _LMResult(st, history, converged)


def table_distance_ratio(c_table: np.ndarray, c_fit: np.ndarray, head: np.ndarray, seen: np.ndarray
                         ) -> tuple[float, np.ndarray]:
    """The nominal table's size against a fit's: the median over the cameras ``seen`` (bool (C,)) of
    ``‖c_table‖ / ‖c_fit − head‖``, each camera's distance from the head in the table (whose head sits at the
    origin) over its distance from the fit's mean head position.

    Distances are what a user measures of a rig, and they do not change when a table entry is only turned about
    the head (a camera's direction a few degrees off), which changes the spread of a few near-frontal cameras
    by per cents; the median leaves out a guessed entry (a raised camera placed hundreds of millimetres off).  A
    camera no landmark places stays where the table put it and says nothing of the scale, so only seen ones count.

    Args:
        c_table: (C, 3) centres of the nominal table (mm), head at the origin.
        c_fit: (C, 3) fitted centres; head (3,) the fit's mean head position in the same frame.
        seen: (C,) bool, the cameras with landmarks.
    Returns:
        ``(ratio, used)``: the median ratio and the cameras it was taken over (bool (C,)).
    """
    c_table = np.asarray(c_table, np.float64)
    c_fit = np.asarray(c_fit, np.float64)
    used = np.asarray(seen, bool) & (np.linalg.norm(c_fit - head, axis=1) > 0)
    r = np.linalg.norm(c_table[used], axis=1) / np.linalg.norm(c_fit[used] - head, axis=1)
    return float(np.median(r)), used


def _scale_anchor(model: ShapeModel, prob: _Problem, st: _State, setup: _RigSetup, cfg: CalibrationConfig
                  ) -> tuple[float, str | None]:
    """Scale factor for the whole scene, and its note (None when not anchored).

    The MAP shrinks each face towards the mean in the directions its landmarks do not determine, and a shrunk face
    is a smaller face (size is a norm of the coefficients), so the joint optimum puts the rig too close by a few per
    cent.  The landmarks fix the scene only up to a similarity; its scale is chosen so that the identities' mean face
    size equals the model's expected size under its prior, fused (in log scale, by inverse variances) with the
    nominal table's camera distances (:func:`table_distance_ratio`) of relative σ ``cfg.distance_sigma_rel``.
    Scaling the whole scene (centres, head positions, faces) leaves every projection unchanged.
    """
    Ks, N, C = setup.Ks, setup.N, setup.C
    if not (cfg.anchor_scale and Ks > 0):
        return 1.0, None
    target, spread = expected_face_size(model, Ks, return_std=True)
    fitted = float(np.mean(_face_size(prob.mean[None] + np.einsum("nk,klj->nlj", st.z[:, :Ks], prob.B[:Ks]))))
    s_face = target / fitted
    sig_f = spread / target / math.sqrt(N)
    logs = math.log(s_face)
    note = (f"scale: the identities' mean landmark-face size set to the model's expected {target:.2f} mm "
            f"(x{s_face:.4f}, ±{100 * sig_f:.1f} %)")
    if cfg.distance_sigma_rel and cfg.distance_sigma_rel > 0 and C >= 2:
        seen = np.isfinite(setup.lm).all(-1).any(-1).any(0)                          # cameras with landmarks
        s_nom, used = table_distance_ratio(setup.c0, st.c, st.th.mean(0), seen)
        wf, wn = 1.0 / sig_f ** 2, 1.0 / cfg.distance_sigma_rel ** 2
        logs = (wf * math.log(s_face) + wn * math.log(s_nom)) / (wf + wn)
        note += (f", fused with the nominal table's distances (x{s_nom:.4f}, ±{100 * cfg.distance_sigma_rel:.1f} %, "
                 f"the median over camera(s) {', '.join(setup.names[k] for k in np.flatnonzero(used))}) "
                 f"at weight {wn / (wf + wn):.2f}")
    anchor = math.exp(logs)
    return anchor, note + f": x{anchor:.4f} on the bundle-adjustment optimum"


def _reframe(st: _State) -> None:
    """Express ``st`` (in place) in the rig table's convention: origin at the identities' mean head position, axes
    along their mean head orientation (x' = R̄ᵀ (x − t̄), R̄ the rotation nearest the mean of the R_h).  The
    landmarks fix the scene only up to a rigid motion, so every projection is unchanged."""
    Rbar = nearest_rotation(st.Rh.mean(0))
    tbar = st.th.mean(0)
    st.R = np.einsum("cij,jk->cik", st.R, Rbar)
    st.c = (st.c - tbar) @ Rbar
    st.Rh = np.einsum("ji,njk->nik", Rbar, st.Rh)
    st.th = (st.th - tbar) @ Rbar


def _residuals(prob: _Problem, st: _State, lm: np.ndarray, cfg: CalibrationConfig) -> _Residuals:
    """Final landmark distances, per-view RMSE and outliers over the landmarks the fit uses (a group of weight 0,
    e.g. a detector's jaw, is neither a residual nor an outlier, nor a degree of freedom of the noise estimate);
    refuses landmarks that ended behind a camera."""
    uv, z = prob.project(st)
    d = np.linalg.norm(uv - lm, axis=-1)                                               # (N, C, 68), NaN missing
    valid = np.isfinite(d) & (np.broadcast_to(prob.wl, d.shape) > 0)
    n = valid.sum(-1)
    rmse = np.full(d.shape[:-1], np.nan)
    rmse[n > 0] = np.sqrt((np.where(valid, d, 0.0) ** 2).sum(-1)[n > 0] / n[n > 0])  # NaN for a view without any
    outliers = valid & (np.nan_to_num(d, nan=0.0) > cfg.outlier_px)
    if np.any(np.isfinite(d) & (z <= 0)):
        raise ReflectmmError("calibrate-rig: landmarks ended up behind a camera; the nominal rig is too far off "
                             "(check camera names, angles and image size)")
    return _Residuals(d, valid, z, rmse, outliers)


def _uncertainty(prob: _Problem, st: _State, res: _Residuals, loss_scale: float) -> _Uncertainty:
    """Laplace approximation at the solution: Gauss–Newton Hessian with the final IRLS weights (robust scale
    ``loss_scale`` in σ_lm units), heads and shapes eliminated by the Schur complement, noise scale from the
    weighted inlier residuals; the centres' covariance has the global rigid motion projected out."""
    cfg, C, N = prob.cfg, prob.C, prob.N
    d, valid, outliers = res.d, res.valid, res.outliers
    eq = prob.normal_equations(st, loss_scale)
    inl = valid & ~outliers
    dof = max(2 * int(inl.sum()) - (prob.Pc + N * prob.n_id), 1)
    _, wr = prob.rho((d / cfg.landmark_sigma_px) ** 2, loss_scale)
    s2 = float((wr[inl] * prob.wl[inl] * (d[inl] / cfg.landmark_sigma_px) ** 2).sum()) / dof
    cov = np.linalg.pinv(prob.schur(eq)) * max(s2, 1e-12)
    ci = (6 * np.arange(C)[:, None] + 3 + np.arange(3)).reshape(-1)
    cov_c = _gauge_free_cov(cov[np.ix_(ci, ci)] * prob.POS_UNIT ** 2, st.c)
    cam_sig = np.sqrt(np.clip(np.diag(cov_c), 0, None)).reshape(C, 3)
    ri = (6 * np.arange(C)[:, None] + np.arange(3)).reshape(-1)
    rot_sig = np.degrees(np.sqrt(np.clip(np.diag(cov[np.ix_(ri, ri)]), 0, None)).reshape(C, 3).max(1)
                         * prob.ROT_UNIT)
    foc_sig = np.zeros(C)
    if prob.nf:
        fv = np.sqrt(np.clip(np.diag(cov)[6 * C:], 0, None)) * prob.F_UNIT
        foc_sig = prob.focal(st) * np.broadcast_to(fv, (C,))
    return _Uncertainty(cam_sig, rot_sig, foc_sig, s2)


def _place_flashes(nominal: Rig, flash_ids: Sequence[str] | None, setup: _RigSetup, st: _State,
                   cam_sig: np.ndarray) -> tuple[_Flashes, list[str]]:
    """Place the flashes in the fitted rig, and say which were not measured.

    A flash attached to a calibrated camera keeps its nominal offset in that camera's frame; the others are carried
    by the rigid map that best aligns the nominal camera centres to the fitted ones (identity below three cameras).
    """
    names, c0, R, c = setup.names, setup.c0, st.R, st.c
    notes: list[str] = []
    fl_ids = list(flash_ids) if flash_ids is not None else nominal.flash_ids
    Ra, ta, _ = rigid_align(c0, c) if setup.C >= 3 else (np.eye(3), np.zeros(3), None)
    fpos, fcam, foff, fint, fsig = [], [], [], [], []
    for fid in fl_ids:
        fl = nominal.flash(fid)
        fint.append(fl.intensity)
        if fl.camera is not None and fl.camera in names:
            k = names.index(fl.camera)
            nom_cam = nominal.camera(fl.camera)
            off_cam = nom_cam.R @ (np.asarray(fl.position) - nom_cam.center)      # offset in the camera frame
            fpos.append(c[k] + R[k].T @ off_cam)
            fcam.append(fl.camera)
            foff.append(off_cam)
            fsig.append(float(np.linalg.norm(cam_sig[k])))
        else:
            p = nominal.camera(fl.camera).center if fl.camera is not None else np.asarray(fl.position)
            fpos.append(Ra @ p + ta)
            fcam.append(fl.camera or "")
            foff.append(np.zeros(3))
            fsig.append(float("nan"))
            why = (f"its camera {fl.camera} has no landmarks in this capture" if fl.camera is not None
                   else "it is free-standing")
            notes.append(f"flash {fid} carried from the nominal table ({why}): not measured")
    for raised, fid in zip(RAISED_CAMERAS, ("14", "18")):
        if fid in fl_ids and raised not in names:
            notes.append(f"flash {fid} sits on camera {raised}, which is not among the calibrated views: "
                         "add its landmarks to place it")
    flashes = _Flashes(fl_ids, np.array(fpos).reshape(-1, 3), fcam, np.array(foff).reshape(-1, 3),
                       np.array(fint, np.float64), np.array(fsig))
    return flashes, notes


def _calibration_report(prob: _Problem, st: _State, setup: _RigSetup, res: _Residuals, unc: _Uncertainty,
                        lmr: _LMResult, anchor: float, t_start: float) -> dict[str, Any]:
    """The report dict of :class:`RigCalibration` (counts, residuals, outliers, history, camera moves)."""
    cfg, N, C, ids, names = prob.cfg, setup.N, setup.C, setup.ids, setup.names
    valid, rmse, c, R, f = res.valid, res.rmse, st.c, st.R, prob.focal(st)
    out_list = [(ids[i], names[k], int(l)) for i, k, l in zip(*np.nonzero(res.outliers))]
    history = lmr.history
    report = {
        "identities": N, "cameras": C, "landmarks_used": int(valid.sum()), "unknowns": int(prob.Pc + N * prob.n_id),
        "landmark_rmse_px_median": float(np.nanmedian(rmse)), "outliers": len(out_list),
        "outlier_fraction": float(len(out_list) / max(int(valid.sum()), 1)),
        "outliers_first": [f"{a}/{b}/#{l}" for a, b, l in out_list[:50]],
        "views_worst": [f"{ids[i]}/{names[k]}: {rmse[i, k]:.2f} px" for i, k in
                        zip(*np.unravel_index(np.argsort(-np.nan_to_num(rmse, nan=-1.0), axis=None)[:10],
                                              rmse.shape))],
        "noise_scale": math.sqrt(unc.s2), "iterations": len(history), "converged": lmr.converged,
        "cost_final": history[-1]["cost"] if history else None, "history": history,
        "seconds": round(time.perf_counter() - t_start, 3),
        "camera_shift_mm": {n: round(float(np.linalg.norm(c[k] - setup.c0[k])), 3) for k, n in enumerate(names)},
        "camera_turn_deg": {n: round(float(np.degrees(rotation_angle(R[k], setup.R0[k]))), 4)
                            for k, n in enumerate(names)},
        "focal_px": [round(float(v), 3) for v in f],
        "config": cfg.as_dict(), "scale_anchor": anchor,
    }
    log.info("calibrate-rig: %d identities x %d views, landmark RMS %.2f px (median), %d outliers, "
             "focal %s px, %.1f s", N, C, report["landmark_rmse_px_median"], len(out_list),
             "/".join(f"{v:.0f}" for v in np.unique(np.round(f))), report["seconds"])
    return report


def _model_coeffs(model: ShapeModel, st: _State, Ks: int, Ke: int) -> tuple[np.ndarray, np.ndarray]:
    """σ-unit coefficients of ``st`` → the model's shape (N, n_shape) and expression (N, n_exp) coefficients."""
    N = len(st.z)
    shape_coeffs = np.zeros((N, model.n_shape))
    shape_coeffs[:, :Ks] = st.z[:, :Ks] * model.shape_sigma[:Ks]
    exp_coeffs = np.zeros((N, model.n_exp))
    exp_coeffs[:, :Ke] = st.z[:, Ks:] * model.exp_sigma[:Ke]
    return shape_coeffs, exp_coeffs


def _subset(setup: _RigSetup, keep: np.ndarray) -> _RigSetup:
    """The setup restricted to the cameras ``keep`` (C,) bool."""
    k = np.nonzero(keep)[0]
    return _RigSetup(setup.lm[:, k], [setup.names[i] for i in k], setup.ids, setup.image_size[k], setup.R0[k],
                     setup.c0[k], setup.f0[k], setup.pp[k], setup.Ks, setup.Ke, setup.assumptions)


def carry_similarity(c0: np.ndarray, c: np.ndarray, R0: np.ndarray, R: np.ndarray, iters: int = 10,
                     scale: float | None = None):
    """The similarity (Ra, ta, sa) with ``c ≈ sa · c0 @ Raᵀ + ta`` and ``R ≈ R0 @ Raᵀ`` that best maps a nominal
    table's cameras onto their calibrated poses, from their centres and their orientations together.

    Cameras on one horizontal arc fix the similarity's tilt about the arc poorly by their centres alone; their
    orientations fix every axis. Each term is weighted by its own residual variance (re-estimated per iteration):
    the rotation maximises tr(Raᵀ (sa Σ y xᵀ / σ_c² + Σ Rₖᵀ R0ₖ / (2 σ_r²))) (x, y the centred centres; σ_c mm and
    σ_r rad per axis).  ``iters = 0``: the centres' similarity alone (Umeyama).  ``scale``: hold sa at this value
    (the rotation and shift are then fitted to the scaled table) instead of fitting it.  Returns (Ra, ta, sa, centre
    residuals (n,) mm, angle residuals (n,) rad)."""
    c0, c = np.asarray(c0, np.float64), np.asarray(c, np.float64)
    if scale is None:
        Ra, ta, sa = align.rigid_align(c0, c, scale=True)
    else:
        sa = float(scale)
        Ra, ta, _ = align.rigid_align(sa * c0, c)
    M = np.transpose(R, (0, 2, 1)) @ R0                                  # each camera's own estimate of Ra
    x, y = c0 - c0.mean(0), c - c.mean(0)
    for _ in range(iters):
        rc = np.linalg.norm(sa * x @ Ra.T - y, axis=-1)
        rr = rotation_angle(M, Ra[None])
        var_c = max(float(np.mean(rc ** 2)) / 3.0, 1.0)
        var_r = max(float(np.mean(rr ** 2)) / 3.0, math.radians(0.1) ** 2)
        A = sa * (y.T @ x) / var_c + M.sum(0) / (2.0 * var_r)
        Ra = nearest_rotation(A)
        if scale is None:
            sa = float(np.sum(y * (x @ Ra.T)) / np.sum(x * x))
        ta = c.mean(0) - sa * c0.mean(0) @ Ra.T
    return Ra, ta, sa, np.linalg.norm(sa * c0 @ Ra.T + ta - c, axis=-1), rotation_angle(M, Ra[None])


def _add_unseen(cal: RigCalibration, setup: _RigSetup, seen: np.ndarray, cfg: CalibrationConfig) -> RigCalibration:
    """Insert the cameras no identity annotates: the nominal table's pose carried by the similarity that best
    aligns the calibrated cameras' nominal centres (``cfg.carry`` ``centres``) or centres and orientations
    (``poses``, :func:`carry_similarity`) to their fitted ones (a table's distance is its least certain part, the
    scale corrects it), their nominal prior, not measured (σ NaN); the focal the nominal one (times the fitted
    common factor with a shared focal)."""
    k_seen, k_un = np.nonzero(seen)[0], np.nonzero(~seen)[0]
    poses = cfg.carry == "poses"  # no iteration: the centres' Umeyama similarity, both residuals reported
    scale = None
    if cfg.carry_scale == "distances":
        ratio, _ = table_distance_ratio(setup.c0[k_seen], cal.centers, np.zeros(3), np.ones(len(k_seen), bool))
        scale = 1.0 / ratio
    Ra, ta, sa, res, res_rot = carry_similarity(setup.c0[k_seen], cal.centers, setup.R0[k_seen], cal.R,
                                                iters=10 if poses else 0, scale=scale)
    how = "centres and orientations" if poses else "centres"
    if scale is not None:
        how += ", the scale from their distances to the head against the table's"
    C, N = setup.C, setup.N
    R = np.zeros((C, 3, 3))
    centers = np.zeros((C, 3))
    focal = setup.f0.copy() if cfg.focal_px is None else np.full(C, float(cfg.focal_px))
    if cfg.focal == "shared":
        focal = focal * float(np.median(cal.focal / focal[k_seen]))
    R[k_seen], centers[k_seen], focal[k_seen] = cal.R, cal.centers, cal.focal
    R[k_un] = setup.R0[k_un] @ Ra.T
    centers[k_un] = sa * setup.c0[k_un] @ Ra.T + ta

    def widen(a, fill):
        out = np.full((C,) + a.shape[1:], fill, dtype=a.dtype)
        out[k_seen] = a
        return out

    names = [setup.names[k] for k in k_un]
    cal.assumptions.append(
        f"camera(s) {', '.join(names)}: no identity has landmarks in them; placed by the nominal table carried "
        f"by the similarity of the calibrated cameras' {how} (x{sa:.4f}, residual "
        f"{np.sqrt(np.mean(res ** 2)):.1f} mm / {math.degrees(np.sqrt(np.mean(res_rot ** 2))):.2f} deg RMS): nominal "
        "prior only, not measured (fit-geometry refines each view by its images)")
    cal.report["camera_placed_by"] = {n: ("nominal prior only" if k in k_un else "landmarks")
                                      for k, n in enumerate(setup.names)}
    cal.report["cameras_nominal_only"] = names
    rmse = np.full((N, C), np.nan)
    rmse[:, k_seen] = cal.landmark_rmse_px
    outl = np.zeros((N, C, 68), dtype=bool)
    outl[:, k_seen] = cal.outliers
    cal.camera_names, cal.R, cal.centers, cal.focal = list(setup.names), R, centers, focal
    cal.image_size = setup.image_size
    cal.center_sigma_mm = widen(cal.center_sigma_mm, np.nan)
    cal.rotation_sigma_deg = widen(cal.rotation_sigma_deg, np.nan)
    cal.focal_sigma_px = widen(cal.focal_sigma_px, np.nan)
    cal.landmark_rmse_px, cal.outliers = rmse, outl
    for i, cam in enumerate(cal.flash_camera):  # their flashes ride on the carried cameras
        if cam in names:
            k, nom = setup.names.index(cam), cal.nominal.camera(cam)
            off = nom.R @ (np.asarray(cal.nominal.flash(cal.flash_ids[i]).position, np.float64) - nom.center)
            cal.flash_pos[i] = centers[k] + R[k].T @ off
            cal.flash_offset[i] = off
    return cal


def calibrate_rig(model: ShapeModel, landmarks: np.ndarray, camera_names: Sequence[str], image_size,
                  nominal: Rig, config: CalibrationConfig | None = None, identities: Sequence[str] | None = None,
                  flash_ids: Sequence[str] | None = None, progress_fn=None) -> RigCalibration:
    """Bundle-adjust one rig to the landmarks of every identity (:func:`_setup`, :func:`_calibrate_seen`).

    Args:
        model: the face model (its landmark vertices, shape / expression bases and σ).
        landmarks: (N, C, 68, 2) float, full-frame pixels (pixel centres at integers), NaN where missing.
        camera_names: (C,) the views, names of cameras of ``nominal``.
        image_size: (W, H) or (C, 2) per camera; must equal the nominal table's size (refused otherwise).
        nominal: the nominal rig (angles + rough distance + focal; the packaged table or the user's).
        config: :class:`CalibrationConfig`; identities: (N,) ids for the report; flash_ids: flashes to place
            (default: every flash of the nominal table).
    Returns:
        :class:`RigCalibration`.

    A camera that no identity annotates (no detector finds a face in it) keeps the nominal table's pose, carried
    by the similarity of the calibrated cameras (``config.carry``, :func:`_add_unseen`); ``camera_placed_by`` says
    which cameras were measured.  Needs at least 3 cameras with landmarks then.
    """
    cfg = config or CalibrationConfig()
    setup = _setup(model, landmarks, camera_names, image_size, nominal, cfg, identities)
    seen = _annotated(setup.lm)
    if seen.all():
        cal = _calibrate_seen(model, setup, nominal, cfg, flash_ids, progress_fn)
        cal.report["camera_placed_by"] = {n: "landmarks" for n in setup.names}
        cal.report["cameras_nominal_only"] = []
        return cal
    cal = _calibrate_seen(model, _subset(setup, seen), nominal, cfg, flash_ids, progress_fn)
    cal = _add_unseen(cal, setup, seen, cfg)
    log.warning("calibrate-rig: no landmarks for camera(s) %s in any identity: kept at the nominal table's pose "
                "(nominal prior only)", ", ".join(cal.report["cameras_nominal_only"]))
    return cal


def _calibrate_seen(model: ShapeModel, setup: _RigSetup, nominal: Rig, cfg: CalibrationConfig,
                    flash_ids: Sequence[str] | None, progress_fn) -> RigCalibration:
    """:func:`calibrate_rig` on cameras that all have landmarks.

    Steps: :func:`_initial_state` → :func:`_levenberg_marquardt` → :func:`_scale_anchor` → :func:`_reframe` →
    :func:`_residuals` → :func:`_uncertainty` → :func:`_place_flashes` → :func:`_calibration_report`.
    """
    t_start = time.perf_counter()
    prob = _Problem(model, setup.lm, setup.R0, setup.c0, setup.f0, setup.pp, cfg, setup.Ks, setup.Ke)
    opts = LMOptions.from_config(cfg)
    lmr = _levenberg_marquardt(prob, _initial_state(prob, setup.R0, setup.c0), opts, progress_fn)
    st = lmr.state
    anchor, note = _scale_anchor(model, prob, st, setup, cfg)
    if note is not None:
        st.c = st.c * anchor
        st.th = st.th * anchor
        setup.assumptions.append(note)
    _reframe(st)
    setup.assumptions.append("rig frame: origin at the identities' mean head position, axes along their mean head "
                             "orientation (the rig table convention: the head at the origin)")
    res = _residuals(prob, st, setup.lm, cfg)
    unc = _uncertainty(prob, st, res, opts.loss_scale)
    flashes, flash_notes = _place_flashes(nominal, flash_ids, setup, st, unc.center_mm)
    setup.assumptions.extend(flash_notes)
    if anchor != 1.0:  # the anchored faces are the fitted ones scaled about the head origin
        setup.assumptions.append(f"shape coefficients are those of the unscaled optimum (faces x{anchor:.4f})")
    shape_coeffs, exp_coeffs = _model_coeffs(model, st, setup.Ks, setup.Ke)
    report = _calibration_report(prob, st, setup, res, unc, lmr, anchor, t_start)
    return RigCalibration(
        camera_names=setup.names, R=st.R, centers=st.c, focal=prob.focal(st), image_size=setup.image_size,
        center_sigma_mm=unc.center_mm, focal_sigma_px=unc.focal_px, rotation_sigma_deg=unc.rotation_deg,
        flash_ids=flashes.ids, flash_pos=flashes.pos, flash_camera=flashes.camera, flash_offset=flashes.offset,
        flash_intensity=flashes.intensity, flash_sigma_mm=flashes.sigma_mm, identities=setup.ids, head_R=st.Rh,
        head_t=st.th, shape_coeffs=shape_coeffs, exp_coeffs=exp_coeffs, landmark_rmse_px=res.rmse,
        outliers=res.outliers, nominal=nominal, assumptions=setup.assumptions, report=report)


# --------------------------------------------------------------------------- artifact

def rig_calibration_arrays(cal: RigCalibration) -> dict[str, np.ndarray]:
    """The arrays of the ``rig`` artifact (docs/artifacts.md)."""
    nom = cal.nominal
    return {
        "camera_names": np.array(cal.camera_names, dtype=str), "K": cal.K, "R": cal.R, "t": cal.t,
        "centers": cal.centers, "focal_px": cal.focal, "image_size": cal.image_size.astype(np.int32),
        "center_sigma_mm": cal.center_sigma_mm, "rotation_sigma_deg": cal.rotation_sigma_deg,
        "focal_sigma_px": cal.focal_sigma_px,
        "nominal_centers": np.array([nom.camera(n).center for n in cal.camera_names]),
        "nominal_focal_px": np.array([nom.camera(n).focal_px for n in cal.camera_names]),
        "flash_ids": np.array(cal.flash_ids, dtype=str), "flash_pos": cal.flash_pos,
        "flash_camera": np.array(cal.flash_camera, dtype=str), "flash_offset_cam": cal.flash_offset,
        "flash_intensity": cal.flash_intensity, "flash_sigma_mm": cal.flash_sigma_mm,
        "identities": np.array(cal.identities, dtype=str), "head_R": cal.head_R, "head_t": cal.head_t,
        "shape_coeffs": cal.shape_coeffs, "exp_coeffs": cal.exp_coeffs,
        "landmark_rmse_px": cal.landmark_rmse_px, "outliers": cal.outliers,
    }


def write_rig_calibration(cal: RigCalibration, path: str | Path, *, toml_path: str | Path | None = None,
                          **artifact_kw: Any) -> list[Path]:
    """Write the ``rig`` NPZ artifact and beside it the rig TOML (default: same stem, ``.toml``).

    ``artifact_kw`` is passed to :func:`reflectmm_cli.artifacts.write_artifact` (params, inputs, producer,
    cache_key).  The TOML loads with :func:`reflectmm_cli.rig.load_rig` and is what ``fit-geometry --rig`` reads.
    """
    from reflectmm_cli.artifacts import write_artifact
    from reflectmm_cli.rig import save_rig

    path = Path(path)
    tpath = Path(toml_path) if toml_path is not None else path.with_suffix(".toml")
    extra = dict(artifact_kw.pop("extra_meta", {}) or {})
    extra.update({"assumptions": cal.assumptions, "report": cal.report, "toml": tpath.name})
    out = write_artifact(path, RIG_KIND, rig_calibration_arrays(cal), extra_meta=extra, **artifact_kw)
    sig = np.linalg.norm(cal.center_sigma_mm, axis=1)
    from reflectmm_cli.workspace import CALIBRATED_RIG_HEADER

    header = (f"{CALIBRATED_RIG_HEADER} from the landmarks of "
              f"{len(cal.identities)} identities x {len(cal.camera_names)} views.\n"
              f"Landmark RMS {cal.report.get('landmark_rmse_px_median', float('nan')):.2f} px (median); "
              f"camera centre 1-sigma {np.nanmedian(sig):.1f} mm (median, rigid gauge removed).\n"
              "Assumed: " + "; ".join(cal.assumptions))
    save_rig(cal.to_rig(), tpath, header=header)
    return [out, tpath]


def read_rig_calibration(path: str | Path):
    """Read a ``rig`` artifact (an :class:`reflectmm_cli.artifacts.Artifact`)."""
    from reflectmm_cli.artifacts import read_artifact

    return read_artifact(path, RIG_KIND)


# --------------------------------------------------------------------------- synthetic data

def perturb_rig(rig: Rig, *, distance_scale: float = 1.0, angle_deg: float = 0.0, raised_offset_mm: float = 0.0,
                focal_scale: float = 1.0, seed: int = 0, raised_aim: str = "kept") -> Rig:
    """A deliberately wrong copy of ``rig``: every camera's distance scaled, its position turned about the head by
    ≈ ``angle_deg`` (random axis) and its aim turned by as much, the raised cameras moved by ``raised_offset_mm``
    (random direction), every focal scaled.  Attached flashes move with their camera.

    ``raised_aim``: a moved raised camera keeps its true aim direction (``"kept"``: it may look past the head) or
    looks at its true look-at point from its wrong place (``"head"``: a table written with a wrong position but
    aimed at the subject), before the aim error."""
    if raised_aim not in ("kept", "head"):
        raise ReflectmmError(f"perturb_rig: raised_aim must be 'kept' or 'head', not {raised_aim!r}")
    rng = np.random.default_rng(seed)
    cams = []
    for cam in rig.cameras:
        w = rng.normal(size=3)
        w *= math.radians(angle_deg) / max(np.linalg.norm(w), 1e-12)
        pos = rodrigues(w) @ cam.position * distance_scale
        if cam.name in RAISED_CAMERAS and raised_offset_mm > 0:
            d = rng.normal(size=3)
            pos = pos + raised_offset_mm * d / np.linalg.norm(d)
        w2 = rng.normal(size=3)
        w2 *= math.radians(angle_deg) / max(np.linalg.norm(w2), 1e-12)
        moved = cam.name in RAISED_CAMERAS and raised_offset_mm > 0 and raised_aim == "head"
        aim = rodrigues(w2) @ (np.asarray(cam.look_at) - (pos if moved else cam.position))
        cams.append(RigCamera(cam.name, pos, pos + aim, cam.up.copy(), cam.focal_px * focal_scale, cam.width,
                              cam.height))
    fls = []
    for fl in rig.flashes:
        if fl.camera is not None:
            fls.append(RigFlash(fl.id, [c for c in cams if c.name == fl.camera][0].position.copy(), fl.intensity,
                                fl.camera))
        else:
            fls.append(RigFlash(fl.id, np.asarray(fl.position, np.float64).copy(), fl.intensity, None))
    return Rig(cams, fls, rig.source)


def simulate_landmarks(model: ShapeModel, rig: Rig, camera_names: Sequence[str], n_identities: int, *, seed: int = 0,
                       noise_px: float = 1.0, head_rotation_deg: float = 5.0, head_shift_mm: float = 20.0,
                       expression: float = 0.5, outlier_fraction: float = 0.0, outlier_px: float = 40.0
                       ) -> dict[str, np.ndarray]:
    """Landmarks of random identities seen by ``rig`` (the synth code's projection, no rendering).

    Returns dict: ``landmarks`` (N, C, 68, 2) px; ``shape`` (N, Ks), ``exp`` (N, Ke) model coefficients;
    ``head_R`` (N,3,3), ``head_t`` (N,3) model → rig; ``outlier`` (N, C, 68) bool (landmarks displaced by
    ``outlier_px`` in a random direction).
    """
    rng = np.random.default_rng(seed)
    names = list(camera_names)
    N, C = int(n_identities), len(names)
    zs = np.clip(rng.normal(size=(N, model.n_shape)), -3, 3)
    ze = np.clip(rng.normal(size=(N, model.n_exp)), -3, 3) * expression
    w = rng.normal(size=(N, 3))
    w *= math.radians(head_rotation_deg) / np.maximum(np.linalg.norm(w, axis=1, keepdims=True), 1e-12) \
        * rng.uniform(0, 1, size=(N, 1))
    Rh = rodrigues(w)
    th = rng.normal(size=(N, 3)) * head_shift_mm / math.sqrt(3)
    out = np.zeros((N, C, 68, 2))
    lm_ids = model.landmarks
    for i in range(N):
        X = model.vertices(zs[i] * model.shape_sigma, ze[i] * model.exp_sigma)[lm_ids] @ Rh[i].T + th[i]
        for k, n in enumerate(names):
            out[i, k] = rig.camera(n).project(X)
    out += rng.normal(size=out.shape) * noise_px
    outl = rng.uniform(size=(N, C, 68)) < outlier_fraction
    ang = rng.uniform(0, 2 * math.pi, size=(N, C, 68))
    out += outl[..., None] * outlier_px * np.stack([np.cos(ang), np.sin(ang)], -1)
    return {"landmarks": out, "shape": zs * model.shape_sigma, "exp": ze * model.exp_sigma, "head_R": Rh,
            "head_t": th, "outlier": outl}


def align_to(cal_centers: np.ndarray, true_centers: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Rigid (no scale) alignment of fitted camera centres to true ones: returns (R, t, residual mm (C,))
    (:func:`reflectmm_cli.geometry_fit.init.rigid_align`, i.e. :func:`reflectmm_cli.geometry.align.rigid_align`
    plus the residuals)."""
    return rigid_align(cal_centers, true_centers)


# --------------------------------------------------------------------------- from capture artifacts

def landmarks_from_captures(capture_paths: Sequence[str | Path], views: Sequence[str] | None = None,
                            purpose: str = "the calibration") -> tuple[np.ndarray, list[str], list[str], np.ndarray]:
    """Stack the landmarks of ``capture`` artifacts (preprocess-multipie outputs) of several identities.

    ``purpose`` names what they are for in the refusals (an identity given twice, one without landmarks).

    Returns (landmarks (N, C, 68, 2) full-frame px with NaN where an identity lacks a view, identities (N,),
    camera names (C,) — the union of the captures' views in first-seen order, or ``views`` —, image size (C, 2)).
    Captures whose frame sizes differ for the same camera are refused.
    """
    from reflectmm_cli.artifacts import read_artifact
    from reflectmm_cli.landmarks import check_view_landmarks

    per: list[tuple[str, list[str], np.ndarray]] = []
    first_path: dict[str, str | Path] = {}
    names: list[str] = [] if views is None else list(views)
    size: dict[str, tuple[int, int]] = {}
    for p in capture_paths:
        art = read_artifact(p, "capture", members=("view_names", "landmarks", "image_size"))  # not the images
        vn = [str(v) for v in np.asarray(art["view_names"]).reshape(-1)]
        if "landmarks" not in art.arrays:
            raise ReflectmmError("capture has no landmarks (preprocess-multipie needs the landmark files)", p)
        lm = np.asarray(art["landmarks"], np.float64)
        if lm.shape != (len(vn), 68, 2):
            raise ReflectmmError(f"capture landmarks have shape {lm.shape}, expected ({len(vn)}, 68, 2)", p)
        W, H = (int(x) for x in np.asarray(art["image_size"]).reshape(-1)[:2])
        for v in vn:
            if v in size and size[v] != (W, H):
                raise ReflectmmError(f"camera {v} is {W}x{H} here but {size[v][0]}x{size[v][1]} in another capture", p)
            size[v] = (W, H)
            if views is None and v not in names:
                names.append(v)
        rep = art.meta.get("report", {}) if isinstance(art.meta.get("report"), dict) else {}
        ident = str(rep.get("identity") or art.meta.get("params", {}).get("id") or Path(p).stem)
        if ident in first_path:
            raise ReflectmmError(f"identity {ident} is given twice (also {first_path[ident]}): each identity counts "
                                 f"once in {purpose}", p)
        first_path[ident] = p
        used = [k for k, v in enumerate(vn) if views is None or v in names]
        if not any([check_view_landmarks(lm[k], vn[k], W, H, p) for k in used]):  # every view checked
            among = f" of {', '.join(names)}" if views else ""
            raise ReflectmmError(f"identity {ident} has no landmarks in any view{among}: it cannot take part in "
                                 f"{purpose}; leave it out", p)
        per.append((ident, vn, lm))
    if not per:
        raise ReflectmmError("calibrate-rig: no capture artifacts given")
    out = np.full((len(per), len(names), 68, 2), np.nan)
    for i, (_, vn, lm) in enumerate(per):
        for k, v in enumerate(vn):
            if v in names:
                out[i, names.index(v)] = lm[k]
    missing = [v for v in names if v not in size]
    if missing:
        raise ReflectmmError(f"calibrate-rig: no capture has view(s) {', '.join(missing)}")
    return out, [p[0] for p in per], names, np.array([size[v] for v in names], np.int64)


def calibrate_from_captures(capture_paths: Sequence[str | Path], face_model_path: str | Path,
                            nominal_rig: str | Path | Rig | None = None, config: CalibrationConfig | None = None,
                            views: Sequence[str] | None = None, progress_fn=None) -> RigCalibration:
    """:func:`calibrate_rig` on the landmarks of capture artifacts (one per identity) with a face model file and a
    nominal rig table (None: the packaged Multi-PIE table, whose image size must then match the captures)."""
    from reflectmm_cli.geometry import load_face_model
    from reflectmm_cli.geometry_fit.embedding import correct_by_face_model
    from reflectmm_cli.rig import load_rig

    lm, ids, names, size = landmarks_from_captures(capture_paths, views)
    fm = load_face_model(face_model_path)
    lm, note = correct_by_face_model(lm, names, fm.info, face_model_path)
    if note:
        log.info("calibrate-rig: %s", note)
    model = ShapeModel.from_face_model(fm)
    nominal = nominal_rig if isinstance(nominal_rig, Rig) else load_rig(nominal_rig)
    cal = calibrate_rig(model, lm, names, size, nominal, config, identities=ids, progress_fn=progress_fn)
    if note:
        cal.assumptions.append(note)
    if nominal_rig is None:
        cal.assumptions.insert(0, "nominal rig: the packaged Multi-PIE table (no rig table given)")
    return cal
