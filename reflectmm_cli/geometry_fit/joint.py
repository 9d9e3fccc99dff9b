"""Joint registration of the cameras no identity annotates: one pose per camera, shared by every identity.

A camera without landmarks in any identity starts at the nominal table's pose carried into the calibrated rig
(:func:`.calibrate._add_unseen`).  Its place is then measured by the flash images of *all* identities at once:
each identity's face (shape, expression) and head pose are held at its preliminary fit from its landmarked views
(``fit-geometry`` run on the calibrated rig), and the camera's pose in the rig frame is the one unknown that every
identity shares.  In identity ``i`` (head ``x_model = R_h,i x_rig + t_h,i``) camera ``k`` with rig pose
``(R_k, c_k)`` sits at ``R = R_k R_h,iᵀ``, centre ``R_h,i c_k + t_h,i``; its own flash rides on its centre and
lights the other views too.

Objective (θ: per camera a turn ω (rad) and a centre shift δc (mm) from the starting pose)::

    J(θ) = Σ_i w_flash · L_i(θ) + (½ Σ_k ‖δc_k‖² / σ_c² + ¼ ‖R_k(θ) − R_k,0‖²_F / σ_r²) / w̄

with ``L_i`` exactly the flash term ``fit-geometry`` registers one identity's views with
(:func:`.fit._flash_objective`: point-light Lambertian residual, albedo eliminated per vertex, visibility and
highlight masks fixed per round), ``σ_c`` / ``σ_r`` the prior of a view without landmarks (``fit-geometry``'s
``unmarked_sigma_mm`` / ``unmarked_rot_sigma_deg``, 100 mm / 2° by default) and ``w̄`` the identities' mean
landmark weight sum (the per-identity objective divides its priors by it).  Each camera starts at the best
(lowest J, camera by camera) of its nominal pose and the poses the identities' own registrations gave it (the
objective is not convex), then L-BFGS, coarse to fine over blurred images.  A camera whose summed flash
residual does not fall, or that moves more than 3 σ_c, goes back to its start ("nominal").  Its uncertainty is
the Laplace approximation of J in its six pose parameters, the other cameras held (the curvature of the image
term cut to its positive semi-definite part, as in :mod:`.placement`).
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Sequence

import numpy as np
import torch

from reflectmm_cli.artifacts import read_artifact
from reflectmm_cli.errors import ReflectmmError
from reflectmm_cli.geometry.camera import axis_angle_to_matrix, matrix_to_axis_angle
from reflectmm_cli.geometry_fit.fit import (FitConfig, ViewSet, _FitProblem, _FlashPairs, _flash_objective,
                                            _sub_mesh, _SubMesh, _usable_flashes, _view_flash_rms, lbfgs_minimise,
                                            pose_under_head)
from reflectmm_cli.geometry_fit.init import place_by_rig
from reflectmm_cli.geometry_fit.placement import data_cut_psd
from reflectmm_cli.geometry_fit.model import ShapeModel

log = logging.getLogger("reflectmm")

__all__ = ["JointOptions", "JointResult", "HeldIdentity", "held_identity", "hold", "register_calibration",
           "check_pairs", "register_jointly", "joint_objective"]


@dataclass(frozen=True)
class JointOptions:
    """Prior and schedule of :func:`register_jointly`.

    center_sigma_mm / rot_sigma_deg: the starting (nominal) pose's prior σ (fit-geometry's defaults for a view
    without landmarks); blur_px: one L-BFGS round per Gaussian blur (px) of the flash images; iters: L-BFGS
    iterations per round; unit_mm: the optimiser's parameter unit (a centre shift of this many mm, or a turn
    moving the face by as much); w_flash: weight of the flash term (fit-geometry's)."""

    center_sigma_mm: float = 100.0
    rot_sigma_deg: float = 2.0
    blur_px: tuple[float, ...] = (4.0, 2.0, 0.0)
    iters: int = 40
    unit_mm: float = 10.0
    w_flash: float = FitConfig.w_flash

    def __post_init__(self) -> None:
        for name in ("center_sigma_mm", "rot_sigma_deg", "unit_mm", "w_flash"):
            v = float(getattr(self, name))
            if not (math.isfinite(v) and v > 0):
                raise ReflectmmError(f"joint registration: {name} must be a finite number > 0, got {v}")


@dataclass
class HeldIdentity:
    """One identity held at its preliminary fit: its fit problem (face and head fixed), photometric sub-mesh,
    flash pairs and their images (P, h, w, 3), saturation masks or None, head (Rh (3, 3), th (3,)) and the index
    of each registered camera among its views (−1: it has no such view)."""

    name: str
    prob: _FitProblem
    sm: _SubMesh
    fp: _FlashPairs
    raw: np.ndarray
    sat: np.ndarray | None
    Rh: np.ndarray
    th: np.ndarray
    view_of: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))
    own_R: np.ndarray | None = None  # (Cu, 3, 3) / (Cu, 3): the identity's own registration of each camera in the
    own_c: np.ndarray | None = None  # rig frame (NaN where it has none): candidate starts of the joint search


