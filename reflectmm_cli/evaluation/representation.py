"""The representation comparison — the paper's Table 1 on our own data (docs/design.md §1 step 8).

Protocol (documented in docs/model.md):

* Input: one ``uv-observations`` mapping per identity.
* Held-out set: every (view, flash) pair whose flash id is in ``holdout`` (default flashes ``05`` and ``09``:
  the flashes on cameras 13_0 and 04_1, ±30° from frontal), all views. Everything else is training data.
* Every representation is fitted on the *same* training pairs with ``reflectance.fit_maps(..., pair_mask=...)``
  (same solver, symmetry, symmetry mode, loss and prior): K = 1 with a global exponent p ∈ {8, 16, 32, 64}, the
  3-lobe default (1, 8, 64), and the paper's baselines "diffuse only" (C alone, the same loss, solved here per texel) and
  "spec albedo + global shininess 20" (K = 1, p = 20 — a white specular albedo with one global exponent, which
  is exactly our K = 1 representation with p = 20).
* Re-rendering in **UV space** (no ``image_space``): for each held-out pair the fitted maps are shaded with
  :func:`reflectmm_cli.shading.shade_directional` at the texel positions/normals of the observations (point
  flash, ``E = I/d²``) and compared with the observed radiance over the texels observed in that pair. In
  **image space** (``image_space`` renderers, :mod:`.image_space`): the fitted mesh is ray cast into the capture
  windows and compared with the captured OLAT images over face ∧ inside the maps' domain (the observations'
  mask, the same for every representation) ∧ lit ∧ n·v > 0 ∧ unsaturated pixels.
* Metrics per held-out pair on the display encoding ``clip(x,0,1)^(1/1.2)`` (peak 1): PSNR, SSIM (and LPIPS if
  weights are given), region = texels observed in that pair; reported as the mean over held-out pairs, then the
  mean over identities.
"""
from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import Any, Callable, Mapping, Sequence

import numpy as np

from reflectmm_cli.errors import ReflectmmError

from .metrics import LPIPS, encode_for_metrics, psnr, ssim

__all__ = ["Representation", "parse_exponent_sets", "default_representations", "holdout_problem",
           "holdout_pairs", "render_pairs_uv", "fit_diffuse_only", "compare_representations", "RepresentationResult",
           "comparison_table", "comparison_figure", "DEFAULT_HOLDOUT"]

DEFAULT_HOLDOUT = ("05", "09")


@dataclass(frozen=True)
class Representation:
    """A fitted representation: a name and its lobe exponents (empty = diffuse only)."""

    name: str
    exponents: tuple[float, ...]


def parse_exponent_sets(text: str) -> list[Representation]:
    """``"8;16;32;64;1,8,64"`` → K = 1 reps with p = 8…64 and the 3-lobe set; ``diffuse`` / ``0`` = diffuse only.

    Each set is a comma list (:func:`reflectmm_cli.params.parse_list`) checked by
    :func:`reflectmm_cli.shading.brdf.check_exponents` (positive, bounded, no collinear lobes)."""
    from reflectmm_cli.params import ParamError, parse_list
    from reflectmm_cli.shading.brdf import check_exponents

    reps = []
    for tok in parse_list(text, "--exponents-sets", sep=";"):
        if tok.lower() in ("diffuse", "0", "none"):
            reps.append(Representation("diffuse only", ()))
            continue
        try:
            exps = tuple(parse_list(tok, "--exponents-sets", float))
        except ParamError:
            raise ReflectmmError(f"--exponents-sets: cannot parse {tok!r} (use e.g. \"8;16;32;64;1,8,64\")") from None
        try:
            check_exponents(exps)
        except ValueError as exc:
            raise ReflectmmError(f"--exponents-sets: {tok!r}: {exc}") from None
        name = (f"global p={exps[0]:g}" if len(exps) == 1 else f"{len(exps)}-lobe ({','.join(f'{p:g}' for p in exps)})")
        reps.append(Representation(name, exps))
    if not reps:
        raise ReflectmmError("--exponents-sets: no representation given")
    return reps


