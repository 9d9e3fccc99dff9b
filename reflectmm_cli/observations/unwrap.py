"""``unwrap-uv`` library: capture + fitted geometry → per-texel observations (``uv-observations`` artifact).

For every texel of the S×S UV map (position ``x``, unit normal ``n``) and every (view, flash) pair j:

* ``visible[v]``: ``n·v > cos(grazing)``, in front of the camera, and the segment from ``x`` to the camera
  centre is not blocked by the mesh (Embree ray, origin offset along ``n``) — the ray-traced equivalent of a
  depth test;
* ``lit[f]``: ``n·l > 0`` and the segment from ``x`` to the flash is not blocked (Embree shadow ray).  No ray is
  traced for texels with ``n·l ≤ 0`` or texels invisible to every view (counted and logged);
* ``radiance[j]``: the OLAT image of the pair sampled bilinearly at the projection of ``x`` (OpenCV pinhole,
  minus the capture's crop origin);
* ``saturated[j]``: any of the 4 bilinear taps saturated;
* ``observed[j] = visible ∧ lit ∧ n·l > 0 ∧ n·v > cut-off ∧ unsaturated ∧ inside the stored image``.

Rays (``reflectmm_cli.geometry.RayScene``, Embree): the scene is the fitted mesh; a ray from a texel (offset by
1e-4 of the mesh diagonal along the normal and the ray) is blocked if it hits a triangle before its target.
"""

from __future__ import annotations

import logging
import math
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from typing import Any, Mapping, Sequence

import numpy as np

from reflectmm_cli.capture.images import check_finite_images
from reflectmm_cli.color import encode_display
from reflectmm_cli.errors import ReflectmmError
from reflectmm_cli.geometry.camera import project
from reflectmm_cli.params import named_twice
from reflectmm_cli.shading.brdf import DEFAULT_EXPONENTS
from reflectmm_cli.threads import default_threads

log = logging.getLogger("reflectmm")


@dataclass
class UVGeometry:
    """UV maps of a mesh: ``position (S,S,3)``, ``normal (S,S,3)`` (unit), ``mask (S,S)``, ``tri``, ``bary``."""

    position: np.ndarray
    normal: np.ndarray
    mask: np.ndarray
    tri: np.ndarray
    bary: np.ndarray


def uv_geometry(vertices: np.ndarray, triangles: np.ndarray, uv: np.ndarray, size: int,
                vertex_nrm: np.ndarray | None = None) -> UVGeometry:
    """Rasterise the mesh in UV space; positions and (area-weighted vertex) normals interpolated per texel."""
    from reflectmm_cli.geometry import rasterize_uv, uv_positions, vertex_normals

    vertices = np.asarray(vertices, dtype=np.float64)
    ras = rasterize_uv(uv, triangles, size)
    vn = vertex_normals(vertices, triangles) if vertex_nrm is None else vertex_nrm
    pos, nrm = uv_positions(vertices, vn, ras)
    mask = ras.mask & (np.linalg.norm(nrm, axis=-1) > 0.5)
    pos = np.where(mask[..., None], pos, 0.0).astype(np.float32)
    nrm = np.where(mask[..., None], nrm, 0.0).astype(np.float32)
    return UVGeometry(pos, nrm, mask, ras.tri_id, ras.bary)