@dataclass
class JointResult:
    """Output of :func:`register_jointly`, per registered camera (Cu,): names; rig-frame pose R (Cu, 3, 3),
    centres (Cu, 3) (the start where rejected); ``accepted``; RMS flash residual over the identities before and
    after; centre σ (Cu, 3) mm and orientation σ (Cu,) deg (NaN where rejected); shift from the start (mm);
    number of identities that see the camera; the L-BFGS history."""

    names: list[str]
    R: np.ndarray
    centers: np.ndarray
    accepted: np.ndarray
    residual_before: np.ndarray
    residual_after: np.ndarray
    center_sigma_mm: np.ndarray
    rotation_sigma_deg: np.ndarray
    shift_mm: np.ndarray
    identities: np.ndarray
    history: list[dict] = field(default_factory=list)


def held_identity(model: ShapeModel, capture_path: str | Path, geometry_path: str | Path, rig,
                  cameras: Sequence[str], config: FitConfig | None = None) -> HeldIdentity:
    """Read one identity's capture and preliminary ``geometry`` (fitted on ``rig``) and hold it: coefficients
    from the geometry, head from its views with landmarks (:func:`.init.place_by_rig`), flash images from the
    capture; ``cameras`` are the cameras to register (their views are those without landmarks)."""
    from reflectmm_cli.geometry_fit.identity import _flash_inputs

    cap = read_artifact(capture_path, "capture")
    geo = read_artifact(geometry_path, "geometry")
    names = [str(v) for v in np.asarray(geo["view_names"]).reshape(-1)]
    if names != [str(v) for v in np.asarray(cap["view_names"]).reshape(-1)]:
        raise ReflectmmError(f"the views of {Path(geometry_path).name} differ from the capture's", capture_path)
    evidence = [str(e) for e in np.asarray(geo["view_evidence"]).reshape(-1)] if "view_evidence" in geo.arrays \
        else ["landmarks"] * len(names)
    marked = np.array([e.startswith("landmarks") for e in evidence])
    lm = np.asarray(geo["landmarks_given"], np.float64).copy()
    lm[~marked] = np.nan
    R_rig = np.array([rig.camera(n).R for n in names])
    t_rig = np.array([rig.camera(n).t for n in names])
    R, t = np.asarray(geo["R"], np.float64), np.asarray(geo["t"], np.float64)
    _, _, Rh, th = place_by_rig(R, t, marked, R_rig, t_rig)
    room = np.asarray(cap["room"], dtype=np.float32)
    W, H = (int(x) for x in np.asarray(cap["image_size"]).reshape(-1)[:2])
    flash_ids = [str(f) for f in np.asarray(cap["flash_ids"]).reshape(-1)]
    kw = _flash_inputs(cap, Path(capture_path), rig, names, flash_ids, room.shape[1:3], None)
    views = ViewSet(names=names, K=np.asarray(geo["K"], np.float64), R0=R, t0=t, landmarks=lm, image_size=(W, H),
                    images=room, rig_centers=np.array([rig.camera(n).center for n in names]),
                    image_origin=np.asarray(cap.arrays.get("crop_origin", np.zeros((len(names), 2))), np.float64),
                    rig_R=R_rig, **kw)
    ident = str(geo.meta.get("report", {}).get("identity") or Path(geometry_path).stem)
    held = hold(model, views, np.asarray(geo["shape_coeffs"], np.float64), np.asarray(geo["exp_coeffs"], np.float64),
                cameras, name=ident, head=(Rh, th), config=config, source=capture_path)
    held.own_R, held.own_c = np.full((len(cameras), 3, 3), np.nan), np.full((len(cameras), 3), np.nan)
    for k, v in enumerate(held.view_of):  # a view fit-geometry registered by the flash images ("rig+flash")
        if v >= 0 and "flash" in evidence[v]:
            held.own_R[k] = R[v] @ Rh
            held.own_c[k] = Rh.T @ (-R[v].T @ t[v] - th)
    return held