def default_representations(sets: str = "8;16;32;64;1,8,64", baselines: bool = True) -> list[Representation]:
    reps = parse_exponent_sets(sets)
    if baselines:
        names = {r.name for r in reps}
        if "diffuse only" not in names:
            reps.append(Representation("diffuse only", ()))
        reps.append(Representation("spec albedo + shininess 20", (20.0,)))
    return reps


def holdout_problem(flash_ids, holdout: Sequence[str]) -> str | None:
    """Why the flashes ``holdout`` cannot be held out of observations with the flashes ``flash_ids`` (one of them
    is missing, or nothing would be left to fit); None when they can."""
    fids = [str(f) for f in np.asarray(flash_ids).reshape(-1)]
    missing = [h for h in holdout if h not in fids]
    if missing:
        return f"flash id(s) {', '.join(missing)} not in the observations (flashes: {', '.join(fids)})"
    if len(set(holdout)) >= len(fids):
        return "holding out every flash leaves nothing to fit"
    return None


def holdout_pairs(obs: Mapping[str, np.ndarray], holdout: Sequence[str] = DEFAULT_HOLDOUT) -> np.ndarray:
    """(P,) bool: pairs whose flash id is in ``holdout``. Refuses ids the observations do not have
    (:func:`holdout_problem`)."""
    why = holdout_problem(obs["flash_ids"], holdout)
    if why is not None:
        raise ReflectmmError(f"--holdout: {why}")
    fids = [str(f) for f in np.asarray(obs["flash_ids"]).reshape(-1)]
    hold_f = np.array([f in set(holdout) for f in fids])
    return hold_f[np.asarray(obs["pair_flash"], np.int64)]


def pair_geometry(obs, j, texels=None):
    """Light direction (to the flash), view direction (to the camera), both unnormalised, and the flash's
    irradiance at normal incidence (inverse square) of pair ``j`` at every texel ((S,S,3), (S,S,3), (S,S)), or at
    the flat texel indices ``texels`` only ((T,3), (T,3), (T,))."""
    pos = np.asarray(obs["position"], np.float64)
    if texels is not None:
        pos = pos.reshape(-1, 3)[texels]
    f = int(obs["pair_flash"][j])
    v = int(obs["pair_view"][j])
    ld = np.asarray(obs["flash_pos"], np.float64)[f] - pos
    vd = np.asarray(obs["cam_centers"], np.float64)[v] - pos
    E = float(np.asarray(obs["flash_intensity"], np.float64).reshape(-1)[f]) / np.maximum(
        np.sum(ld * ld, -1), 1e-12)
    return ld, vd, E


def render_pairs_uv(albedo: np.ndarray, weights: np.ndarray | None, exponents: Sequence[float],
                    obs: Mapping[str, np.ndarray], pairs: Sequence[int]) -> np.ndarray:
    """(len(pairs), S, S, 3) radiance of the maps for the given pairs with the shading core (UV space).

    ``albedo`` (3,S,S), ``weights`` (K,S,S) or None/empty for diffuse only. Texels outside the mask are 0.
    """
    from reflectmm_cli.shading import shade_directional

    c = np.moveaxis(np.asarray(albedo, np.float64), 0, -1)
    nrm = np.asarray(obs["normal"], np.float64)
    mask = np.asarray(obs["mask"], bool)
    if weights is None or len(exponents) == 0:
        w, p = np.zeros(c.shape[:2] + (1,)), np.array([1.0])
    else:
        w, p = np.moveaxis(np.asarray(weights, np.float64), 0, -1), np.asarray(exponents, np.float64)
    out = np.zeros((len(pairs),) + c.shape, np.float64)
    for i, j in enumerate(pairs):
        ld, vd, E = pair_geometry(obs, j)
        s = shade_directional(c, w, p, nrm, ld, vd, np.repeat(E[..., None], 3, -1))
        out[i] = np.where(mask[..., None], s, 0.0)
    return out


