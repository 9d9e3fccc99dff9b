"""Alignment of in-the-wild images to the Deep3DFaceRecon crop, single-image geometry and skin masks
(docs/wild.md).

Alignment (the convention of Deep3DFaceRecon's ``util/preprocess.py``, re-derived, not copied):

1. five points from the 68 (iBUG, 0-based): left eye centre = mean of the corners 36 and 39, right eye centre =
   mean of 42 and 45, nose tip 30, mouth corners 48 and 54 — in that order (:func:`five_points`);
2. an orthographic fit of the face model's mean 3D five points (mm, +y up) to them in y-up image coordinates:
   a 2×3 linear map + translation by least squares; ``s`` = mean norm of its two rows (pixels per mm) and
   ``t`` = where the mean shape's centroid lands (Deep3D re-centres its BFM on that centroid, so its origin is
   this point) (:func:`similarity_from_five_points`);
3. the image is scaled by ``k = rescale / s`` with ``rescale`` = 102 px per decimetre = 1.02 px/mm at S = 224
   (Deep3D's ``rescale_factor`` for its decimetre model; × S/224 for other sizes) and cropped to S×S so that
   ``t`` lands on the crop centre:
   ``x' = k (x − t_x) + c``, ``y' = k (y − t_y) + c`` in y-down pixel-centre coordinates, ``c = 112`` at
   S = 224 (scaled with S).  Deep3D rounds the resized size and crop corner to integers; this sub-pixel
   difference is not reproduced.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from reflectmm_cli.errors import ReflectmmError

__all__ = ["FIVE_POINT_NAMES", "five_points", "model_five_points", "model_centre", "similarity_from_five_points", "crop_transform",
           "warp_to_crop", "transform_points", "AlignResult", "align_image", "fit_single_image",
           "CELEBAMASK_SKIN_LABELS", "skin_mask_from_labels", "skin_mask_from_model", "mask_overlay"]

FIVE_POINT_NAMES = ("left_eye", "right_eye", "nose_tip", "mouth_left", "mouth_right")
RESCALE_PX_PER_MM = 1.02   # Deep3DFaceRecon: rescale_factor 102 for a model in decimetres


def five_points(lm68) -> np.ndarray:
    """(5, 2) from (68, 2): eye centres (mean of the two corners), nose tip, mouth corners (this order)."""
    lm = np.asarray(lm68, np.float64)
    if lm.shape != (68, 2):
        raise ReflectmmError(f"alignment needs 68 landmarks, got {lm.shape[0] if lm.ndim else 0}")
    return np.stack([(lm[36] + lm[39]) / 2, (lm[42] + lm[45]) / 2, lm[30], lm[48], lm[54]])


def model_five_points(face_model) -> np.ndarray:
    """(5, 3) the five points of the face model's mean shape (mm)."""
    return five_points_3d(face_model.mean_shape.astype(np.float64)[face_model.landmarks])


def model_centre(face_model) -> np.ndarray:
    """(3,) centroid of the mean shape: the point the crop is centred on (Deep3D re-centres its BFM so that
    its origin is this centroid)."""
    return face_model.mean_shape.astype(np.float64).mean(0)


def five_points_3d(lm3d) -> np.ndarray:
    lm = np.asarray(lm3d, np.float64)
    return np.stack([(lm[36] + lm[39]) / 2, (lm[42] + lm[45]) / 2, lm[30], lm[48], lm[54]])


def similarity_from_five_points(p2d, p3d, image_height: int, centre=None) -> tuple[np.ndarray, float]:
    """Orthographic fit ``[x, y_up] ≈ A·(X − centre) + b`` of 3D points (N,3) to image points (N,2, y down).

    Returns (t (2,) where ``centre`` (default the model origin) lands, in y-down pixels; s = mean row norm of A
    in pixels per model unit).
    """
    p = np.asarray(p2d, np.float64)
    X = np.asarray(p3d, np.float64) - (0.0 if centre is None else np.asarray(centre, np.float64))
    y_up = (image_height - 1) - p[:, 1]
    D = np.concatenate([X, np.ones((len(X), 1))], 1)
    cx, *_ = np.linalg.lstsq(D, p[:, 0], rcond=None)
    cy, *_ = np.linalg.lstsq(D, y_up, rcond=None)
    s = (np.linalg.norm(cx[:3]) + np.linalg.norm(cy[:3])) / 2
    if not np.isfinite(s) or s <= 0:
        raise ReflectmmError("alignment: degenerate five points")
    return np.array([cx[3], (image_height - 1) - cy[3]]), float(s)