def hold(model: ShapeModel, views: ViewSet, shape_coeffs: np.ndarray, exp_coeffs: np.ndarray,
         cameras: Sequence[str], *, name: str = "", head: tuple[np.ndarray, np.ndarray] | None = None,
         config: FitConfig | None = None, source: str | Path | None = None) -> HeldIdentity:
    """An identity held at a fit: ``views`` (its views without landmarks are those whose landmarks are all NaN;
    needs flash images, rig centres and orientations), the model coefficients (n_shape,), (n_exp,), the head
    (rig → model: Rh (3, 3), th (3,); default :func:`.init.place_by_rig` from the views with landmarks) and the
    cameras ``cameras`` to register (Cu,)."""
    if views.flash_images is None:
        raise ReflectmmError(f"identity {name}: no flash images: the joint registration needs them", source)
    marked = np.isfinite(views.landmarks).all(-1).any(-1)
    if head is None:
        _, _, Rh, th = place_by_rig(views.R0, views.t0, marked, views.rig_R,
                                    -np.einsum("vij,vj->vi", views.rig_R, views.rig_centers))
    else:
        Rh, th = (np.asarray(a, np.float64) for a in head)
    prob = _FitProblem(model, views, config or FitConfig(flash_rounds=1), "cpu")
    with torch.no_grad():
        prob.zs.copy_(prob.tt(np.asarray(shape_coeffs, np.float64) / model.shape_sigma))
        if prob.ze.numel():
            prob.ze.copy_(prob.tt(np.asarray(exp_coeffs, np.float64)[:prob.ze.numel()]
                                  / model.exp_sigma[:prob.ze.numel()]))
    prob.Rh0_t, prob.th0_t = prob.tt(Rh), prob.tt(th)  # the head of the landmarked views; dwh = dth = 0
    sm = _sub_mesh(prob)
    usable = _usable_flashes(prob, on_unmarked_too=True)
    usable = usable[views.flash_view[usable] >= 0]  # flashes on the fitted views: the others are the table's guess
    if len(usable) == 0:
        raise ReflectmmError(f"identity {name}: no flash sits on a camera of its views: the joint registration has "
                             "no flash evidence", source)
    fp = _FlashPairs(prob, usable)
    raw, sat = fp.images()
    names = list(views.names)
    view_of = np.array([names.index(c) if c in names and not marked[names.index(c)] else -1 for c in cameras],
                       dtype=np.int64)
    return HeldIdentity(name, prob, sm, fp, raw, sat, Rh, th, view_of)


