"""Table 2 on in-the-wild images with ground truth: image metrics of reconstructions and the reconstructed
per-vertex reflectance against the truth (pure functions on arrays; docs/evaluation.md).

Inputs are per-image predictions of one method over N images of a ``wild-shard`` (S×S crops) and the shard's
arrays:

* predictions: ``render`` (N,S,S,3) LINEAR full shading, optionally ``diffuse`` / ``specular`` (N,S,S,3) linear
  layers, ``vertex_albedo`` (N,V,3) linear diffuse albedo and ``vertex_spec`` (N,V) Σ_i w_i per vertex (what
  ``reconstruct`` writes);
* shard: ``image`` (N,S,S,3) uint8 in the shard's ``encoding``, ``face_mask`` / ``skin_mask`` (N,S,S) bool,
  ``truth_vertex_albedo`` (N,V,3), the truth's per-vertex specular albedo (N,V) (or lobe weights (N,V,K), summed:
  :func:`spec_albedo_of`), ``pix_offset`` / ``vert_ids`` for the vertices seen in each image.

**Image metrics** (:func:`image_metrics_table`): the prediction is encoded like the shard's images
(:func:`encode_like`: gamma1.2 → ``clip(x,0,1)^(1/1.2)``, srgb → the sRGB OETF, linear → clip) and compared with
the stored image ``/255`` over the face region (``face_mask`` by default, ``skin_mask`` optional), per image then
mean ± 95 % CI (:mod:`.face_metrics`), plus the released protocol on the same arrays.

**Reflectance errors** (:func:`vertex_reflectance_errors`), per image over the vertices it sees (a vertex of a
triangle hit by a face pixel; :func:`seen_vertices`): diffuse albedo RMSE / relative error (RMSE/RMS truth) /
PSNR (linear, peak 1) over vertices and RGB, and the same for Σw against the truth's specular albedo; **raw** and
after ONE per-image scale ``s_i = Σ a·a* / Σ a²`` (closed-form least squares on the diffuse albedo, all channels;
applied to albedo and Σw alike) — a single image cannot separate albedo from light intensity (the albedo/lighting
ambiguity), so the scaled error measures the reflectance's *pattern*, the raw one also its absolute level. Then
mean ± CI over images.
"""
from __future__ import annotations

from typing import Any, Mapping, Sequence

import numpy as np

from reflectmm_cli.color import SRGB_DECODE_KNEE_EXACT, encode_display, gamma_to_linear, srgb_to_linear
from reflectmm_cli.errors import ReflectmmError

from .face_metrics import FaceMetrics, face_region_metrics, format_ci, mean_ci, released_protocol
from .metrics import LPIPS

__all__ = ["decode_image", "encode_like", "spec_albedo_of", "seen_vertices", "per_image_scale",
           "image_metrics_table", "vertex_reflectance_errors", "evaluate_reconstruction", "table_row",
           "markdown_table"]

ENCODINGS = ("gamma1.2", "srgb", "linear")


def _check_encoding(encoding: str) -> str:
    if encoding not in ENCODINGS:
        raise ReflectmmError(f"unknown image encoding {encoding!r} (one of {', '.join(ENCODINGS)})")
    return encoding


def decode_image(codes: np.ndarray, encoding: str) -> np.ndarray:
    """uint8 codes (or floats in [0,1]) in ``encoding`` → linear float64."""
    x = np.asarray(codes)
    x = x.astype(np.float64) / 255.0 if x.dtype == np.uint8 else x.astype(np.float64)
    enc = _check_encoding(encoding)
    if enc == "gamma1.2":
        return gamma_to_linear(np.clip(x, 0, None), 1.2)
    if enc == "srgb":
        return srgb_to_linear(x, threshold=SRGB_DECODE_KNEE_EXACT)
    return x


def encode_like(linear: np.ndarray, encoding: str) -> np.ndarray:
    """Linear radiance → the shard's display encoding in [0, 1] (clipped), so predictions compare with
    ``image/255``."""
    return encode_display(linear, _check_encoding(encoding), dtype=np.float64)


