"""Relighting (the paper's Fig. 7) on data with held-out OLAT images (docs/evaluation.md).

Given one identity's geometry (mesh in model space, mm), one camera and the rig's flashes, a reconstructed
reflectance (per vertex ``albedo (V,3)``, ``weights (V,K)``, or UV maps ``(3,S,S)``/``(K,S,S)`` with the face
model's vertex UVs) is re-rendered under each held-out flash — a point light of radiant intensity I at the flash
position, ``E = I/d²``, ray-traced cast shadows — with :func:`reflectmm_cli.geometry.render_point_light` (the
shading core, Embree), and compared with the captured OLAT image of that flash.

* **Region** of a flash: rendered face pixels ∧ lit (n·l > 0 and no occluder between the point and the flash,
  ray cast) ∧ n·v > 0 ∧ (optionally) not saturated in the capture. It depends only on the geometry, so it is
  computed once per flash (:class:`RelightScene`) and shared by every method.
* **Scale**: a reconstruction from one image under unknown light carries the albedo/lighting scale ambiguity.
  With ``scale="global"`` (default) ONE least-squares factor per method and identity,
  ``s = Σ r·t / Σ r²`` over the linear pixels of all held-out regions, is applied before the metrics (reported);
  ``scale="none"`` compares as rendered.
* **Metrics** per flash on the display encoding ``clip(x,0,1)^(1/1.2)`` (peak 1): PSNR and SSIM over the
  region (:mod:`.metrics`), then the mean over flashes.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, Mapping, Sequence

import numpy as np

from reflectmm_cli.errors import ReflectmmError

from .figures import method_panels
from .metrics import encode_for_metrics, psnr, ssim

__all__ = ["RelightScene", "scene_from_artifacts", "capture_targets", "relight", "relighting_metrics",
           "relighting_rows"]


@dataclass
class RelightScene:
    """One identity seen by one camera with its flashes. Rasterises once and casts each flash's shadow rays
    once; :meth:`region` and the renders reuse them.

    Args:
        vertices (V,3) mm, triangles (T,3), normals (V,3) or None (area-weighted vertex normals),
        camera: :class:`reflectmm_cli.geometry.Camera`,
        flash_pos (F,3) mm, flash_intensity (F,) radiant intensity, flash_ids F names,
        uv (V,2) vertex UVs (only for UV-map reflectance), saturated: flash id → (H,W) bool (optional).
    """

    vertices: np.ndarray
    triangles: np.ndarray
    camera: Any
    flash_pos: np.ndarray
    flash_intensity: np.ndarray
    flash_ids: Sequence[str]
    normals: np.ndarray | None = None
    uv: np.ndarray | None = None
    saturated: Mapping[str, np.ndarray] | None = None
    _scene: Any = field(default=None, repr=False)
    _raster: Any = field(default=None, repr=False)
    _regions: dict = field(default_factory=dict, repr=False)

    def __post_init__(self):
        from reflectmm_cli.geometry import RayScene, has_embree, rasterize

        if not has_embree():
            raise ReflectmmError("relighting needs Embree ray casting (the 'embreex' package)")
        self.flash_ids = [str(f) for f in self.flash_ids]
        fp = np.asarray(self.flash_pos, np.float64)
        fi = np.asarray(self.flash_intensity, np.float64).reshape(-1)
        if fp.shape != (len(self.flash_ids), 3) or fi.shape != (len(self.flash_ids),):
            raise ReflectmmError(f"relighting: {len(self.flash_ids)} flash ids but flash_pos {fp.shape} and "
                                 f"flash_intensity {fi.shape}")
        self.flash_pos, self.flash_intensity = fp, fi
        self._scene = RayScene(np.asarray(self.vertices, np.float64), np.asarray(self.triangles),
                               None if self.normals is None else np.asarray(self.normals, np.float64))
        self._raster = rasterize(self._scene, self.camera)

    def _flash(self, fid: str) -> int:
        try:
            return self.flash_ids.index(str(fid))
        except ValueError:
            raise ReflectmmError(f"relighting: flash '{fid}' not in {', '.join(self.flash_ids)}") from None

    @property
    def mask(self) -> np.ndarray:
        """(H,W) bool rendered face pixels."""
        return self._raster.mask

    def region(self, fid: str) -> np.ndarray:
        """(H,W) bool evaluation region of flash ``fid`` (module docstring)."""
        from reflectmm_cli.geometry import shadow_mask

        if fid not in self._regions:
            r = self._raster
            m = r.mask
            x = r.position[m].astype(np.float64)
            n = r.normal[m].astype(np.float64)
            lit = shadow_mask(self._scene, x, n, self.flash_pos[self._flash(fid)])
            lit &= ((self.camera.center - x) * n).sum(1) > 0
            full = np.zeros(m.shape, bool)
            full[m] = lit
            if self.saturated is not None and fid in self.saturated:
                full &= ~np.asarray(self.saturated[fid], bool)
            self._regions[fid] = full
        return self._regions[fid]

    def render(self, albedo, weights, exponents, fid: str) -> tuple[np.ndarray, np.ndarray]:
        """(full, diffuse) (H,W,3) linear renders under flash ``fid``, 0 outside its region."""
        from reflectmm_cli.geometry import render_point_light

        f = self._flash(fid)
        reg = self.region(fid)
        w = np.asarray(weights, np.float64)
        res = render_point_light(self._scene, self.camera, albedo, w, exponents, self.flash_pos[f],
                                 self.flash_intensity[f], uv=self.uv, shadows=False, raster=self._raster)
        dif = render_point_light(self._scene, self.camera, albedo, np.zeros_like(w), exponents, self.flash_pos[f],
                                 self.flash_intensity[f], uv=self.uv, shadows=False, raster=self._raster)
        keep = reg[..., None]
        return (np.where(keep, res.image.astype(np.float64), 0.0), np.where(keep, dif.image.astype(np.float64), 0.0))


def relight(scene: RelightScene, albedo, weights, exponents, flashes: Sequence[str]) -> dict[str, dict[str, Any]]:
    """flash id → ``{"full", "diffuse", "specular"}`` linear (H,W,3) renders of one reconstruction."""
    exps = np.asarray(exponents, np.float64).reshape(-1)
    w = np.asarray(weights, np.float64)
    if exps.size == 0:
        raise ReflectmmError("relighting: at least one lobe is needed (a diffuse-only model has one all-zero lobe)")
    out = {}
    for fid in flashes:
        full, dif = scene.render(albedo, w, exps, fid)
        out[str(fid)] = {"full": full, "diffuse": dif, "specular": full - dif}
    return out


def relighting_metrics(scene: RelightScene, renders: Mapping[str, Mapping[str, np.ndarray]],
                       targets: Mapping[str, np.ndarray], *, scale: str = "global",
                       gamma: float = 1.2) -> dict[str, Any]:
    """PSNR / SSIM per held-out flash of one method (module docstring).

    Args:
        renders: output of :func:`relight`; targets: flash id → (H,W,3) LINEAR captured OLAT image.
    Returns:
        ``{"scale", "per_flash": {fid: {"psnr", "ssim", "pixels"}}, "psnr", "ssim"}`` (means over flashes).
    """
    if scale not in ("global", "none"):
        raise ReflectmmError(f"relighting: scale must be 'global' or 'none', got {scale!r}")
    fids = list(renders)
    for fid in fids:
        if fid not in targets:
            raise ReflectmmError(f"relighting: no captured OLAT image for flash '{fid}'")
        if np.shape(targets[fid]) != np.shape(renders[fid]["full"]):
            raise ReflectmmError(f"relighting: flash '{fid}': capture {np.shape(targets[fid])} vs render "
                                 f"{np.shape(renders[fid]['full'])}")
    s = 1.0
    if scale == "global":
        num = den = 0.0
        for fid in fids:
            reg = scene.region(fid)
            r = renders[fid]["full"][reg]
            t = np.asarray(targets[fid], np.float64)[reg]
            num += float((r * t).sum())
            den += float((r * r).sum())
        s = num / den if den > 0 else 1.0
    per = {}
    for fid in fids:
        reg = scene.region(fid)
        if not reg.any():
            continue
        a = encode_for_metrics(s * renders[fid]["full"], gamma)
        b = encode_for_metrics(targets[fid], gamma)
        per[fid] = {"psnr": float(min(psnr(a, b, reg), 100.0)), "ssim": float(ssim(a, b, reg)),
                    "pixels": int(reg.sum())}
    if not per:
        raise ReflectmmError("relighting: no held-out flash lights any face pixel")
    return {"scale": float(s), "per_flash": per, "psnr": float(np.mean([v["psnr"] for v in per.values()])),
            "ssim": float(np.mean([v["ssim"] for v in per.values()]))}


def relighting_rows(scene: RelightScene, input_display: np.ndarray, methods: Mapping[str, Mapping[str, Any]],
                    targets: Mapping[str, np.ndarray], fid: str, *, scales: Mapping[str, float] | None = None,
                    gamma: float = 1.2, err_max: float = 0.2) -> list[list[np.ndarray]]:
    """Figure rows for flash ``fid``: first row the input image and the captured OLAT (display encoded), then
    one row per method with :data:`.figures.PANELS` (relit image, diffuse / specular layers, error against the
    capture). ``methods``: name → output of :func:`relight`; ``scales``: name → the metrics' scale."""
    tgt = encode_for_metrics(targets[fid], gamma)
    reg = scene.region(fid)
    inp = np.clip(np.asarray(input_display, np.float64), 0, 1)
    if inp.shape != tgt.shape:
        raise ReflectmmError(f"relighting figure: input {inp.shape} and capture {tgt.shape} differ in size")
    rows = [[inp, tgt]]
    for name, rend in methods.items():
        s = 1.0 if scales is None else float(scales.get(name, 1.0))
        r = rend[fid]
        rows.append(method_panels(tgt, encode_for_metrics(s * r["full"], gamma),
                                  encode_for_metrics(s * r["diffuse"], gamma),
                                  encode_for_metrics(s * r["specular"], gamma), reg, err_max=err_max))
    return rows