class _Shared:
    """The shared unknowns θ (Cu, 6) (turn, shift; in ``unit_mm``) around the starting rig poses R0 (Cu, 3, 3),
    c0 (Cu, 3), and the pose function that puts them into each identity's model space."""

    def __init__(self, R0: np.ndarray, c0: np.ndarray, opts: JointOptions):
        self.R0 = torch.as_tensor(R0, dtype=torch.float64)
        self.c0 = torch.as_tensor(c0, dtype=torch.float64)
        self.dist = torch.linalg.norm(self.c0, dim=-1).clamp_min(1.0)[:, None]
        self.opts = opts
        self.theta = torch.zeros(len(R0), 6, dtype=torch.float64, requires_grad=True)

    def rig_pose(self):
        """(R (Cu, 3, 3) world → camera, centres (Cu, 3)) in the rig frame at the current θ."""
        u = self.opts.unit_mm
        return axis_angle_to_matrix(self.theta[:, :3] * u / self.dist) @ self.R0, self.c0 + self.theta[:, 3:] * u

    def theta_of(self, k: int, R: np.ndarray, c: np.ndarray) -> np.ndarray:
        """(6,) θ of camera ``k`` that puts it at the rig pose R (3, 3), c (3,) (the inverse of :meth:`rig_pose`)."""
        u, dist = self.opts.unit_mm, float(self.dist[k, 0])
        w = matrix_to_axis_angle(np.asarray(R, np.float64) @ self.R0[k].numpy().T)
        return np.concatenate([w * dist / u, (np.asarray(c, np.float64) - self.c0[k].numpy()) / u])

    def prior(self) -> torch.Tensor:
        """½ Σ ‖δc‖²/σ_c² + ¼ Σ ‖R − R0‖²_F/σ_r² (≈ ½ θ²/σ_r² for a turn θ)."""
        R, c = self.rig_pose()
        return (0.5 * ((c - self.c0) ** 2).sum() / self.opts.center_sigma_mm ** 2
                + 0.25 * ((R - self.R0) ** 2).sum() / math.radians(self.opts.rot_sigma_deg) ** 2)

    def attach(self, ident: HeldIdentity) -> None:
        """Make ``ident.prob.poses()`` put the shared cameras at their rig pose moved by the identity's head."""
        rows = np.nonzero(ident.view_of >= 0)[0]
        idx = torch.as_tensor(ident.view_of[rows], dtype=torch.long)
        rows_t = torch.as_tensor(rows, dtype=torch.long)
        Rh, th = ident.prob.tt(ident.Rh), ident.prob.tt(ident.th)

        def pose_fn(R, t):
            if len(rows) == 0:
                return R, t
            Rk, ck = self.rig_pose()
            Rv, tv = pose_under_head(Rk[rows_t], ck[rows_t], Rh, th)
            R, t = R.clone(), t.clone()
            R[idx] = Rv
            t[idx] = tv
            return R, t

        ident.prob.pose_fn = pose_fn


def joint_objective(idents: Sequence[HeldIdentity], shared: _Shared, blur: float, w_flash: float):
    """The summed objective of one round: a closure J() (scalar tensor) over the identities' flash terms at
    ``blur`` (visibility fixed at the current θ) plus the shared prior over the mean landmark weight sum, and the
    per-identity closures L_i() (the flash loss alone, for tests and reports)."""
    wbar = float(np.mean([d.prob.wsum for d in idents]))
    terms = []
    for d in idents:
        flash, images_t, _ = _flash_objective(d.prob, d.sm, d.fp, d.raw, blur, d.sat)
        terms.append(lambda flash=flash, images_t=images_t: flash(images_t, residual=False)[0][0])

    def total():
        return w_flash * sum(L() for L in terms) + shared.prior() / wbar

    return total, terms, wbar