def spec_albedo_of(truth_weights: np.ndarray) -> np.ndarray:
    """Per-vertex specular albedo (N,V): (N,V) as given, or Σ over the last axis of lobe weights (N,V,K)."""
    a = np.asarray(truth_weights, np.float64)
    if a.ndim == 3:
        return a.sum(-1)
    if a.ndim == 2:
        return a
    raise ReflectmmError(f"truth specular: expected (N,V) or (N,V,K), got {a.shape}")


def seen_vertices(pix_offset: np.ndarray, vert_ids: np.ndarray, n_vertices: int,
                  rows: np.ndarray | None = None) -> np.ndarray:
    """(N,V) bool: vertex v is seen in image i when a triangle hit by one of its G-buffer pixels uses it.
    ``rows`` (P,) bool optionally restricts the pixels (e.g. the skin pixels)."""
    off = np.asarray(pix_offset, np.int64)
    vid = np.asarray(vert_ids, np.int64)
    n = off.shape[0] - 1
    out = np.zeros((n, int(n_vertices)), bool)
    for i in range(n):
        v = vid[off[i]:off[i + 1]]
        if rows is not None:
            v = v[np.asarray(rows[off[i]:off[i + 1]], bool)]
        out[i, v.reshape(-1)] = True
    return out


def per_image_scale(pred: np.ndarray, truth: np.ndarray, region: np.ndarray) -> np.ndarray:
    """(N,) least-squares scales ``s_i = argmin_s Σ_{v∈region_i, c} (s·pred − truth)²`` for (N,V,3) albedos
    (1 where the region is empty or the prediction is zero)."""
    p = np.asarray(pred, np.float64)
    t = np.asarray(truth, np.float64)
    r = np.asarray(region, bool)[..., None]
    num = (p * t * r).sum(axis=(1, 2))
    den = (p * p * r).sum(axis=(1, 2))
    return np.where(den > 0, num / np.where(den > 0, den, 1.0), 1.0)


def image_metrics_table(render_linear: np.ndarray, images: np.ndarray, masks: np.ndarray, encoding: str, *,
                        lpips: LPIPS | None = None, level: float = 0.95, method: str = "t",
                        batch_size: int = 32, names: Sequence[str] | None = None) -> dict[str, Any]:
    """Per-image face-region metrics (+ CI) and the released protocol of one method.

    Args:
        render_linear: (N,S,S,3) linear predicted full shading.
        images: (N,S,S,3) uint8 images as stored in the shard (or floats in [0,1], display-encoded).
        masks: (N,S,S) bool face region.
        encoding: the shard's ``encoding`` meta.
    Returns:
        ``{"per_image": FaceMetrics, "released": dict}``.
    """
    tgt = np.asarray(images)
    tgt = tgt.astype(np.float64) / 255.0 if tgt.dtype == np.uint8 else tgt.astype(np.float64)
    pred = encode_like(render_linear, encoding)
    fm = face_region_metrics(pred, tgt, masks, lpips=lpips, level=level, method=method, names=names)
    rel = released_protocol(render_linear, tgt, masks, batch_size=batch_size, lpips=lpips)
    return {"per_image": fm, "released": rel}


def _psnr_rows(d2: np.ndarray, cnt: np.ndarray) -> np.ndarray:
    mse = d2 / np.maximum(cnt, 1)
    return np.where(mse > 0, 10 * np.log10(1.0 / np.where(mse > 0, mse, 1.0)), 100.0)


