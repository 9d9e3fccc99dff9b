"""The paper's baseline reflectance models, rebuilt in the synthetic world from ground truth (docs/design.md §8).

Both are ``reflectance-model`` artifacts of the same kind as ``build-pca``'s
(:func:`reflectmm_cli.model.fit_reflectance_pca` + :func:`reflectmm_cli.model.model_arrays`), so ``render``,
``finetune``, ``reconstruct`` and ``evaluate`` read them unchanged. Their data are the **ground-truth** maps of
``synth multipie`` identities (``synth-truth`` artifacts: ``albedo`` (3,S,S) linear diffuse albedo,
``spec_albedo`` (S,S) the GGX directional albedo at normal view, ``uv_mask`` (S,S)) — the role of the scans the
real baselines were built from (BFM09: 200 laser scans; AlbedoMM: Light Stage captures), where our own model is
built from fitted maps of images.

* **BFM09's role — diffuse only** (:func:`diffuse_only_model`): PCA of the diffuse albedo. Representation of
  "no specular": ONE lobe (K = 1, exponent :data:`DIFFUSE_ONLY_EXPONENT` = 1) whose mean and bases are all zero.
  K = 0 is not used because the shading core requires K ≥ 1 (``shade_directional``/``shade_env`` refuse an empty
  exponent list) and finetuning gathers a (Nv,K) weight array; an all-zero lobe costs no work in ``shade_env``
  (lobes whose weights are all zero are skipped) and makes the specular layer exactly 0. The artifact's meta says
  ``baseline = "diffuse-only"``; :func:`is_diffuse_only` recognises such a model from its arrays.
* **AlbedoMM's role — specular albedo + one global Blinn-Phong exponent** (:func:`global_exponent_model`):
  PCA of the diffuse albedo with the specular albedo carried by the same combination of training samples
  (AlbedoMM's transfer, as in ``build-pca``), one lobe (K = 1) of exponent 20 whose weight IS the specular
  albedo: w = ``spec_albedo``, so Σw = the specular albedo (the lobe is normalised so that under uniform unit
  radiance seen head-on it shades to w). Grey (white) specular, as in our model; AlbedoMM's specular albedo is
  RGB but nearly grey.
"""
from __future__ import annotations

from pathlib import Path
from typing import Any, Callable, Mapping, Sequence

import numpy as np

from reflectmm_cli.errors import ReflectmmError
from reflectmm_cli.model.pca import MODEL_KIND, ReflectanceModel, add_vertex_model, fit_reflectance_pca, model_arrays
from reflectmm_cli.shading.exponents import ExponentError, check_exponents

__all__ = ["DIFFUSE_ONLY_EXPONENT", "ALBEDOMM_EXPONENT", "BASELINES", "truth_maps",
           "diffuse_only_model", "global_exponent_model", "build_baseline", "is_diffuse_only",
           "write_baseline_model"]

#: exponent of the single all-zero lobe of a diffuse-only model (irrelevant to the shading: the weights are 0).
DIFFUSE_ONLY_EXPONENT = 1.0
#: the AlbedoMM baseline's global Blinn-Phong exponent (the paper's "spec albedo + shininess 20").
ALBEDOMM_EXPONENT = 20.0
#: baseline name → (description, role)
BASELINES = {"diffuse-only": ("Lambertian PCA of ground-truth diffuse albedo", "BFM09"),
             "albedomm": ("PCA of ground-truth diffuse + specular albedo, one Blinn-Phong exponent 20", "AlbedoMM"),
             "oracle": ("PCA of the wild training identities' true per-vertex diffuse albedo and lobe weights",
                        "the oracle of finetuning (a ceiling, not a method)")}