def crop_transform(t, s, size: int = 224, rescale: float = RESCALE_PX_PER_MM) -> np.ndarray:
    """(2, 3) affine original pixels → crop pixels: ``k (x − t) + c`` with ``k = rescale / s``, ``c = size/2``."""
    k = rescale / float(s)
    c = size / 2.0
    return np.array([[k, 0.0, c - k * t[0]], [0.0, k, c - k * t[1]]])


def transform_points(A, pts) -> np.ndarray:
    p = np.asarray(pts, np.float64)
    return p @ np.asarray(A)[:, :2].T + np.asarray(A)[:, 2]


def warp_to_crop(image, A, size: int = 224, *, interpolation: str = "linear") -> np.ndarray:
    """Resample ``image`` (H,W[,C]) into the S×S crop of affine A (original → crop, pixel centres).
    When shrinking (scale k < 1) the image is first Gaussian-filtered (σ = 0.45/k px) against aliasing.
    ``interpolation="nearest"`` for label images (no filtering)."""
    import cv2

    img = np.asarray(image)
    k = float(A[0, 0])
    flags = cv2.INTER_NEAREST if interpolation == "nearest" else cv2.INTER_LINEAR
    if interpolation != "nearest" and k < 0.9:
        sig = 0.45 / k
        img = cv2.GaussianBlur(img.astype(np.float32), (0, 0), sig)
    out = cv2.warpAffine(img, np.asarray(A, np.float64), (size, size), flags=flags, borderMode=cv2.BORDER_REPLICATE)
    return out


@dataclass
class AlignResult:
    image: np.ndarray        # (S, S, 3) same dtype as the input
    landmarks: np.ndarray    # (68, 2) in the crop
    transform: np.ndarray    # (2, 3) original → crop
    scale: float             # k
    centre: np.ndarray       # t (original pixels)


def align_image(image, lm68, face_model, size: int = 224) -> AlignResult:
    """Deep3DFaceRecon alignment of one image with its 68 landmarks (see the module docstring)."""
    img = np.asarray(image)
    t, s = similarity_from_five_points(five_points(lm68), model_five_points(face_model), img.shape[0],
                                       centre=model_centre(face_model))
    A = crop_transform(t, s, size, RESCALE_PX_PER_MM * size / 224.0)
    out = warp_to_crop(img, A, size)
    if img.dtype == np.uint8:
        out = np.clip(np.round(out), 0, 255).astype(np.uint8)
    return AlignResult(out, transform_points(A, lm68), A, float(A[0, 0]), t)


# --------------------------------------------------------------------------- single-image geometry

def fit_single_image(face_model, landmarks, image_linear, K, *, config=None, size: int | None = None):
    """Shape, expression and pose of one aligned image with the fit-geometry machinery and a single view
    (:func:`reflectmm_cli.geometry_fit.fit.fit_geometry`: landmarks + priors, then the order-2 SH Lambert
    photometric term when an image is given).  Fixed intrinsics K (3,3).  Initial pose: frontal at 1 m
    (the Deep3D camera), refined with PnP on the landmarks.

    Returns the :class:`~reflectmm_cli.geometry_fit.fit.GeometryFit` (R (1,3,3), t (1,3), shape/exp coefficients).
    """
    from reflectmm_cli.geometry_fit.fit import FitConfig, ViewSet, fit_geometry
    from reflectmm_cli.geometry_fit.init import pnp_pose
    from reflectmm_cli.geometry_fit.model import ShapeModel

    lm = np.asarray(landmarks, np.float64).reshape(68, 2)
    S = int(size or (image_linear.shape[0] if image_linear is not None else 224))
    K = np.asarray(K, np.float64)
    R0 = np.diag([1.0, -1.0, -1.0])
    t0 = np.array([0.0, 0.0, 1000.0])
    R0, t0, _ = pnp_pose(face_model.mean_shape.astype(np.float64)[face_model.landmarks], lm, K, R0, t0)
    views = ViewSet(names=["image"], K=K[None], R0=R0[None], t0=t0[None], landmarks=lm[None], image_size=(S, S),
                    images=None if image_linear is None else np.asarray(image_linear, np.float32)[None])
    cfg = config or FitConfig(photo_rounds=1, photo_iters=30, landmark_iters=200, photo_blur_px=(1.0,),
                              photo_vertices=1500)
    return fit_geometry(ShapeModel.from_face_model(face_model), views, cfg)