def vertex_reflectance_errors(pred_albedo: np.ndarray, pred_spec: np.ndarray | None, truth_albedo: np.ndarray,
                              truth_spec: np.ndarray | None, region: np.ndarray, *, level: float = 0.95,
                              method: str = "t") -> dict[str, Any]:
    """Per-image errors of reconstructed per-vertex reflectance, raw and per-image scaled (module docstring).

    Args:
        pred_albedo, truth_albedo: (N,V,3) linear diffuse albedo.
        pred_spec, truth_spec: (N,V) Σw and the true specular albedo (None: no specular errors).
        region: (N,V) bool vertices evaluated per image (e.g. :func:`seen_vertices`).
    Returns:
        ``{"scale": (N,) array, "per_image": {mode: {metric: (N,) array}}, "summary": {mode: {metric: ci}}}``
        with modes ``raw``/``scaled`` and metrics ``albedo_rmse``, ``albedo_rel``, ``albedo_psnr`` (+ ``spec_*``).
    """
    pa, ta = np.asarray(pred_albedo, np.float64), np.asarray(truth_albedo, np.float64)
    reg = np.asarray(region, bool)
    if pa.shape != ta.shape or pa.ndim != 3 or pa.shape[-1] != 3 or reg.shape != pa.shape[:2]:
        raise ReflectmmError(f"reflectance errors: albedo {pa.shape} vs truth {ta.shape}, region {reg.shape} "
                             "(expected (N,V,3), (N,V,3), (N,V))")
    empty = np.flatnonzero(~reg.any(1))
    if empty.size:
        raise ReflectmmError(f"reflectance errors: image #{int(empty[0])} has no evaluated vertex")
    spec = pred_spec is not None and truth_spec is not None
    if spec:
        ps, ts = np.asarray(pred_spec, np.float64), np.asarray(truth_spec, np.float64)
        if ps.shape != reg.shape or ts.shape != reg.shape:
            raise ReflectmmError(f"reflectance errors: Σw {ps.shape} / truth {ts.shape} must be {reg.shape}")
    scale = per_image_scale(pa, ta, reg)
    cnt = reg.sum(1).astype(np.float64)
    rms_t = np.sqrt((ta ** 2 * reg[..., None]).sum((1, 2)) / (3 * cnt))
    per: dict[str, dict[str, np.ndarray]] = {}
    for mode, s in (("raw", np.ones_like(scale)), ("scaled", scale)):
        d2 = (((s[:, None, None] * pa - ta) ** 2) * reg[..., None]).sum((1, 2))
        e = {"albedo_rmse": np.sqrt(d2 / (3 * cnt))}
        e["albedo_rel"] = e["albedo_rmse"] / np.where(rms_t > 0, rms_t, np.nan)
        e["albedo_psnr"] = _psnr_rows(d2, 3 * cnt)
        if spec:
            d2s = (((s[:, None] * ps - ts) ** 2) * reg).sum(1)
            rms_s = np.sqrt((ts ** 2 * reg).sum(1) / cnt)
            e["spec_rmse"] = np.sqrt(d2s / cnt)
            e["spec_rel"] = e["spec_rmse"] / np.where(rms_s > 0, rms_s, np.nan)
            e["spec_psnr"] = _psnr_rows(d2s, cnt)
        per[mode] = e
    summary = {mode: {k: mean_ci(v[np.isfinite(v)], level=level, method=method) for k, v in e.items()
                      if np.isfinite(v).any()} for mode, e in per.items()}
    return {"scale": scale, "per_image": per, "summary": summary}