def bilinear(images: np.ndarray, uv: np.ndarray, saturated: np.ndarray | None = None
             ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Sample ``images (F, H, W, C)`` at pixel coordinates ``uv (N, 2)`` (pixel centres at integers).

    Returns ``(values (F, N, C) float32, inside (N,) bool, sat (F, N) bool)``; ``inside`` means all four taps
    exist (``0 ≤ u ≤ W−1``, ``0 ≤ v ≤ H−1``); ``sat`` is true when any tap is saturated.  Outside: 0.
    """
    F, H, W = images.shape[:3]
    u, v = uv[:, 0], uv[:, 1]
    inside = (u >= 0) & (v >= 0) & (u <= W - 1) & (v <= H - 1) & np.isfinite(u) & np.isfinite(v)
    uc = np.where(inside, u, 0.0)
    vc = np.where(inside, v, 0.0)
    x0 = np.minimum(np.floor(uc).astype(np.int64), max(W - 2, 0))
    y0 = np.minimum(np.floor(vc).astype(np.int64), max(H - 2, 0))
    x1 = np.minimum(x0 + 1, W - 1)
    y1 = np.minimum(y0 + 1, H - 1)
    fx = (uc - x0).astype(np.float32)[None, :, None]
    fy = (vc - y0).astype(np.float32)[None, :, None]
    flat = images.reshape(F, H * W, -1)
    i00, i01, i10, i11 = y0 * W + x0, y0 * W + x1, y1 * W + x0, y1 * W + x1
    g = lambda i: flat[:, i].astype(np.float32)  # noqa: E731
    val = (g(i00) * (1 - fx) + g(i01) * fx) * (1 - fy) + (g(i10) * (1 - fx) + g(i11) * fx) * fy
    val[:, ~inside] = 0.0
    if saturated is None:
        sat = np.zeros((F, uv.shape[0]), bool)
    else:
        sflat = saturated.reshape(F, H * W)
        sat = sflat[:, i00] | sflat[:, i01] | sflat[:, i10] | sflat[:, i11]
        sat &= inside[None, :]
    return val, inside, sat


def _footprint_on_surface(scene, pix: np.ndarray, Z: np.ndarray, ndv: np.ndarray, K, R, t, crop, H: int, W: int,
                          depth_image: np.ndarray | None = None) -> tuple[np.ndarray, int]:
    """(M,) bool: each of the four bilinear taps around ``pix`` (crop-window pixels) sees the front of a triangle
    at the texel's depth ``Z`` within ``tol = (Z/f)·(1 + 1.5·√2·tanθ)`` (θ = angle between normal and view). Taps outside
    the window count as failing here only if they miss the mesh.  ``depth_image (H, W)``: the window's depths
    (:func:`_window_depths`) instead of casting rays.  Returns the mask and the number of rays cast."""
    M = pix.shape[0]
    if M == 0:
        return np.zeros(0, bool), 0
    taps_x, taps_y = _taps(pix)
    inwin = (taps_x >= 0) & (taps_x < W) & (taps_y >= 0) & (taps_y < H)
    key = np.where(inwin, taps_y * W + taps_x, -1)
    tap_depth = np.full(key.shape, np.inf)
    if depth_image is not None:  # the window's depths are already cast (the edge margin needs them all)
        tap_depth[inwin] = depth_image[taps_y[inwin], taps_x[inwin]]
        n_rays = 0
    else:
        uniq, inv = np.unique(key[inwin], return_inverse=True)
        # one primary ray per distinct tap pixel (full-frame pixel centre = window pixel + crop origin)
        tap_depth[inwin] = _pixel_depths(scene, (uniq % W).astype(np.float64) + crop[0],
                                         (uniq // W).astype(np.float64) + crop[1], K, R, t)[inv]
        n_rays = int(uniq.size)
    tol = _depth_tolerance(Z, ndv, K, 1.0)
    good = np.all(np.where(inwin, np.abs(tap_depth - Z[:, None]) <= tol[:, None], True), axis=1)
    return good, n_rays


def _taps(pix: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Integer pixel columns and rows ``(M, 4)`` of the four bilinear taps around each point of ``pix (M, 2)``."""
    x0 = np.floor(pix[:, 0]).astype(np.int64)
    y0 = np.floor(pix[:, 1]).astype(np.int64)
    return np.stack([x0, x0 + 1, x0, x0 + 1], 1), np.stack([y0, y0, y0 + 1, y0 + 1], 1)


def _depth_tolerance(Z: np.ndarray, ndv: np.ndarray, K, reach_px: float) -> np.ndarray:
    """Depth tolerance ``(Z/f)·(1 + 1.5·√2·reach·tanθ)`` of a surface point seen at depth ``Z`` under the angle θ
    (``cos θ = ndv``), for a pixel up to ``√2·reach`` pixels away: the surface's own depth change there, with slack."""
    f = float(np.asarray(K)[1, 1])
    cosv = np.clip(ndv, 1e-3, 1.0)
    tan = np.sqrt(np.clip(1.0 - cosv ** 2, 0.0, None)) / cosv
    return (Z / f) * (1.0 + 1.5 * math.sqrt(2.0) * reach_px * tan)


def _pixel_depths(scene, px: np.ndarray, py: np.ndarray, K, R, t) -> np.ndarray:
    """Camera depth ``(M,)`` of the front surface that the primary ray through each full-frame pixel centre
    ``(px, py)`` hits; ``inf`` where it misses the mesh or sees the back of a triangle (through a hole of an open
    mesh: mouth, eyes), which is not a surface of the face."""
    R = np.asarray(R, dtype=np.float64)
    Kinv = np.linalg.inv(np.asarray(K, dtype=np.float64))
    d_cam = np.stack([px, py, np.ones_like(px)], 1) @ Kinv.T
    d = d_cam @ R  # camera → model: Rᵀ d
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    c = -R.T @ np.asarray(t, dtype=np.float64)
    hit = scene.intersect(np.broadcast_to(c, d.shape), d)
    tri = hit["tri"]
    ok = tri >= 0
    tv = scene.vertices[scene.triangles[np.where(ok, tri, 0)]]
    gn = np.cross(tv[:, 1] - tv[:, 0], tv[:, 2] - tv[:, 0])
    ok &= np.einsum("ij,ij->i", gn, d) < 0
    return np.where(ok, hit["t"].astype(np.float64) * (d @ R[2]), np.inf)


def _window_depths(scene, K, R, t, crop, H: int, W: int) -> np.ndarray:
    """(H, W) :func:`_pixel_depths` of every pixel of a view's stored window (one primary ray each)."""
    yy, xx = np.mgrid[0:H, 0:W]
    return _pixel_depths(scene, xx.reshape(-1).astype(np.float64) + crop[0],
                         yy.reshape(-1).astype(np.float64) + crop[1], K, R, t).reshape(H, W)


def _away_from_edges(depth: np.ndarray, pix: np.ndarray, Z: np.ndarray, ndv: np.ndarray, K, margin: int
                     ) -> np.ndarray:
    """(M,) bool: every pixel within ``margin`` pixels of the four bilinear taps around ``pix`` (crop-window
    pixels) sees the front of the mesh at the texel's depth (the tolerance of :func:`_depth_tolerance` for that
    reach), by the window's depths ``depth (H, W)`` (:func:`_window_depths`).  So a sample keeps ``margin`` pixels
    from the mesh's open border, from its silhouette and from the occluding edges in front of it: a registration
    error of that size still samples this surface, not the background, hair or the nose.  Pixels outside the
    window repeat its edge."""
    from scipy.ndimage import maximum_filter, minimum_filter

    M = pix.shape[0]
    if M == 0 or margin <= 0:
        return np.ones(M, bool)
    H, W = depth.shape
    size = 2 * int(margin) + 1
    lo = minimum_filter(depth, size=size, mode="nearest")
    hi = maximum_filter(depth, size=size, mode="nearest")
    taps_x, taps_y = _taps(pix)
    taps_x = np.clip(taps_x, 0, W - 1)
    taps_y = np.clip(taps_y, 0, H - 1)
    near = lo[taps_y, taps_x].min(axis=1)
    far = hi[taps_y, taps_x].max(axis=1)
    tol = _depth_tolerance(Z, ndv, K, 1.0 + margin)
    return (Z - near <= tol) & (far - Z <= tol)


def _index_of(names: Sequence[str], wanted: Sequence[str], what: str, where) -> np.ndarray:
    names = [str(n) for n in names]
    idx = []
    for w in wanted:
        if str(w) not in names:
            raise ReflectmmError(f"{what} {w} of the capture is not in the geometry ({', '.join(names)})", where)
        idx.append(names.index(str(w)))
    return np.array(idx, dtype=np.int64)


def _names(value: str | Sequence[str]) -> list[str]:
    """Names from a comma string or a list, stripped, empty ones dropped."""
    items = value.split(",") if isinstance(value, str) else value
    return [str(x).strip() for x in items if str(x).strip()]


#: ``unwrap-uv --views / --flashes trusted``: the landmarked views and flashes, plus those of the cameras that the
#: images registered well (:func:`trusted_views`, :func:`trusted_flashes`).
TRUSTED = "trusted"

#: Defaults of the ``trusted`` selection: a registered camera's centre 1-σ (mm) and its flash residual as a
#: multiple of the median over the views that landmarks placed.
TRUST_CENTER_SIGMA_MM = 10.0
TRUST_RESIDUAL_RATIO = 3.0


def reflectance_views(capture: Mapping[str, np.ndarray], views: str | Sequence[str] | None = None,
                      geometry: Mapping[str, np.ndarray] | None = None, geometry_path=None,
                      max_center_sigma_mm: float = TRUST_CENTER_SIGMA_MM,
                      max_residual_ratio: float = TRUST_RESIDUAL_RATIO) -> list[str]:
    """The capture views whose images enter the reflectance fit.

    ``views`` if given (a comma string or a list; ``"all"`` = every view of the capture; ``"landmarked"`` = the
    views that landmarks placed, :func:`landmarked_views` of ``geometry``; ``"trusted"`` = those and the views
    registered by their images that check out, :func:`trusted_views` with the two bounds), else every view of
    ``capture["view_names"]`` but the raised cameras 08_1 / 19_1 (the paper uses them only to place flashes 14 / 18).
    The raised cameras are left out of ``landmarked`` and ``trusted`` too.  A capture holding only raised cameras
    keeps them (with a warning)."""
    from reflectmm_cli.rig import RAISED_CAMERAS

    have = [str(v) for v in np.asarray(capture["view_names"]).reshape(-1)]
    if views is not None:
        vs = _names(views)
        if vs in ([LANDMARKED], [TRUSTED]):
            if geometry is None:
                raise ReflectmmError(f"--views {vs[0]} needs the geometry (which views were placed, and how)",
                                     geometry_path)
            placed, how = _kept_by_rule(vs[0], geometry, "views", max_center_sigma_mm, max_residual_ratio,
                                        geometry_path)
            keep = [v for v in have if v in placed and v not in RAISED_CAMERAS]
            left = [v for v in have if v not in keep]
            if not keep:
                raise ReflectmmError(f"no view left to unwrap: none of the capture's views ({', '.join(have)}) "
                                     f"was {how}, but raised ones", geometry_path)
            if left:
                log.info("unwrap-uv: leaving out view(s) %s (raised, or not %s)", ", ".join(left), how)
            return keep
        return have if vs == ["all"] else vs
    keep = [v for v in have if v not in RAISED_CAMERAS]
    if not keep:
        log.warning("unwrap-uv: the capture has only raised cameras (%s): unwrapping them", ", ".join(have))
        return have
    if len(keep) < len(have):
        log.info("unwrap-uv: leaving out the raised camera(s) %s (geometry / flash placement only; --views all "
                 "keeps them)", ", ".join(v for v in have if v in RAISED_CAMERAS))
    return keep


def rig_placed(geometry: Mapping[str, np.ndarray], views: Sequence[str], flashes: Sequence[str] | None
               ) -> tuple[list[str], list[str]]:
    """Of ``views`` and ``flashes`` (None: all, as :func:`reflectance_flashes` returns them), those whose camera
    only the rig placed: ``view_evidence`` exactly ``rig`` (no landmarks, and no image registration that held).
    Their texels and their flashes' light rest on the rig's guess.  A geometry without ``view_evidence`` has
    none."""
    if "view_evidence" not in geometry or "view_names" not in geometry:
        return [], []
    names = [str(v) for v in np.asarray(geometry["view_names"]).reshape(-1)]
    guessed = {n for n, e in zip(names, np.asarray(geometry["view_evidence"]).reshape(-1)) if str(e) == "rig"}
    fl: list[str] = []
    if guessed and all(k in geometry for k in ("flash_from_view", "flash_ids", "flash_pos", "cam_centers")):
        ids = [str(f) for f in np.asarray(geometry["flash_ids"]).reshape(-1)]
        fl = [f for f, v in zip(ids, _carrying_views(geometry)) if v is not None and names[v] in guessed
              and (flashes is None or f in set(flashes))]
    return [v for v in views if v in guessed], fl


def warn_rig_placed(geometry: Mapping[str, np.ndarray], views: Sequence[str], flashes: Sequence[str] | None,
                    identity: str = "") -> None:
    """One stderr warning when the unwrap takes views or flashes whose camera only the rig placed
    (:func:`rig_placed`): a side view of a detector capture fitted without flash rounds, say."""
    vs, fs = rig_placed(geometry, views, flashes)
    if vs or fs:
        log.warning("unwrap-uv%s: cameras placed by the rig alone (fit-geometry's evidence 'rig': no landmarks, no "
                    "image registration), so these observations rest on the rig's guess: %s; --views trusted "
                    "--flashes trusted leaves them out", f" {identity}" if identity else "",
                    "; ".join(x for x in (f"view(s) {', '.join(vs)}" if vs else "",
                                          f"flash(es) {', '.join(fs)} on those cameras" if fs else "") if x))


def landmarked_views(geometry: Mapping[str, np.ndarray], geometry_path=None) -> list[str]:
    """The view names of a ``geometry`` whose ``view_evidence`` starts with ``landmarks``: the views whose camera
    landmarks placed (a view placed by the rig or registered by its flash images is left out)."""
    placed = _placed_by_landmarks(geometry, ("view_names",), "views", geometry_path)
    names = [str(v) for v in np.asarray(geometry["view_names"]).reshape(-1)]
    return [n for n, m in zip(names, placed) if m]


def _placed_by_landmarks(geometry: Mapping[str, np.ndarray], keys: Sequence[str], what: str,
                         geometry_path=None) -> list[bool]:
    """(V,) whether each view of ``geometry`` was placed by landmarks (``view_evidence`` starts with
    ``landmarks``). A geometry without ``view_evidence`` or one of ``keys`` (written before fit-geometry recorded
    each view's evidence) is a one-line error that says to rerun fit-geometry or name the ``what`` to keep."""
    for key in ("view_evidence", *keys):
        if key not in geometry:
            raise ReflectmmError(f"geometry has no '{key}' (written before fit-geometry recorded each view's "
                                 f"evidence): rerun fit-geometry, or name the {what} to keep", geometry_path)
    return [str(e).startswith("landmarks") for e in np.asarray(geometry["view_evidence"]).reshape(-1)]


def _positions(have, select: Sequence[str], what: str, capture_path=None) -> list[int]:
    """Indices of the names ``select`` in the capture's names ``have``; a one-line error names those missing."""
    have = [str(x) for x in np.asarray(have).reshape(-1)]
    twice = named_twice(select)
    if twice:
        raise ReflectmmError(f"{what} {', '.join(twice)} named more than once: each would count again in the "
                             "reflectance fit", capture_path)
    missing = [x for x in select if x not in have]
    if missing:
        words = [x for x in missing if x.lower() in ("all", LANDMARKED, TRUSTED)]
        hint = (f" ({', '.join(words)}: the selections all, {LANDMARKED} and {TRUSTED} are written in lower case and "
                "stand alone, not in a list of names)") if words else ""
        raise ReflectmmError(f"{what} {', '.join(missing)} are not in the capture (it has {', '.join(have)}){hint}",
                             capture_path)
    return [have.index(x) for x in select]


def _select_flashes(capture: Mapping[str, np.ndarray], select: Sequence[str], capture_path=None) -> dict:
    """The capture with only the flashes ``select`` (in that order): ``flash_ids`` and the flash axis (1) of
    ``olat`` and ``saturated``."""
    keep = _positions(capture["flash_ids"], select, "flash(es)", capture_path)
    out = dict(capture)
    out["flash_ids"] = np.array(list(select), dtype=str)
    for k in ("olat", "saturated"):
        out[k] = np.asarray(capture[k])[:, keep]
    return out


#: ``unwrap-uv --flashes landmarked``: only the flashes carried by cameras that landmarks placed.
LANDMARKED = "landmarked"


def landmarked_flashes(geometry: Mapping[str, np.ndarray], geometry_path=None) -> list[str]:
    """The flash ids of a ``geometry`` whose place rests on landmarks: carried by a fitted view
    (``flash_from_view``) whose ``view_evidence`` starts with ``landmarks``.

    fit-geometry puts a carried flash exactly at its view's fitted centre, so the carrying view is the one whose
    ``cam_centers`` row equals the flash position (to 1e-9 relative).  A flash on a view placed by the rig alone or
    by its flash images (evidence ``rig``, ``rig+flash``) sits where that camera was guessed, and a free-standing
    flash where the rig's alignment to all fitted views puts it: both are left out.
    """
    placed = _placed_by_landmarks(geometry, ("flash_from_view", "flash_ids", "flash_pos", "cam_centers"), "flashes",
                                  geometry_path)
    ids = [str(f) for f in np.asarray(geometry["flash_ids"]).reshape(-1)]
    return [fid for fid, v in zip(ids, _carrying_views(geometry)) if v is not None and placed[v]]


def _carrying_views(geometry: Mapping[str, np.ndarray]) -> list[int | None]:
    """For each flash of ``geometry``, the index of the fitted view that carries it (its ``cam_centers`` row equals
    the flash position to 1e-9 relative and ``flash_from_view`` is set), else None (a free-standing flash)."""
    carried = np.asarray(geometry["flash_from_view"], bool).reshape(-1)
    pos = np.asarray(geometry["flash_pos"], np.float64).reshape(-1, 3)
    centers = np.asarray(geometry["cam_centers"], np.float64).reshape(-1, 3)
    out: list[int | None] = []
    for i in range(len(pos)):
        d = np.linalg.norm(centers - pos[i], axis=1)
        v = int(np.argmin(d))
        ok = carried[i] and d[v] <= 1e-9 * max(1.0, float(np.linalg.norm(pos[i])))
        out.append(v if ok else None)
    return out


def _trusted_placement(geometry: Mapping[str, np.ndarray], max_center_sigma_mm: float, max_residual_ratio: float,
                       geometry_path=None, keys: Sequence[str] = ("view_names",), what: str = "views") -> list[bool]:
    """(V,) whether each view's place can be trusted: landmarks placed it, or its images registered it (evidence
    ``rig+…``, not ``rig`` alone) with a finite centre 1-σ ≤ ``max_center_sigma_mm`` and a flash residual ≤
    ``max_residual_ratio`` × the median flash residual of the views that landmarks placed (no such median: no
    registered view is trusted).  ``keys`` / ``what``: the other arrays the caller needs, and what it selects (for
    :func:`_placed_by_landmarks`' error)."""
    placed = _placed_by_landmarks(geometry, (*keys, "center_sigma_mm", "flash_residual"), what, geometry_path)
    evidence = [str(e) for e in np.asarray(geometry["view_evidence"]).reshape(-1)]
    sigma = np.asarray(geometry["center_sigma_mm"], np.float64).reshape(-1)
    resid = np.asarray(geometry["flash_residual"], np.float64).reshape(-1)
    ref = resid[np.asarray(placed, bool) & np.isfinite(resid)]
    ref_med = float(np.median(ref)) if ref.size else np.nan
    out = []
    for v, lm in enumerate(placed):
        registered = "+" in evidence[v]                        # "rig" alone: the rig's guess, no image evidence
        out.append(bool(lm) or bool(registered and np.isfinite(sigma[v]) and sigma[v] <= max_center_sigma_mm
                                    and np.isfinite(ref_med) and np.isfinite(resid[v])
                                    and resid[v] <= max_residual_ratio * ref_med))
    return out


def trusted_views(geometry: Mapping[str, np.ndarray], max_center_sigma_mm: float = TRUST_CENTER_SIGMA_MM,
                  max_residual_ratio: float = TRUST_RESIDUAL_RATIO, geometry_path=None) -> list[str]:
    """The view names of a ``geometry`` whose place can be trusted: placed by landmarks, or registered by their
    images and checking out on both of the fit's own measures of that registration:

    - ``center_sigma_mm`` (the Laplace 1-σ of the camera centre) finite and at most ``max_center_sigma_mm``;
    - ``flash_residual`` at most ``max_residual_ratio`` × the median ``flash_residual`` of the views that
      landmarks placed.

    A view placed by the rig alone (evidence ``rig``), and every registered view when no landmarked view has a
    finite flash residual to compare with, are left out."""
    names = [str(v) for v in np.asarray(geometry["view_names"]).reshape(-1)]
    ok = _trusted_placement(geometry, max_center_sigma_mm, max_residual_ratio, geometry_path)
    return [n for n, k in zip(names, ok) if k]


def trusted_flashes(geometry: Mapping[str, np.ndarray], max_center_sigma_mm: float = TRUST_CENTER_SIGMA_MM,
                    max_residual_ratio: float = TRUST_RESIDUAL_RATIO, geometry_path=None) -> list[str]:
    """The flash ids of a ``geometry`` carried by a view whose place can be trusted (:func:`trusted_views`): the
    landmarked flashes (:func:`landmarked_flashes`) and those of the registered cameras that check out.  A
    free-standing flash is left out."""
    ok = _trusted_placement(geometry, max_center_sigma_mm, max_residual_ratio, geometry_path,
                            keys=("flash_from_view", "flash_ids", "flash_pos", "cam_centers"), what="flashes")
    ids = [str(f) for f in np.asarray(geometry["flash_ids"]).reshape(-1)]
    return [fid for fid, v in zip(ids, _carrying_views(geometry)) if v is not None and ok[v]]


def _kept_by_rule(rule: str, geometry: Mapping[str, np.ndarray], what: str, max_center_sigma_mm: float,
                  max_residual_ratio: float, geometry_path=None) -> tuple[set[str], str]:
    """The ``what`` ("views" or "flashes") of ``geometry`` that the selection ``rule`` (``landmarked`` or
    ``trusted``) keeps, and the words that say how their cameras were placed (for stderr and errors)."""
    if rule == LANDMARKED:
        pick = landmarked_views if what == "views" else landmarked_flashes
        return set(pick(geometry, geometry_path)), "placed by landmarks"
    pick = trusted_views if what == "views" else trusted_flashes
    return (set(pick(geometry, max_center_sigma_mm, max_residual_ratio, geometry_path)),
            f"placed by landmarks or registered by their images within {max_center_sigma_mm:g} mm (1-sigma) and "
            f"{max_residual_ratio:g}x the landmarked views' flash residual")


def reflectance_flashes(capture: Mapping[str, np.ndarray], geometry: Mapping[str, np.ndarray],
                        flashes: str | Sequence[str] | None = None, geometry_path=None,
                        max_center_sigma_mm: float = TRUST_CENTER_SIGMA_MM,
                        max_residual_ratio: float = TRUST_RESIDUAL_RATIO) -> list[str] | None:
    """The capture flashes whose images enter the reflectance fit: ``None`` (all), a list / comma string of flash
    ids, ``"landmarked"`` (:func:`landmarked_flashes`) or ``"trusted"`` (:func:`trusted_flashes`, with the two
    bounds).  Refuses an empty selection in one line."""
    if flashes is None:
        return None
    fs = _names(flashes)
    if fs == ["all"]:
        return None
    if fs in ([LANDMARKED], [TRUSTED]):
        have = [str(f) for f in np.asarray(capture["flash_ids"]).reshape(-1)]
        placed, how = _kept_by_rule(fs[0], geometry, "flashes", max_center_sigma_mm, max_residual_ratio,
                                    geometry_path)
        fs = [f for f in have if f in placed]
        left = [f for f in have if f not in placed]
        if left:
            log.info("unwrap-uv: leaving out flash(es) %s (not carried by a camera %s)", ", ".join(left), how)
    if not fs:
        raise ReflectmmError("no flash left to unwrap: no camera that carries a flash was placed by landmarks"
                             + (" or registered well by its images" if _names(flashes) == [TRUSTED] else ""),
                             geometry_path)
    return fs


@dataclass
class _PairInputs:
    """The capture's images and the geometry's cameras and flashes, aligned view by view and flash by flash."""

    views: list[str]
    flashes: list[str]
    K: np.ndarray            # (V, 3, 3)
    R: np.ndarray            # (V, 3, 3)
    t: np.ndarray            # (V, 3)
    cam_centers: np.ndarray  # (V, 3)
    flash_pos: np.ndarray    # (F, 3)
    flash_int: np.ndarray    # (F,)
    olat: np.ndarray         # (V, F, h, w, 3)
    saturated: np.ndarray    # (V, F, h, w)
    crop: np.ndarray         # (V, 2)


def _pair_inputs(capture: Mapping[str, np.ndarray], geometry: Mapping[str, np.ndarray],
                 select_views: Sequence[str] | None, select_flashes: Sequence[str] | None,
                 geometry_path, capture_path) -> _PairInputs:
    """Select the views and flashes to unwrap, match them to the geometry's, and check the capture's shapes."""
    views = [str(v) for v in capture["view_names"]]
    if select_views is not None:
        keep = _positions(views, select_views, "view(s)", capture_path)
        V0 = len(views)
        capture = {k: (np.asarray(capture[k])[keep] if k in ("olat", "saturated", "crop_origin", "view_names")
                       and np.asarray(capture[k]).shape[:1] == (V0,) else capture[k]) for k in capture}
        views = [str(v) for v in capture["view_names"]]
    if select_flashes is not None:
        capture = _select_flashes(capture, select_flashes, capture_path)
    flashes = [str(f) for f in capture["flash_ids"]]
    gv = _index_of(geometry["view_names"], views, "view", geometry_path)
    gf = _index_of(geometry["flash_ids"], flashes, "flash", geometry_path)
    cap_size = np.asarray(capture["image_size"]).reshape(-1)
    geo_size = np.asarray(geometry["image_size"]).reshape(-1)
    if geo_size.size >= 2 and tuple(cap_size[:2]) != tuple(geo_size[:2]):
        raise ReflectmmError(f"geometry image_size {tuple(geo_size[:2])} differs from the capture's "
                             f"{tuple(cap_size[:2])}", geometry_path)
    olat = capture["olat"]
    satur = capture["saturated"]
    crop = np.asarray(capture.get("crop_origin", np.zeros((len(views), 2))), dtype=np.float64)
    V, F = len(views), len(flashes)
    if olat.ndim != 5 or olat.shape[:2] != (V, F) or olat.shape[4] != 3:
        raise ReflectmmError(f"capture 'olat' has shape {olat.shape}, expected ({V}, {F}, h, w, 3)", capture_path)
    if satur.shape != olat.shape[:4]:
        raise ReflectmmError(f"capture 'saturated' has shape {satur.shape}, expected {olat.shape[:4]}", capture_path)
    check_finite_images(olat, "olat", views, capture_path, flashes)
    if crop.shape != (V, 2):
        raise ReflectmmError(f"capture 'crop_origin' has shape {crop.shape}, expected ({V}, 2)", capture_path)
    return _PairInputs(
        views=views, flashes=flashes,
        K=np.asarray(geometry["K"], dtype=np.float64)[gv], R=np.asarray(geometry["R"], dtype=np.float64)[gv],
        t=np.asarray(geometry["t"], dtype=np.float64)[gv],
        cam_centers=np.asarray(geometry["cam_centers"], dtype=np.float64)[gv],
        flash_pos=np.asarray(geometry["flash_pos"], dtype=np.float64)[gf],
        flash_int=np.asarray(geometry["flash_intensity"], dtype=np.float64).reshape(-1)[gf],
        olat=olat, saturated=satur, crop=crop)


def _view_visibility(scene, x: np.ndarray, n: np.ndarray, inp: _PairInputs, cos_cut: float, edge_margin: int = 0
                     ) -> tuple[np.ndarray, np.ndarray, dict[str, int]]:
    """Which texels each view sees, and where (``vis (V, N)``, ``pix (V, N, 2)`` in stored-image pixels).

    A texel is seen when it faces the camera within the grazing cut-off, lies in front of it, its ray to the
    camera centre is unblocked, and all four taps of its bilinear footprint see the same surface (not a silhouette
    or an occluding edge, where the sample would mix surfaces).  With ``edge_margin`` > 0 every pixel within that
    many pixels of the taps must see it too (:func:`_away_from_edges`)."""
    from reflectmm_cli.geometry import visibility

    V, N = len(inp.views), x.shape[0]
    vis = np.zeros((V, N), bool)
    pix_all = np.zeros((V, N, 2))
    counts = {"rays_view": 0, "rays_depth": 0, "footprint_rejected": 0, "edge_rejected": 0}
    h, w = inp.olat.shape[2], inp.olat.shape[3]
    for vi in range(V):
        dv = inp.cam_centers[vi] - x
        ndv = np.einsum("nk,nk->n", n, dv) / np.linalg.norm(dv, axis=1)
        pix, Z = project(x, inp.K[vi], inp.R[vi], inp.t[vi])
        pix -= inp.crop[vi][None, :]
        pix_all[vi] = pix
        cand = np.flatnonzero((ndv > cos_cut) & (Z > 0))
        ok = visibility(scene, x[cand], n[cand], inp.cam_centers[vi])
        counts["rays_view"] += cand.size
        ci = cand[ok]
        depth = None
        if edge_margin > 0:
            depth = _window_depths(scene, inp.K[vi], inp.R[vi], inp.t[vi], inp.crop[vi], h, w)
            counts["rays_depth"] += h * w
        good, nr = _footprint_on_surface(scene, pix[ci], Z[ci], ndv[ci], inp.K[vi], inp.R[vi], inp.t[vi],
                                         inp.crop[vi], h, w, depth)
        counts["rays_depth"] += nr
        counts["footprint_rejected"] += int((~good).sum())
        ci = ci[good]
        if depth is not None:
            away = _away_from_edges(depth, pix[ci], Z[ci], ndv[ci], inp.K[vi], edge_margin)
            counts["edge_rejected"] += int((~away).sum())
            ci = ci[away]
        vis[vi, ci] = True
    return vis, pix_all, counts


def _flash_lighting(scene, x: np.ndarray, n: np.ndarray, flash_pos: np.ndarray, seen: np.ndarray
                    ) -> tuple[np.ndarray, dict[str, int]]:
    """Which texels each flash lights (``lit (F, N)``): facing it and unshadowed.  No shadow ray is traced for a
    texel facing away from the flash or seen by no view."""
    from reflectmm_cli.geometry import shadow_mask

    F, N = flash_pos.shape[0], x.shape[0]
    lit = np.zeros((F, N), bool)
    counts = {"rays_shadow": 0, "skipped_backfacing_light": 0, "skipped_unseen": 0}
    for fi in range(F):
        ndl = np.einsum("nk,nk->n", n, flash_pos[fi] - x)
        front = ndl > 0
        counts["skipped_backfacing_light"] += int((~front).sum())
        counts["skipped_unseen"] += int((front & ~seen).sum())
        ci = np.flatnonzero(front & seen)
        lit[fi, ci] = shadow_mask(scene, x[ci], n[ci], flash_pos[fi])
        counts["rays_shadow"] += ci.size
    return lit, counts


def _sample_pairs(inp: _PairInputs, vis: np.ndarray, lit: np.ndarray, pix_all: np.ndarray, idx: np.ndarray,
                  S: int) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Bilinear samples of every (view, flash) pair at its texels: ``radiance (P, S², 3)`` float16, ``observed``
    and ``saturated (P, S²)`` (P = V·F, view-major), and which texels fall inside any stored image."""
    V, F = len(inp.views), len(inp.flashes)
    P = V * F
    radiance = np.zeros((P, S * S, 3), dtype=np.float16)
    observed = np.zeros((P, S * S), bool)
    saturated = np.zeros((P, S * S), bool)
    inside_any = np.zeros(idx.size, bool)
    for vi in range(V):
        ci = np.flatnonzero(vis[vi])
        vals, inside, sat = bilinear(np.asarray(inp.olat[vi], dtype=np.float32), pix_all[vi][ci],
                                     inp.saturated[vi])
        inside_any[ci] |= inside
        tex = idx[ci]
        for fi in range(F):
            p = vi * F + fi
            ob = lit[fi, ci] & inside & ~sat[fi]
            observed[p, tex] = ob
            saturated[p, tex] = sat[fi]
            radiance[p, tex] = np.where(ob[:, None], vals[fi], 0.0)
    return radiance, observed, saturated, inside_any


def _conditioning_maps(arrays: Mapping[str, np.ndarray], exponents: Sequence[float]) -> dict[str, np.ndarray]:
    """Per-texel conditioning of the reflectance design (``conditioning``, ``conditioning_exponents``,
    ``observability``), for the texels with at least one observation.

    The texels are independent, so interleaved rows run in threads (numpy releases the GIL in the per-texel
    linear algebra); texels without observations stay 0."""
    from reflectmm_cli.reflectance.design import conditioning

    S = arrays["mask"].shape[0]
    need = arrays["mask"] & (arrays["obs_count"] > 0)
    workers = default_threads(2)
    rows = np.arange(S)[:, None]
    masks = [need & (rows % workers == k) for k in range(workers)]

    def part(mk):
        return conditioning(arrays["position"], arrays["normal"], arrays["cam_centers"], arrays["flash_pos"],
                            arrays["flash_intensity"], arrays["pair_view"], arrays["pair_flash"],
                            arrays["observed"], exponents, mask=mk)

    with ThreadPoolExecutor(workers) as ex:
        parts = list(ex.map(part, masks))
    cond_map = np.zeros((S, S), np.float32)
    obsv = np.zeros((len(exponents), S, S), np.float32)
    for mk, c in zip(masks, parts):
        cond_map[mk] = c.conditioning[mk]
        obsv[:, mk] = c.observability[:, mk]
    return {"conditioning": cond_map, "conditioning_exponents": np.asarray(parts[0].exponents, dtype=np.float32),
            "observability": obsv}


def unwrap_observations(capture: Mapping[str, np.ndarray], geometry: Mapping[str, np.ndarray],
                        triangles: np.ndarray, uv: np.ndarray, *, uv_size: int = 256, grazing_deg: float = 80.0,
                        edge_margin: int = 1,
                        exponents: Sequence[float] = DEFAULT_EXPONENTS, geometry_path=None, capture_path=None,
                        with_conditioning: bool = True, select_views: Sequence[str] | None = None,
                        select_flashes: Sequence[str] | None = None
                        ) -> tuple[dict[str, np.ndarray], dict[str, Any]]:
    """Build the ``uv-observations`` arrays of docs/pipeline.md.

    Steps: select and check the inputs, rasterise the mesh in UV space, find what each view sees and each flash
    lights (Embree rays), sample every (view, flash) pair, then the per-texel conditioning.

    Args:
        capture: arrays of a ``capture`` artifact (``olat``, ``saturated``, ``view_names``, ``flash_ids``,
            ``crop_origin``, ``image_size``).
        geometry: arrays of a ``geometry`` artifact (``vertices``, ``view_names``, ``K``, ``R``, ``t``,
            ``cam_centers``, ``flash_ids``, ``flash_pos``, ``flash_intensity``, ``image_size``).
        triangles, uv: the face model's topology and texture coordinates.
        grazing_deg: views with ``n·v ≤ cos(grazing_deg)`` do not see the texel.
        edge_margin: pixels that a view's sample keeps from the mesh's border, silhouette and occluding edges
            (0: only its bilinear footprint must lie on the surface; the stage's default is 1).
        select_views: the capture views to unwrap (default all; the stage leaves out 08_1 / 19_1).
        select_flashes: the capture flashes to unwrap (default all).
    Returns:
        ``(arrays, report)``.
    """
    if not 0.0 < grazing_deg <= 90.0:
        raise ReflectmmError(f"--grazing-deg must be in (0, 90], got {grazing_deg}")
    if int(edge_margin) != edge_margin or edge_margin < 0:
        raise ReflectmmError(f"--edge-margin must be a whole number of pixels ≥ 0, got {edge_margin}")
    verts = np.asarray(geometry["vertices"], dtype=np.float64)
    if verts.ndim != 2 or verts.shape[1] != 3:
        raise ReflectmmError(f"geometry 'vertices' must be (N, 3), got {verts.shape}", geometry_path)
    if np.asarray(uv).shape[0] != verts.shape[0]:
        raise ReflectmmError(f"geometry has {verts.shape[0]} vertices but the face model has "
                             f"{np.asarray(uv).shape[0]}", geometry_path)
    inp = _pair_inputs(capture, geometry, select_views, select_flashes, geometry_path, capture_path)
    V, F = len(inp.views), len(inp.flashes)
    S = int(uv_size)

    from reflectmm_cli.geometry import RayScene, vertex_normals

    vnorm = vertex_normals(verts, triangles)
    g = uv_geometry(verts, triangles, uv, S, vnorm)
    idx = np.flatnonzero(g.mask.reshape(-1))
    x = g.position.reshape(-1, 3)[idx].astype(np.float64)
    n = g.normal.reshape(-1, 3)[idx].astype(np.float64)
    scene = RayScene(verts, triangles, vnorm)

    vis, pix_all, view_counts = _view_visibility(scene, x, n, inp, math.cos(math.radians(grazing_deg)),
                                                 int(edge_margin))
    seen = vis.any(0)
    lit, flash_counts = _flash_lighting(scene, x, n, inp.flash_pos, seen)
    radiance, observed, saturated, inside_any = _sample_pairs(inp, vis, lit, pix_all, idx, S)

    P = V * F
    arrays: dict[str, np.ndarray] = {
        "position": g.position, "normal": g.normal, "mask": g.mask,
        "view_names": np.array(inp.views, dtype=str), "flash_ids": np.array(inp.flashes, dtype=str),
        "cam_centers": inp.cam_centers.astype(np.float32), "flash_pos": inp.flash_pos.astype(np.float32),
        "flash_intensity": inp.flash_int.astype(np.float32),
        "pair_view": np.repeat(np.arange(V, dtype=np.int32), F), "pair_flash": np.tile(np.arange(F, dtype=np.int32), V),
        "radiance": radiance.reshape(P, S, S, 3), "observed": observed.reshape(P, S, S),
        "visible": _scatter(vis, idx, S), "lit": _scatter(lit, idx, S),
        "saturated": saturated.reshape(P, S, S),
        "obs_count": observed.sum(0).astype(np.int32).reshape(S, S),
    }
    report = {"texels": int(idx.size), "uv_size": S, "views": V, "flashes": F, "grazing_deg": float(grazing_deg),
              "rays_view": int(view_counts["rays_view"]), "rays_shadow": int(flash_counts["rays_shadow"]),
              "rays_depth": int(view_counts["rays_depth"]),
              "footprint_rejected": int(view_counts["footprint_rejected"]),
              "edge_margin": int(edge_margin), "edge_rejected": int(view_counts["edge_rejected"]),
              "skipped_backfacing_light": int(flash_counts["skipped_backfacing_light"]),
              "skipped_unseen": int(flash_counts["skipped_unseen"]),
              "texels_unseen": int((~seen).sum()), "texels_outside_images": int((seen & ~inside_any).sum()),
              "observed_pairs": int(observed.sum()), "saturated_pairs": int(saturated.sum()),
              "ray_engine": "embree"}
    if with_conditioning:
        arrays.update(_conditioning_maps(arrays, exponents))
    return arrays, report


def _scatter(a: np.ndarray, idx: np.ndarray, S: int) -> np.ndarray:
    out = np.zeros((a.shape[0], S * S), dtype=a.dtype)
    out[:, idx] = a
    return out.reshape(a.shape[0], S, S)


def previews(arrays: Mapping[str, np.ndarray], n_radiance: int = 3, tile: int = 256) -> np.ndarray:
    """RGB uint8 preview row: observation count, conditioning (log10, 1e-6..1), and a few radiance maps."""
    import cv2

    S = arrays["mask"].shape[0]
    mask = arrays["mask"]
    tiles = []
    cnt = arrays["obs_count"].astype(np.float32)
    cmax = max(float(cnt.max()), 1.0)
    c8 = (np.clip(cnt / cmax, 0, 1) * 255).astype(np.uint8)
    tiles.append(cv2.applyColorMap(c8, cv2.COLORMAP_VIRIDIS)[..., ::-1] * mask[..., None])
    if "conditioning" in arrays:
        lc = (np.log10(np.clip(arrays["conditioning"], 1e-6, 1.0)) + 6.0) / 6.0
        tiles.append(cv2.applyColorMap((lc * 255).astype(np.uint8), cv2.COLORMAP_VIRIDIS)[..., ::-1]
                     * mask[..., None])
    rad = arrays["radiance"]
    obs = arrays["observed"]
    counts = obs.reshape(obs.shape[0], -1).sum(1)
    picks = np.argsort(-counts, kind="stable")[:n_radiance]
    if picks.size:
        scale = float(np.percentile(rad[picks].astype(np.float32)[obs[picks]], 99.5)) if obs[picks].any() else 1.0
        for p in sorted(picks.tolist()):
            tiles.append(encode_display(rad[p].astype(np.float32) / max(scale, 1e-8), "gamma", nan_to_num=False,
                                        uint8=True))
    tiles = [cv2.resize(np.ascontiguousarray(t), (tile, tile), interpolation=cv2.INTER_NEAREST)
             if S != tile else np.ascontiguousarray(t) for t in tiles]
    return np.concatenate(tiles, axis=1)