def _weighted_median(vals: np.ndarray, wts: np.ndarray) -> np.ndarray:
    """Row-wise weighted median (the minimiser of Σ w |x − v|); rows with no weight give 0."""
    order = np.argsort(vals, axis=1)
    v = np.take_along_axis(vals, order, 1)
    w = np.take_along_axis(wts, order, 1)
    cw = np.cumsum(w, 1)
    tot = cw[:, -1:]
    k = np.argmax(cw >= 0.5 * tot, axis=1)
    out = v[np.arange(v.shape[0]), k]
    return np.where(tot[:, 0] > 0, out, 0.0)


def fit_diffuse_only(obs: Mapping[str, np.ndarray], pair_mask: np.ndarray | None = None, symmetry: float = 1.0,
                     loss: str = "l1", symmetry_mode: str = "ill-posed") -> np.ndarray:
    """Diffuse-only baseline: per texel and channel the C ≥ 0 minimising the cos-weighted L1 misfit
    ``Σ_j ⟨l_j,n⟩ |d_j C − I_j|`` (weighted median of I/d with weights ⟨l,n⟩·d; ``loss="l2"``: the weighted
    least-squares ``Σ ⟨l,n⟩ d I / Σ ⟨l,n⟩ d²``) over the training pairs, the mirror texel's
    observations pooled with weight ``symmetry`` (as fit-reflectance's mirror pooling: in ``symmetry_mode``
    ``ill-posed`` only for texels without an observation of their own — C alone needs one —, ``all``: every
    texel; ``adaptive`` is treated as ``ill-posed`` by this baseline: it has no per-texel noise estimate to
    measure asymmetry with). Texels of the mask with no observation of their own or of their mirror are filled
    from their solved neighbours, as fit-reflectance fills its flagged texels (:func:`fill_flagged`), so that the
    baselines cover the same texels. Returns (3,S,S)."""
    from reflectmm_cli.reflectance.design import design_columns, mirror_index
    from reflectmm_cli.reflectance.fit import fill_flagged

    S = np.asarray(obs["position"]).shape[0]
    P = np.asarray(obs["pair_view"]).shape[0]
    pm = np.ones(P, bool) if pair_mask is None else np.asarray(pair_mask, bool)
    sel = np.flatnonzero(pm)
    mask = np.asarray(obs["mask"], bool).reshape(-1)
    observed = np.asarray(obs["observed"], bool).reshape(P, -1)[sel].T  # (S², P')
    des = design_columns(np.asarray(obs["position"]).reshape(-1, 3), np.asarray(obs["normal"]).reshape(-1, 3),
                         obs["cam_centers"], obs["flash_pos"], obs["flash_intensity"],
                         np.asarray(obs["pair_view"])[sel], np.asarray(obs["pair_flash"])[sel], [1.0], observed)
    d = des.diffuse  # (S², P')
    cw = des.cos_l  # the paper's per-observation weight ⟨l, n⟩ (as fit_maps)
    rad = np.asarray(obs["radiance"], np.float64).reshape(P, S * S, 3)[sel].transpose(1, 0, 2)  # (S², P', 3)
    mir = mirror_index(S)
    if symmetry_mode not in ("adaptive", "ill-posed", "all"):
        raise ReflectmmError(f"symmetry_mode must be 'adaptive', 'ill-posed' or 'all', got {symmetry_mode!r}")
    if symmetry:
        d2 = np.concatenate([d, d[mir]], 1)
        r2 = np.concatenate([rad, rad[mir]], 1)
        sv = np.full((S * S, 1), float(symmetry))
        if symmetry_mode in ("ill-posed", "adaptive"):
            sv[(d > 0).sum(1) > 0] = 0.0
        wt = np.concatenate([cw, sv * cw[mir]], 1)
    else:
        d2, r2, wt = d, rad, cw
    out = np.zeros((S * S, 3))
    ok = d2 > 0
    for ch in range(3):
        if loss == "l1":
            vals = np.where(ok, r2[..., ch] / np.where(ok, d2, 1.0), 0.0)
            out[:, ch] = _weighted_median(vals, np.where(ok, d2 * wt, 0.0))
        else:
            num = (wt * d2 * r2[..., ch]).sum(1)
            den = (wt * d2 * d2).sum(1)
            out[:, ch] = np.where(den > 0, num / np.where(den > 0, den, 1.0), 0.0)
    out = np.clip(out, 0.0, None)
    out[~mask] = 0.0
    out = out.T.reshape(3, S, S)
    solved = (ok.any(1) & mask).reshape(S, S)
    empty = mask.reshape(S, S) & ~solved
    if empty.any() and solved.any():
        out, _ = fill_flagged(out, solved, empty, 0.0, np.zeros_like(out))
    return out