def evaluate_reconstruction(pred: Mapping[str, np.ndarray], shard: Mapping[str, np.ndarray], *, encoding: str,
                            select: np.ndarray | None = None, region: str = "face", lpips: LPIPS | None = None,
                            level: float = 0.95, method: str = "t", batch_size: int = 32) -> dict[str, Any]:
    """Table 2 numbers of one method on (a subset of) one shard.

    Args:
        pred: ``render`` (N,S,S,3) linear; optional ``vertex_albedo`` (N,V,3) and ``vertex_spec`` (N,V) (or
            ``vertex_weights`` (N,V,K), summed) — per image, in the order of ``select``.
        shard: wild-shard arrays (``image``, ``face_mask``, ``skin_mask``, ``pix_offset``, ``vert_ids``, ``names``
            and, for reflectance errors, ``truth_vertex_albedo`` and ``truth_vertex_weights`` (N,V,K) / (N,V)).
        encoding: the shard's ``encoding`` meta; select: (n,) indices of the evaluated images (default all),
        region: ``"face"`` (face_mask, the paper's face region) or ``"skin"`` (skin_mask).
    Returns:
        ``{"image": image_metrics_table(...), "reflectance": vertex_reflectance_errors(...) | None,
        "n_images", "region"}``.
    """
    if region not in ("face", "skin"):
        raise ReflectmmError(f"reconstruction eval: region must be 'face' or 'skin', got {region!r}")
    n_all = int(np.asarray(shard["pix_offset"]).shape[0] - 1)
    idx = np.arange(n_all) if select is None else np.asarray(select, np.int64)
    render = np.asarray(pred["render"])
    if render.shape[0] != idx.shape[0]:
        raise ReflectmmError(f"reconstruction eval: {render.shape[0]} predicted renders for {idx.shape[0]} images")
    masks = np.asarray(shard[f"{region}_mask"])[idx]
    names = [str(x) for x in np.asarray(shard["names"])[idx]] if "names" in shard else None
    img = image_metrics_table(render, np.asarray(shard["image"])[idx], masks, encoding, lpips=lpips, level=level,
                              method=method, batch_size=batch_size, names=names)
    refl = None
    if "vertex_albedo" in pred and "truth_vertex_albedo" in shard:
        ta = np.asarray(shard["truth_vertex_albedo"])[idx]
        off = np.asarray(shard["pix_offset"], np.int64)
        vid = np.asarray(shard["vert_ids"])
        # the seen vertices of the selected images (G-buffer rows of each image, re-packed)
        rows = [np.arange(off[i], off[i + 1]) for i in idx]
        sub_off = np.concatenate([[0], np.cumsum([len(r) for r in rows])])
        sub_vid = vid[np.concatenate(rows)] if rows else vid[:0]
        seen = seen_vertices(sub_off, sub_vid, ta.shape[1])
        ps = ts = None
        if "truth_vertex_weights" in shard and ("vertex_spec" in pred or "vertex_weights" in pred):
            ts = spec_albedo_of(np.asarray(shard["truth_vertex_weights"])[idx])
            ps = spec_albedo_of(pred["vertex_spec"] if "vertex_spec" in pred else pred["vertex_weights"])
        refl = vertex_reflectance_errors(pred["vertex_albedo"], ps, ta, ts, seen, level=level, method=method)
    return {"image": img, "reflectance": refl, "n_images": int(idx.shape[0]), "region": region}


def table_row(name: str, image: Mapping[str, Any] | None = None,
              reflectance: Mapping[str, Any] | None = None) -> dict[str, str]:
    """One Table 2 row of formatted cells: PSNR / SSIM / LPIPS (mean ± CI half width), the released protocol's
    PSNR / SSIM, and the scaled and raw albedo / Σw relative errors."""
    row = {"method": name}
    if image is not None:
        fm: FaceMetrics = image["per_image"]
        row.update(fm.row())
        rel = image["released"]
        row["PSNR (released)"] = f"{rel['psnr']:.2f}"
        row["SSIM (released)"] = f"{rel['ssim']:.4f}"
    if reflectance is not None:
        for mode in ("scaled", "raw"):
            sm = reflectance["summary"][mode]
            for k, label in (("albedo_rel", "albedo rel"), ("spec_rel", "Σw rel")):
                if k in sm:
                    row[f"{label} ({mode})"] = format_ci(sm[k], 3)
    return row


def markdown_table(rows: Sequence[Mapping[str, str]], align: str | None = None) -> str:
    """Rows of cells (same keys, in order of the first row) → a Markdown table (no trailing newline).

    ``align``: one letter per column, ``l`` (the default for every column) or ``r`` (right-aligned, ``---:``).
    """
    if not rows:
        return ""
    cols = list(rows[0].keys())
    for r in rows[1:]:
        cols += [k for k in r if k not in cols]
    if align is not None and (len(align) != len(cols) or set(align) - {"l", "r"}):
        raise ValueError(f"markdown_table: align {align!r} is not one of l/r per column ({len(cols)} columns)")
    rule = "|" + "".join("---:|" if a == "r" else "---|" for a in (align or "l" * len(cols)))
    lines = ["| " + " | ".join(cols) + " |", rule]
    lines += ["| " + " | ".join(str(r.get(c, "")) for c in cols) + " |" for r in rows]
    return "\n".join(lines)