def _camera_residuals(idents: Sequence[HeldIdentity], Cu: int) -> tuple[np.ndarray, np.ndarray]:
    """(Cu,) RMS over identities of each camera's flash residual (unblurred) and the number of identities seen."""
    acc, n = np.zeros(Cu), np.zeros(Cu, np.int64)
    for d in idents:
        r = _view_flash_rms(d.prob, d.sm, d.fp, d.raw, d.sat)
        for k, v in enumerate(d.view_of):
            if v >= 0 and np.isfinite(r[v]):
                acc[k] += r[v] ** 2
                n[k] += 1
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(n > 0, np.sqrt(acc / np.maximum(n, 1)), np.nan), n


def _curvature(total, shared: _Shared, wbar: float, h: float = 0.2) -> np.ndarray:
    """(Cu, 6, 6) curvature of ``total`` × w̄ in each camera's θ (the others held): central differences of the
    gradient (step ``h`` units), the image part cut to its positive semi-definite part, plus the prior's."""
    Cu = shared.theta.shape[0]
    base = shared.theta.detach().clone()

    def grads(fn, k):
        H = np.zeros((6, 6))
        for j in range(6):
            g = []
            for s in (1.0, -1.0):
                with torch.no_grad():
                    shared.theta.copy_(base)
                    shared.theta[k, j] += s * h
                (gr,) = torch.autograd.grad(fn(), shared.theta)
                g.append(gr[k].numpy())
            H[:, j] = (g[0] - g[1]) / (2 * h)
        return 0.5 * (H + H.T)

    out = np.zeros((Cu, 6, 6))
    try:
        for k in range(Cu):
            out[k] = data_cut_psd(grads(total, k), grads(lambda: shared.prior() / wbar, k)) * wbar
    finally:
        with torch.no_grad():
            shared.theta.copy_(base)
    return out


def _sigmas(H: np.ndarray, shared: _Shared) -> tuple[np.ndarray, np.ndarray]:
    """Centre σ (Cu, 3) mm and orientation σ (Cu,) deg (largest axis) from the θ curvatures (Cu, 6, 6)."""
    u, dist = shared.opts.unit_mm, shared.dist.numpy()[:, 0]
    cs, rs = np.full((len(H), 3), np.nan), np.full(len(H), np.nan)
    for k in range(len(H)):
        w = np.linalg.eigvalsh(H[k])
        if w.min() <= 1e-12 * max(abs(w).max(), 1e-300):
            continue
        cov = np.linalg.inv(H[k])
        cs[k] = np.sqrt(np.clip(np.diag(cov)[3:], 0, None)) * u
        rs[k] = math.degrees(math.sqrt(max(np.linalg.eigvalsh(cov[:3, :3]).max(), 0.0)) * u / dist[k])
    return cs, rs


def _best_start(idents: Sequence[HeldIdentity], shared: _Shared, opts: JointOptions) -> dict:
    """Set θ to the best start, camera by camera: the nominal pose or one of the identities' own registrations
    (``own_R`` / ``own_c``), whichever gives the lowest summed objective (unblurred) with the other cameras at their
    choice so far.  The objective is not convex and each identity's registration already found a basin of its own
    term.  Returns the history entry (which start each camera took)."""
    cands = [d for d in idents if d.own_R is not None]
    chosen = ["nominal"] * shared.theta.shape[0]
    if not cands:
        return {"start": chosen}

    def value(th):
        with torch.no_grad():
            shared.theta.copy_(torch.as_tensor(th))
            return float(joint_objective(idents, shared, 0.0, opts.w_flash)[0]())

    theta = np.zeros(tuple(shared.theta.shape))
    best = value(theta)
    for k in range(len(theta)):
        for d in cands:
            if not np.isfinite(d.own_c[k]).all():
                continue
            trial = theta.copy()
            trial[k] = shared.theta_of(k, d.own_R[k], d.own_c[k])
            v = value(trial)
            if v < best:
                best, theta, chosen[k] = v, trial, f"identity {d.name}"
    with torch.no_grad():
        shared.theta.copy_(torch.as_tensor(theta))
    return {"start": chosen, "start_loss": best}