@dataclass
class RepresentationResult:
    """Results of :func:`compare_representations` (R representations, N identities, H held-out pairs each)."""

    representations: list[Representation]
    ids: list[str]
    holdout: list[str]
    psnr: np.ndarray  # (N, R) mean over held-out pairs
    ssim: np.ndarray  # (N, R)
    lpips: np.ndarray | None  # (N, R) or None when no LPIPS weights
    psnr_pairs: np.ndarray  # (N, R, H) H the most held-out pairs of an identity; NaN beyond an identity's own
    ssim_pairs: np.ndarray  # (N, R, H)
    train_psnr: np.ndarray  # (N, R) PSNR on the training pairs (fit quality)
    fit_seconds: np.ndarray  # (N, R)
    n_holdout_pairs: int  # the most held-out pairs of an identity (H)
    figure: dict[str, Any] = field(default_factory=dict)  # renders of the first identity for the figure
    space: str = "uv"
    #: (N,) image space: fraction of lit face pixels of the held-out pairs left out because their UV footprint
    #: leaves the maps' domain (NaN in UV space)
    outside_domain: np.ndarray | None = None
    #: (N,) held-out pairs per identity: identities whose captures keep different views (a detector's
    #: landmarks place different views per identity) hold different numbers of them
    pairs_per_identity: np.ndarray | None = None

    def mean(self, what: str = "psnr") -> np.ndarray:
        arr = getattr(self, what)
        return None if arr is None else np.nanmean(arr, axis=0)


def _default_fit(obs, exponents, pair_mask, **kw):
    from reflectmm_cli.reflectance.fit import fit_maps

    maps = fit_maps(obs, exponents=tuple(exponents), pair_mask=pair_mask, **kw)
    return np.asarray(maps.albedo, np.float64), np.asarray(maps.weights, np.float64)


def _metrics(pred, truth, observed, lp: LPIPS | None):
    P = pred.shape[0]
    out = np.zeros((3, P))
    for i in range(P):
        m = observed[i]
        if not m.any():
            out[:, i] = np.nan
            continue
        a, b = encode_for_metrics(pred[i]), encode_for_metrics(truth[i])
        out[0, i] = psnr(a, b, m)
        out[1, i] = ssim(a, b, m)
        out[2, i] = lp(a, b, m) if lp is not None else np.nan
    return out