def _names(arr) -> list[str]:
    return [str(x) for x in np.asarray(arr).reshape(-1)]


def scene_from_artifacts(capture: Mapping[str, np.ndarray], geometry: Mapping[str, np.ndarray],
                         triangles: np.ndarray, view: str, *, uv: np.ndarray | None = None) -> RelightScene:
    """A :class:`RelightScene` for ``view`` of one identity from its ``capture`` artifact arrays (``view_names``,
    ``flash_ids``, ``crop_origin`` (V,2), ``olat`` (V,F,h,w,3), optional ``saturated`` (V,F,h,w)) and its
    ``geometry`` artifact arrays (fit-geometry or the synthetic truth: ``vertices``, per-view ``K``/``R``/``t``
    with ``view_names`` (or ``camera_names``), ``flash_ids``, ``flash_pos``, ``flash_intensity``). The camera
    is the view's camera restricted to the stored capture window (principal point minus the crop origin), the
    flashes those the geometry knows."""
    from reflectmm_cli.geometry import Camera

    gv = _names(geometry["view_names"] if "view_names" in geometry else geometry["camera_names"])
    cv = _names(capture["view_names"])
    if view not in gv or view not in cv:
        raise ReflectmmError(f"relighting: view '{view}' not in the geometry ({', '.join(gv)}) and the capture "
                             f"({', '.join(cv)})")
    g, c = gv.index(view), cv.index(view)
    x0, y0 = (int(v) for v in np.asarray(capture["crop_origin"])[c])
    h, w = np.asarray(capture["olat"]).shape[2:4]
    K = np.array(geometry["K"][g], np.float64)
    K[0, 2] -= x0
    K[1, 2] -= y0
    cam = Camera(K, np.asarray(geometry["R"][g], np.float64), np.asarray(geometry["t"][g], np.float64), w, h, view)
    fids = _names(geometry["flash_ids"])
    sat = None
    if "saturated" in capture:
        cf = _names(capture["flash_ids"])
        sat = {f: np.asarray(capture["saturated"][c, cf.index(f)], bool) for f in fids if f in cf}
    return RelightScene(np.asarray(geometry["vertices"], np.float64), np.asarray(triangles), cam,
                        np.asarray(geometry["flash_pos"], np.float64),
                        np.asarray(geometry["flash_intensity"], np.float64).reshape(-1), fids, uv=uv, saturated=sat)


def capture_targets(capture: Mapping[str, np.ndarray], view: str, flashes: Sequence[str]) -> dict[str, np.ndarray]:
    """flash id → (h,w,3) linear OLAT image of ``view`` from a capture artifact's arrays."""
    cv, cf = _names(capture["view_names"]), _names(capture["flash_ids"])
    if view not in cv:
        raise ReflectmmError(f"relighting: view '{view}' not in the capture ({', '.join(cv)})")
    out = {}
    for f in flashes:
        if str(f) not in cf:
            raise ReflectmmError(f"relighting: flash '{f}' not in the capture ({', '.join(cf)})")
        out[str(f)] = np.asarray(capture["olat"][cv.index(view), cf.index(str(f))], np.float64)
    return out