# --------------------------------------------------------------------------- skin masks

#: CelebAMask-HQ / face-parsing (BiSeNet) label ids: 0 background, 1 skin, 2 nose, 3 eyeglasses, 4 l_eye,
#: 5 r_eye, 6 l_brow, 7 r_brow, 8 l_ear, 9 r_ear, 10 mouth (inner), 11 u_lip, 12 l_lip, 13 hair, 14 hat,
#: 15 earring, 16 necklace, 17 neck, 18 cloth.  Skin for the photometric loss: skin, nose, both lips.
CELEBAMASK_SKIN_LABELS = (1, 2, 11, 12)


def skin_mask_from_labels(labels, skin_labels=CELEBAMASK_SKIN_LABELS) -> np.ndarray:
    """(H, W) bool from a face-parsing label image (H, W) of CelebAMask-HQ / BiSeNet ids."""
    lab = np.asarray(labels)
    if lab.ndim == 3:
        lab = lab[..., 0]
    return np.isin(lab, np.asarray(skin_labels))


def skin_mask_from_model(gbuffer, vertex_skin, image_linear, *, k_sigma: float = 2.5) -> np.ndarray:
    """The face model's skin region projected (barycentric vote of ``vertex_skin`` at ``visible`` pixels) ∩ a
    colour test: pixels whose chromaticity (r/(r+g+b), g/(r+g+b)) and log-luminance lie within ``k_sigma``
    robust σ (MAD) of the median over that region — rejects hands of another colour, hair, hats, glasses."""
    fm = np.asarray(gbuffer["face_mask"], bool)
    H, W = fm.shape
    vis = np.asarray(gbuffer["visible"], bool)
    yx = np.asarray(gbuffer["pix_yx"])[vis].astype(np.int64)
    b = np.asarray(gbuffer["bary"])[vis]
    vote = (b * np.asarray(vertex_skin, np.float64)[np.asarray(gbuffer["vert_ids"])[vis]]).sum(1) > 0.5
    reg = np.zeros((H, W), bool)
    reg[yx[vote, 0], yx[vote, 1]] = True
    if image_linear is None or not reg.any():
        return reg
    img = np.asarray(image_linear, np.float64)
    s = img.sum(-1) + 1e-6
    feats = np.stack([img[..., 0] / s, img[..., 1] / s, np.log(s)], -1)
    f = feats[reg]
    med = np.median(f, 0)
    mad = np.median(np.abs(f - med), 0) * 1.4826 + np.array([0.01, 0.01, 0.1])
    ok = (np.abs(feats - med) <= k_sigma * mad).all(-1)
    ok &= img.max(-1) < 0.995          # saturated pixels carry no shading information
    return reg & ok


def mask_overlay(image_u8, mask, colour=(0, 255, 0), alpha: float = 0.45) -> np.ndarray:
    """uint8 (H,W,3) preview: ``mask`` tinted over the image."""
    img = np.asarray(image_u8, np.float64)
    c = np.asarray(colour, np.float64)
    out = np.where(np.asarray(mask, bool)[..., None], (1 - alpha) * img + alpha * c, img)
    return np.clip(np.round(out), 0, 255).astype(np.uint8)