def compare_representations(observations: Sequence[Mapping[str, np.ndarray]], ids: Sequence[str],
                            representations: Sequence[Representation] | None = None,
                            holdout: Sequence[str] = DEFAULT_HOLDOUT, lpips: LPIPS | None = None,
                            fit_kwargs: Mapping[str, Any] | None = None,
                            fit_fn: Callable | None = None, progress: Callable = lambda it, **k: it,
                            figure_pair: tuple[str, str] | None = None,
                            image_space: Sequence[Any] | None = None) -> RepresentationResult:
    """Fit every representation on the training pairs of every identity and score the held-out pairs.

    Args:
        observations: per identity a uv-observations mapping.
        ids: identity names (same order).
        representations: default :func:`default_representations`.
        holdout: flash ids held out (all views).
        lpips: an :class:`LPIPS` with weights, or None (no LPIPS).
        fit_kwargs: passed to ``fit_maps`` (solver, symmetry, loss, prior) for every representation; symmetry
            and loss are also used by the diffuse-only baseline.
        fit_fn: ``fit_fn(obs, exponents, pair_mask, **fit_kwargs) -> (albedo, weights)`` (default: fit_maps).
        figure_pair: (view name, flash id) of the pair shown in the figure (default: the held-out pair of the
            most frontal view with the first held-out flash).
        image_space: per identity an :class:`~reflectmm_cli.evaluation.image_space.ImageSpaceRenderer`; then
            every pair is re-rendered in image space and compared with the captured OLAT image (else UV space).
    """
    reps = list(representations or default_representations())
    fit_fn = fit_fn or _default_fit
    kw = dict(fit_kwargs or {})
    N, R = len(observations), len(reps)
    if N == 0:
        raise ReflectmmError("evaluate representation: no identities")
    ps, ss, lp, tp, secs = (np.full((N, R), np.nan) for _ in range(5))
    per_pair_p, per_pair_s = [], []
    outside = np.full(N, np.nan)
    fig: dict[str, Any] = {}
    n_pairs = np.zeros(N, np.int64)
    for n, (obs, ident) in enumerate(progress(list(zip(observations, ids)), desc="identities")):
        held = holdout_pairs(obs, holdout)
        train = ~held
        hp = np.flatnonzero(held)
        tr = np.flatnonzero(train)
        H = n_pairs[n] = hp.size
        isr = image_space[n] if image_space is not None else None
        if isr is not None and hasattr(isr, "set_domain"):
            isr.set_domain(np.asarray(obs["mask"], bool))  # the maps of every representation are defined there
        vnames = [str(x) for x in np.asarray(obs["view_names"])]
        fnames = [str(x) for x in np.asarray(obs["flash_ids"])]
        pair_name = lambda j: (vnames[int(obs["pair_view"][j])], fnames[int(obs["pair_flash"][j])])  # noqa: E731
        if isr is None:
            truth = np.asarray(obs["radiance"], np.float64)
            observed = np.asarray(obs["observed"], bool)
        else:
            sub_t = tr[:: max(1, tr.size // 12)]
            truth, observed = {}, {}
            for j in np.concatenate([hp, sub_t]):
                truth[j] = isr.target(*pair_name(j))
                observed[j] = isr.region(*pair_name(j))

        def render(alb, wts, exps, pairs, key):
            if isr is None:
                return render_pairs_uv(alb, wts, exps, obs, pairs)
            return np.stack([isr.render(alb, wts, exps, *pair_name(j), key=key) for j in pairs])

        def stack(d, pairs):
            return d[pairs] if isr is None else np.stack([d[j] for j in pairs])

        if isr is not None and hasattr(isr, "set_domain"):
            kept = sum(int(observed[j].sum()) for j in hp)
            isr.set_domain(None)
            lit_all = sum(int(isr.region(*pair_name(j)).sum()) for j in hp)
            isr.set_domain(np.asarray(obs["mask"], bool))
            outside[n] = 1.0 - kept / lit_all if lit_all else np.nan
        if not stack(observed, hp).any():
            raise ReflectmmError(f"evaluate representation: identity {ident}: no observed texel in the held-out "
                                 "pairs")
        pp, sp = np.full((R, H), np.nan), np.full((R, H), np.nan)
        if n == 0:
            fj = _figure_pair_index(obs, hp, figure_pair)
            fig = {"identity": ident, "pair": int(fj), "truth": stack(truth, [fj])[0], "mask": stack(observed, [fj])[0],
                   "view": str(np.asarray(obs["view_names"])[int(obs["pair_view"][fj])]),
                   "flash": str(np.asarray(obs["flash_ids"])[int(obs["pair_flash"][fj])]), "renders": []}
        for r, rep in enumerate(reps):
            t0 = time.perf_counter()
            if rep.exponents:
                alb, wts = fit_fn(obs, rep.exponents, train, **kw)
            else:
                alb = fit_diffuse_only(obs, train, symmetry=float(kw.get("symmetry", 1.0)),
                                       loss=str(kw.get("loss", "l1")),
                                       symmetry_mode=str(kw.get("symmetry_mode", "ill-posed")))
                wts = None
            secs[n, r] = time.perf_counter() - t0
            pred = render(alb, wts, rep.exponents, hp, r + 1000 * n)
            m = _metrics(pred, stack(truth, hp), stack(observed, hp), lpips)
            pp[r], sp[r] = m[0], m[1]
            ps[n, r], ss[n, r] = np.nanmean(m[0]), np.nanmean(m[1])
            if lpips is not None:
                lp[n, r] = np.nanmean(m[2])
            # fit quality on (a subsample of) the training pairs
            sub = tr[:: max(1, tr.size // 12)]
            pr_t = render(alb, wts, rep.exponents, sub, r + 1000 * n)
            vals = [psnr(encode_for_metrics(pr_t[i]), encode_for_metrics(truth[j]), observed[j])
                    for i, j in enumerate(sub) if observed[j].any()]
            tp[n, r] = float(np.mean(vals)) if vals else np.nan
            if n == 0:
                k = int(np.flatnonzero(hp == fig["pair"])[0])
                fig["renders"].append((rep.name, pred[k]))
        per_pair_p.append(pp)
        per_pair_s.append(sp)
    H = int(n_pairs.max())
    pad = lambda a: np.pad(a, ((0, 0), (0, H - a.shape[1])), constant_values=np.nan)  # noqa: E731
    return RepresentationResult(reps, list(ids), list(holdout), ps, ss, lp if lpips is not None else None,
                                np.stack([pad(a) for a in per_pair_p]), np.stack([pad(a) for a in per_pair_s]),
                                tp, secs, H, fig, space="uv" if image_space is None else "image",
                                outside_domain=outside, pairs_per_identity=n_pairs)


def _figure_pair_index(obs, hp, figure_pair):
    names = [str(x) for x in np.asarray(obs["view_names"])]
    fids = [str(x) for x in np.asarray(obs["flash_ids"])]
    if figure_pair is not None:
        for j in hp:
            if names[int(obs["pair_view"][j])] == figure_pair[0] and fids[int(obs["pair_flash"][j])] == figure_pair[1]:
                return int(j)
        raise ReflectmmError(f"figure pair {figure_pair} is not a held-out pair")
    # most frontal view: the camera centre with the largest z relative to its distance
    cams = np.asarray(obs["cam_centers"], np.float64)
    frontal = int(np.argmax(cams[:, 2] / np.linalg.norm(cams, axis=1)))
    cand = [int(j) for j in hp if int(obs["pair_view"][j]) == frontal]
    if not cand:
        cand = [int(hp[0])]
    counts = [np.asarray(obs["observed"])[j].sum() for j in cand]
    return cand[int(np.argmax(counts))]


def comparison_table(res: RepresentationResult) -> str:
    """The comparison as a markdown table (mean over identities; best value per column in bold) and its footnote."""
    from .reconstruction_eval import markdown_table

    has_lp = res.lpips is not None
    mp, ms = res.mean("psnr"), res.mean("ssim")
    ml = res.mean("lpips") if has_lp else None
    mt, sec = res.mean("train_psnr"), res.mean("fit_seconds")
    bp, bs = np.nanargmax(mp), np.nanargmax(ms)
    bl = int(np.nanargmin(ml)) if has_lp else -1
    rows = []
    for r, rep in enumerate(res.representations):
        b = lambda s, ok: f"**{s}**" if ok else s  # noqa: E731
        rows.append({"representation": rep.name, "PSNR (dB) ↑": b(f"{mp[r]:.2f}", r == bp),
                     "SSIM ↑": b(f"{ms[r]:.4f}", r == bs),
                     "LPIPS ↓": b(f"{ml[r]:.4f}", r == bl) if has_lp else "off",
                     "train PSNR (dB)": f"{mt[r]:.2f}", "fit time (s)": f"{sec[r]:.2f}"})
    where = ("re-rendered in UV space over the texels observed in each held-out pair" if res.space == "uv" else
             "re-rendered in image space (fitted mesh ray cast into the capture windows) against the captured OLAT "
             "images over face ∧ inside the maps' UV domain ∧ lit ∧ unsaturated pixels")
    counts = res.pairs_per_identity if res.pairs_per_identity is not None else [res.n_holdout_pairs]
    lo, hi = int(np.min(counts)), int(np.max(counts))
    pairs = f"{hi} pairs per identity" if lo == hi else (
        f"{lo}–{hi} pairs per identity, each identity's mean over its own; their captures keep different views")
    foot = (f"\n{len(res.ids)} identities ({', '.join(res.ids)}); held-out flashes {', '.join(res.holdout)} "
            f"(all views, {pairs}); {where}; metrics on clip(x,0,1)^(1/1.2), peak 1.")
    if res.space == "image" and res.outside_domain is not None and np.isfinite(res.outside_domain).any():
        foot += (f" Lit face pixels left out because their UV lookup leaves the maps' domain: "
                 f"{100 * np.nanmean(res.outside_domain):.2f} % (mean over identities).")
    if not has_lp:
        foot += " LPIPS: off (no weights given)."
    return markdown_table(rows, align="lrrrrr") + "\n" + foot + "\n"


def margin_of_multilobe(res: RepresentationResult) -> dict[str, Any] | None:
    """PSNR/SSIM margin of the best multi-lobe representation over the best global-exponent one (K = 1)."""
    mp, ms = res.mean("psnr"), res.mean("ssim")
    multi = [r for r, rep in enumerate(res.representations) if len(rep.exponents) > 1]
    glob = [r for r, rep in enumerate(res.representations) if len(rep.exponents) == 1]
    if not multi or not glob:
        return None
    m = max(multi, key=lambda r: mp[r])
    g = max(glob, key=lambda r: mp[r])
    gs = max(glob, key=lambda r: ms[r])
    per_id = res.psnr[:, m][:, None] - res.psnr[:, glob]
    return {"multilobe": res.representations[m].name, "best_global": res.representations[g].name,
            "psnr_margin_db": float(mp[m] - mp[g]), "ssim_margin": float(ms[m] - ms[gs]),
            "beats_every_global_psnr": bool(np.all(mp[m] > mp[glob])),
            "beats_every_global_ssim": bool(np.all(ms[m] > ms[glob])),
            "identities_where_multilobe_wins_psnr": int(np.sum(np.all(per_id > 0, axis=1)))}


def comparison_figure(res: RepresentationResult, scale: int = 2, err_max: float = 0.05,
                      labels: Sequence[str] | None = None) -> np.ndarray:
    """Figure (H,W,3) in [0,1]: top row truth | each representation (display encoding), bottom row the absolute
    error of each (display encoding, mean over channels; ``err_max`` → full scale, i.e. ×20 by default, through
    :func:`.figures.error_colormap`, the ramp of every error figure) over the observed texels; a label above each
    column."""
    import cv2

    from .figures import error_colormap

    fig = res.figure
    if not fig:
        raise ReflectmmError("no figure data")
    m = fig["mask"]
    tr = encode_for_metrics(fig["truth"])
    tiles_top = [np.where(m[..., None], tr, 0.0)]
    tiles_bot = [np.zeros_like(tr)]
    for _name, img in fig["renders"]:
        e = encode_for_metrics(img)
        tiles_top.append(np.where(m[..., None], e, 0.0))
        err = np.abs(e - tr).mean(-1)
        tiles_bot.append(np.where(m[..., None], error_colormap(err, err_max), 0.0))
    names = ["truth"] + list(labels if labels is not None else [n for n, _ in fig["renders"]])
    S = tr.shape[0]
    size = max(S * scale, 96)
    pad, lab_h = 2, 16
    cols = []
    for name, top, bot in zip(names, tiles_top, tiles_bot):
        t = [cv2.resize(x.astype(np.float32), (size, size), interpolation=cv2.INTER_NEAREST) for x in (top, bot)]
        label = np.full((lab_h, size, 3), 255, np.uint8)
        txt = name if len(name) <= size // 6 else name[: size // 6 - 1] + "."
        cv2.putText(label, txt, (2, lab_h - 4), cv2.FONT_HERSHEY_SIMPLEX, 0.33, (0, 0, 0), 1, cv2.LINE_AA)
        label = label.astype(np.float32) / 255.0
        col = np.concatenate([label, t[0], np.ones((pad, size, 3), np.float32), t[1]], 0)
        cols.append(np.pad(col, ((pad, pad), (pad, pad), (0, 0)), constant_values=1.0))
    return np.concatenate(cols, 1)
