"""Table 1 of two evaluate-representation runs (e.g. the single- and the two-lobe skin, benchmarks/skin_table1.toml)
with per-identity paired differences and 95 % t-intervals over identities.

    python benchmarks/bench_skin_table1.py A.npz B.npz [--labels single,two-lobe]

Prints markdown: per run the mean PSNR / SSIM of every representation, the per-identity PSNR of the 3-lobe
representation minus that of each global exponent and of the best global exponent (chosen per run on the mean),
each as mean [95 % CI] over identities.
"""
from __future__ import annotations

import argparse
import sys

import numpy as np


def t_interval(x: np.ndarray, level: float = 0.95) -> tuple[float, float, float]:
    """(mean, low, high) of the t-interval of the mean of ``x`` (n ≥ 2)."""
    from scipy import stats

    x = np.asarray(x, np.float64)
    n = len(x)
    m = float(x.mean())
    if n < 2:
        return m, float("nan"), float("nan")
    h = float(stats.t.ppf(0.5 + level / 2, n - 1) * x.std(ddof=1) / np.sqrt(n))
    return m, m - h, m + h


def load(path):
    from reflectmm_cli.artifacts import read_artifact

    a = read_artifact(path)
    reps = [str(r) for r in a["representations"]]
    exps = a.meta.get("exponents", {})
    return reps, exps, [str(i) for i in a["ids"]], np.asarray(a["psnr"], np.float64), np.asarray(a["ssim"], np.float64)


def _fmt(t):
    return f"{t[0]:+.3f} [{t[1]:+.3f}, {t[2]:+.3f}]"


def report(paths, labels) -> str:
    lines = []
    runs = [load(p) for p in paths]
    reps = runs[0][0]
    lines.append("| representation | " + " | ".join(f"{lab} PSNR (dB) / SSIM" for lab in labels) + " |")
    lines.append("|---|" + "---|" * len(runs))
    for r in reps:
        cells = []
        for reps_i, _, _, ps, ss in runs:
            k = reps_i.index(r)
            cells.append(f"{ps[:, k].mean():.2f} / {ss[:, k].mean():.4f}")
        lines.append(f"| {r} | " + " | ".join(cells) + " |")
    lines.append("")
    for lab, (reps_i, exps, ids, ps, ss) in zip(labels, runs):
        multi = [r for r in reps_i if len(exps.get(r, [])) > 1]
        glob = [r for r in reps_i if len(exps.get(r, [])) == 1]
        if not multi or not glob:
            continue
        m = reps_i.index(multi[0])
        gi = [reps_i.index(g) for g in glob]
        best = gi[int(np.argmax(ps[:, gi].mean(0)))]
        lines.append(f"{lab} ({len(ids)} identities: {', '.join(ids)}); per-identity PSNR of {reps_i[m]}:")
        lines.append("")
        lines.append("| identity | " + " | ".join(reps_i[g] for g in gi) + f" | {reps_i[m]} |")
        lines.append("|---|" + "---:|" * (len(gi) + 1))
        for j, i in enumerate(ids):
            lines.append(f"| {i} | " + " | ".join(f"{ps[j, g]:.2f}" for g in gi) + f" | {ps[j, m]:.2f} |")
        lines.append("")
        lines.append(f"| {reps_i[m]} − … (dB, mean [95 % t-CI] over identities) | PSNR | SSIM ×1000 |")
        lines.append("|---|---:|---:|")
        for g in gi + [None]:
            gg = best if g is None else g
            name = f"best global ({reps_i[best]})" if g is None else reps_i[g]
            dp = t_interval(ps[:, m] - ps[:, gg])
            dsim = t_interval(1000 * (ss[:, m] - ss[:, gg]))
            lines.append(f"| {name} | {_fmt(dp)} | {_fmt(dsim)} |")
        lines.append("")
    margins = [_margin(r) for r in runs]
    if len(runs) == 2 and all(m is not None for m in margins) and runs[0][2] == runs[1][2]:
        d = margins[1][0] - margins[0][0]
        lines.append(f"Change of the 3-lobe margin over each run's best global exponent ({margins[0][1]} → "
                     f"{margins[1][1]}), {labels[1]} − {labels[0]}, paired by identity: PSNR {_fmt(t_interval(d))} dB.")
        lines.append("")
    return "\n".join(lines)


def _margin(run):
    """Per-identity PSNR of the multi-lobe representation minus that of the best (on the mean) single-exponent one."""
    reps_i, exps, _, ps, _ = run
    multi = [r for r in reps_i if len(exps.get(r, [])) > 1]
    gi = [reps_i.index(r) for r in reps_i if len(exps.get(r, [])) == 1]
    if not multi or not gi:
        return None
    best = gi[int(np.argmax(ps[:, gi].mean(0)))]
    return ps[:, reps_i.index(multi[0])] - ps[:, best], reps_i[best]


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("paths", nargs="+")
    ap.add_argument("--labels", default=None)
    a = ap.parse_args(argv)
    labels = a.labels.split(",") if a.labels else [f"run {k + 1}" for k in range(len(a.paths))]
    print(report(a.paths, labels))
    print("\n`" + " ".join(["python", "benchmarks/bench_skin_table1.py", *sys.argv[1:]]) + "`")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