def register_jointly(idents: Sequence[HeldIdentity], names: Sequence[str], R0: np.ndarray, c0: np.ndarray,
                     opts: JointOptions | None = None) -> JointResult:
    """Register the cameras ``names`` (Cu,) from their starting rig poses R0 (Cu, 3, 3), c0 (Cu, 3) by the flash
    images of every identity in ``idents`` (built for these cameras by :func:`held_identity`).

    A camera that no identity sees with flash images keeps its start (not accepted, residual NaN)."""
    opts = opts or JointOptions()
    if not idents:
        raise ReflectmmError("joint camera registration needs at least one identity's preliminary fit")
    Cu = len(names)
    shared = _Shared(np.asarray(R0, np.float64), np.asarray(c0, np.float64), opts)
    for d in idents:
        shared.attach(d)
    before, seen = _camera_residuals(idents, Cu)
    history: list[dict] = [_best_start(idents, shared, opts)]
    total = wbar = None
    for rnd, blur in enumerate(opts.blur_px):
        total, _, wbar = joint_objective(idents, shared, blur, opts.w_flash)
        lbfgs_minimise([shared.theta], total, opts.iters)
        with torch.no_grad():
            history.append({"round": rnd + 1, "blur_px": blur, "loss": float(total())})
        log.debug("joint registration round %d (blur %g px): loss %.6g", rnd + 1, blur, history[-1]["loss"])
    after, _ = _camera_residuals(idents, Cu)
    with torch.no_grad():
        R, c = (a.numpy().copy() for a in shared.rig_pose())
    shift = np.linalg.norm(c - np.asarray(c0), axis=-1)
    with np.errstate(invalid="ignore"):
        ok = (seen > 0) & (after <= before) & (shift <= 3.0 * opts.center_sigma_mm)
    cs, rs = np.full((Cu, 3), np.nan), np.full(Cu, np.nan)
    if total is not None and ok.any():
        cs, rs = _sigmas(_curvature(total, shared, wbar), shared)
    R[~ok], c[~ok] = np.asarray(R0)[~ok], np.asarray(c0)[~ok]
    cs[~ok], rs[~ok] = np.nan, np.nan
    return JointResult(list(names), R, c, ok, before, np.where(ok, after, before), cs, rs,
                       np.where(ok, shift, 0.0), seen, history)


def check_pairs(capture_paths: Sequence, geometry_paths: Sequence) -> None:
    """Refuse a number of preliminary fits that differs from the number of captures (they pair by order)."""
    if len(capture_paths) != len(geometry_paths):
        raise ReflectmmError(f"joint camera registration: {len(geometry_paths)} geometry file(s) for "
                             f"{len(capture_paths)} capture(s): give one preliminary fit per identity")


def register_calibration(cal, model: ShapeModel, capture_paths: Sequence[str | Path],
                         geometry_paths: Sequence[str | Path], opts: JointOptions | None = None):
    """Register jointly the cameras of a :class:`.calibrate.RigCalibration` that no identity annotates
    (``report["cameras_nominal_only"]``), from each identity's capture and preliminary geometry (fitted on that
    calibration's rig; paired by order), and update ``cal`` in place: their pose, σ, attached flashes and the
    report's ``camera_placed_by`` (``flash-joint`` or ``nominal``) and ``camera_placement`` (per camera: evidence,
    residual, uncertainty).  Returns (cal, :class:`JointResult` or None when every camera has landmarks)."""
    opts = opts or JointOptions()
    check_pairs(capture_paths, geometry_paths)
    todo = list(cal.report.get("cameras_nominal_only", []))
    result = None
    if todo:
        rig = cal.to_rig()
        idents = [held_identity(model, c, g, rig, todo) for c, g in zip(capture_paths, geometry_paths)]
        k = [cal.camera_names.index(n) for n in todo]
        result = register_jointly(idents, todo, cal.R[k], cal.centers[k], opts)
        _update_calibration(cal, result, opts)
    cal.report["camera_placement"] = _placement(cal, result)
    return cal, result