def truth_maps(truth: Mapping[str, np.ndarray], name: str = "") -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(albedo (3,S,S) float32, spec_albedo (S,S) float32, mask (S,S) bool) from a ``synth-truth`` mapping."""
    for k in ("albedo", "spec_albedo"):
        if k not in truth:
            raise ReflectmmError(f"{name}: truth has no '{k}' array (a synth multipie truth file is needed)")
    a = np.asarray(truth["albedo"], np.float32)
    s = np.asarray(truth["spec_albedo"], np.float32)
    if a.ndim != 3 or a.shape[0] != 3 or s.shape != a.shape[1:]:
        raise ReflectmmError(f"{name}: truth albedo {a.shape} / spec_albedo {s.shape} are not (3,S,S) / (S,S)")
    m = np.asarray(truth["uv_mask"], bool) if "uv_mask" in truth else np.ones(s.shape, bool)
    return a, s, m


def _build(truths, weights_fn, exponent, components, ids, vertex_uv, log, baseline) -> ReflectanceModel:
    albedos, weights, masks = [], [], []
    names = list(ids) if ids is not None else [f"#{i}" for i in range(len(truths))]
    for t, nm in zip(truths, names):
        a, s, m = truth_maps(t, nm)
        albedos.append(a)
        weights.append(weights_fn(s))
        masks.append(m)
    model = fit_reflectance_pca(albedos, weights, [exponent], masks=masks, components=components, ids=names,
                                log=log)
    model.stats["baseline"] = baseline
    if vertex_uv is not None:
        add_vertex_model(model, vertex_uv)
    return model


def diffuse_only_model(truths: Sequence[Mapping[str, np.ndarray]], components: int = 80,
                       ids: Sequence[str] | None = None, vertex_uv: np.ndarray | None = None,
                       log: Callable[[str], Any] | None = None) -> ReflectanceModel:
    """BFM09's role: PCA of the truths' diffuse albedo; one all-zero lobe (module docstring).
    ``vertex_uv`` (Nv,2): the face model's vertex UVs, to add the per-vertex model."""
    return _build(truths, lambda s: np.zeros((1,) + s.shape, np.float32), DIFFUSE_ONLY_EXPONENT, components, ids,
                  vertex_uv, log, "diffuse-only")


def global_exponent_model(truths: Sequence[Mapping[str, np.ndarray]], exponent: float = ALBEDOMM_EXPONENT,
                          components: int = 80, ids: Sequence[str] | None = None,
                          vertex_uv: np.ndarray | None = None,
                          log: Callable[[str], Any] | None = None) -> ReflectanceModel:
    """AlbedoMM's role: PCA of the diffuse albedo, specular albedo transferred with the same sample combination,
    one lobe of ``exponent`` with weight = specular albedo (Σw = spec albedo)."""
    try:  # the one exponent check, its positivity rule (a baseline lobe may be as sharp as it likes)
        check_exponents([exponent], max_exponent=None, distinct=False)
    except ExponentError:
        raise ReflectmmError(f"baseline: the global exponent must be > 0, got {exponent}") from None
    return _build(truths, lambda s: s[None].astype(np.float32), float(exponent), components, ids, vertex_uv, log,
                  "albedomm")


def build_baseline(kind: str, truths, **kw) -> ReflectanceModel:
    """``kind`` ∈ :data:`BASELINES` → the model (keyword arguments as the two builders)."""
    if kind == "diffuse-only":
        kw.pop("exponent", None)
        return diffuse_only_model(truths, **kw)
    if kind == "albedomm":
        return global_exponent_model(truths, **kw)
    raise ReflectmmError(f"unknown baseline {kind!r} (one of {', '.join(BASELINES)})")


def is_diffuse_only(model) -> bool:
    """True when every lobe weight of the model (mean and all bases) is exactly zero."""
    get = (lambda k: getattr(model, k)) if isinstance(model, ReflectanceModel) else (lambda k: model[k])
    return not np.any(np.asarray(get("weights_mean"))) and not np.any(np.asarray(get("weights_basis")))


def write_baseline_model(model: ReflectanceModel, path: str | Path, *, params: Mapping[str, Any] | None = None,
                         inputs: list | None = None, producer: Mapping[str, Any] | None = None,
                         cache_key: str | None = None, face_model: Mapping[str, Any] | None = None) -> Path:
    """Write the baseline as a ``reflectance-model`` artifact (meta as build-pca's plus ``baseline``/``role``)."""
    from reflectmm_cli.artifacts import write_artifact

    kind = model.stats.get("baseline", "")
    desc, role = BASELINES.get(kind, ("", ""))
    extra = {"n_identities": len(model.ids), "n_components": model.n_components, "stats": model.stats,
             "ids": model.ids, "baseline": kind, "role": role,
             "data": ("ground-truth per-vertex reflectance (synth wild, train split)" if kind == "oracle"
                      else "ground-truth maps (synth-truth)"),
             "method": desc + "; PCA as build-pca (specular bases = the same combination of training samples)",
             "face_model": dict(face_model) if face_model else None}
    return write_artifact(path, MODEL_KIND, model_arrays(model), params=dict(params or {}), inputs=inputs,
                          producer=producer, cache_key=cache_key, extra_meta=extra)