def _update_calibration(cal, res: JointResult, opts: JointOptions) -> None:
    """Write the accepted joint poses (and their flashes) into ``cal`` and say which evidence placed each camera."""
    for j, name in enumerate(res.names):
        k = cal.camera_names.index(name)
        if not res.accepted[j]:
            log.warning("calibrate-rig: camera %s: the joint registration by the flash images was rejected (%s): "
                        "kept at the nominal pose", name, "no identity has a flash sample of it" if res.identities[j]
                        == 0 else "residual not lower, or moved more than 3 sigma")
            continue
        cal.R[k], cal.centers[k] = res.R[j], res.centers[j]
        cal.center_sigma_mm[k], cal.rotation_sigma_deg[k] = res.center_sigma_mm[j], res.rotation_sigma_deg[j]
        cal.report["camera_placed_by"][name] = "flash-joint"
        for i, cam in enumerate(cal.flash_camera):
            if cam == name:
                cal.flash_pos[i] = cal.centers[k] + cal.R[k].T @ cal.flash_offset[i]
                cal.flash_sigma_mm[i] = float(np.linalg.norm(res.center_sigma_mm[j]))
    cal.report["cameras_nominal_only"] = [n for j, n in enumerate(res.names) if not res.accepted[j]]
    cal.report["joint_registration"] = {
        "cameras": res.names, "accepted": [bool(a) for a in res.accepted],
        "identities": [int(n) for n in res.identities], "shift_mm": [round(float(s), 2) for s in res.shift_mm],
        "flash_rms_before": [None if not np.isfinite(x) else round(float(x), 5) for x in res.residual_before],
        "flash_rms_after": [None if not np.isfinite(x) else round(float(x), 5) for x in res.residual_after],
        "prior": {"center_sigma_mm": opts.center_sigma_mm, "rot_sigma_deg": opts.rot_sigma_deg},
        "history": res.history}
    cal.assumptions.append(
        "camera(s) " + ", ".join(res.names) + ": registered jointly over the identities by their flash images "
        f"(faces held at their preliminary fits; nominal pose prior {opts.center_sigma_mm:g} mm / "
        f"{opts.rot_sigma_deg:g} deg); accepted: " + (", ".join(n for n, a in zip(res.names, res.accepted) if a)
                                                       or "none"))


def _placement(cal, res: JointResult | None) -> list[dict]:
    """Per camera: the evidence that placed it (landmarks / nominal / flash-joint), its residual (median landmark
    RMS px, or the RMS flash residual over the identities) and its 1-σ centre (mm) and orientation (deg)."""
    out = []
    for k, name in enumerate(cal.camera_names):
        by = cal.report.get("camera_placed_by", {}).get(name, "landmarks")
        ev = {"landmarks": "landmarks", "flash-joint": "flash-joint"}.get(by, "nominal")
        row = {"camera": name, "evidence": ev, "residual": None, "residual_kind": None}
        if ev == "landmarks":
            r = cal.landmark_rmse_px[:, k]
            row["residual"], row["residual_kind"] = round(float(np.nanmedian(r)), 4), "landmark RMS px (median)"
        elif res is not None and name in res.names:
            x = res.residual_after[res.names.index(name)]
            row["residual"] = None if not np.isfinite(x) else round(float(x), 5)
            row["residual_kind"] = "flash RMS (linear), over identities"
        s = np.linalg.norm(cal.center_sigma_mm[k])
        row["center_sigma_mm"] = None if not np.isfinite(s) else round(float(s), 2)
        r = cal.rotation_sigma_deg[k]
        row["rotation_sigma_deg"] = None if not np.isfinite(r) else round(float(r), 4)
        out.append(row)
    return out
