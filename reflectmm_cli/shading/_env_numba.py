"""Compiled kernel of ``shade_env``'s blocked path (numba): the same basis and coefficient rows as the numpy
kernel, but the basis is consumed as it is made.

The numpy kernel writes the Chebyshev basis Φ of a block (``_cheb_basis_into``: up to 81 rows × 16 384 texels,
3–5 MB) and then multiplies the coefficient rows with it; both products read the basis back from L3. Here every
sub-block of :data:`SUB` texels evaluates Φ into an L2-resident (rows, SUB) buffer and at once multiplies it
with the coefficient rows, three output rows (one colour triple) and four basis rows per pass, into 3 (diffuse)
or 3·J (lobes) L1-resident accumulator rows; nothing of size N other than the inputs and outputs is written,
and the inner loops run along the texels, where they vectorise. Per texel it does the numpy kernel's operations in the same order
(normalising, reflecting, T_j, (x + iy)^m, view albedo, lobe weights); only the sums over the basis rows run in
another order than BLAS's, so the two kernels agree to rounding (docs/shading.md).

Inputs (all of one float dtype, C-contiguous): ``c``, ``n``, ``v`` (N, 3), ``w`` (N, K); ``idx`` (N_tex,) int64
texels to shade (``use_idx``), else texels 0..N−1; ``rows_d`` (3, n_d) and ``rows_s`` (3·J, n_s) the coefficient
rows on the Chebyshev basis (``terms @ plan.M``); a plan as :func:`plan_arrays`; ``active`` (J,) int64 lobes;
``view_tab`` (J, 65) the view albedo table per active lobe (``use_vc``); ``consts`` (1e-30, 1, 64) and ``grid``
(0, 1, …, 64) in the dtype. Outputs ``diffuse``, ``specular`` (N, 3), zero where nothing is shaded.
"""
from __future__ import annotations

import numpy as np
from numba import njit

__all__ = ["SUB", "plan_arrays", "shade_range"]

#: texels per sub-block: the accumulators (3 or 3·J rows) stay in L1, the basis (≤ 81 rows, 83 KB in float32) in L2;
#: below ~128 the per-row loop overhead dominates (measured)
SUB = 256


def plan_arrays(plan):
    """A ``_ChebPlan`` as arrays for the kernel: ``(jmax, mtab, jtab)``, ``mtab`` (n_m, 4) = (m, number of j, first
    cosine row, first sine row), ``jtab`` (n_m, max number of j) the j of each (−1 padded)."""
    nm = len(plan.m_rows)
    width = max([len(js) for _, js, _, _ in plan.m_rows], default=1)
    mtab = np.zeros((nm, 4), np.int64)
    jtab = np.full((nm, width), -1, np.int64)
    for k, (m, js, rc, rs) in enumerate(plan.m_rows):
        mtab[k] = (m, len(js), rc, rs)
        jtab[k, :len(js)] = js
    return plan.jmax, mtab, jtab


@njit(cache=True, fastmath=False, nogil=True)
def _rows_product(R, Phi, acc, cnt):
    """``acc[:, :cnt] = R @ Phi[:, :cnt]`` for R (3·k, rows): three output rows (one colour triple) and four basis
    rows per pass along the texels, so each pass loads every accumulator and basis value once for 12 products."""
    nr = R.shape[1]
    for q in range(0, R.shape[0], 3):
        A0, A1, A2 = acc[q], acc[q + 1], acc[q + 2]
        A0[:cnt] = 0
        A1[:cnt] = 0
        A2[:cnt] = 0
        for k in range(0, nr - 3, 4):
            a0, a1, a2, a3 = R[q, k], R[q, k + 1], R[q, k + 2], R[q, k + 3]
            b0, b1, b2, b3 = R[q + 1, k], R[q + 1, k + 1], R[q + 1, k + 2], R[q + 1, k + 3]
            c0, c1, c2, c3 = R[q + 2, k], R[q + 2, k + 1], R[q + 2, k + 2], R[q + 2, k + 3]
            P0, P1, P2, P3 = Phi[k], Phi[k + 1], Phi[k + 2], Phi[k + 3]
            for t in range(cnt):
                p0, p1, p2, p3 = P0[t], P1[t], P2[t], P3[t]
                A0[t] += (a0 * p0 + a1 * p1) + (a2 * p2 + a3 * p3)
                A1[t] += (b0 * p0 + b1 * p1) + (b2 * p2 + b3 * p3)
                A2[t] += (c0 * p0 + c1 * p1) + (c2 * p2 + c3 * p3)
        for k in range(nr - nr % 4, nr):
            a0, b0, c0 = R[q, k], R[q + 1, k], R[q + 2, k]
            P0 = Phi[k]
            for t in range(cnt):
                A0[t] += a0 * P0[t]
                A1[t] += b0 * P0[t]
                A2[t] += c0 * P0[t]


@njit(cache=True, fastmath=False, nogil=True)
def _basis_product(x, y, z, cnt, jmax, mtab, jtab, R, acc, Phi, cm, sm):
    """``acc[:, :cnt] = R Φ`` for the Chebyshev basis Φ (plan ``jmax, mtab, jtab``) of the unit vectors (x, y, z):
    Φ of the sub-block into ``Phi`` (≥ rows, SUB; L1-resident), then :func:`_rows_product`; ``cm``, ``sm`` (SUB)
    are scratch. The same operations per value as ``env._cheb_basis_into``."""
    for t in range(cnt):
        Phi[0, t] = 1
    if jmax >= 1:
        for t in range(cnt):
            Phi[1, t] = z[t]
    for j in range(2, jmax + 1):  # T_j = 2z T_(j−1) − T_(j−2)
        for t in range(cnt):
            Phi[j, t] = (z[t] + z[t]) * Phi[j - 1, t] - Phi[j - 2, t]
    for t in range(cnt):
        cm[t] = x[t]
        sm[t] = y[t]
    m_cur = 1
    for k in range(mtab.shape[0]):
        m, nj, rc, rs = mtab[k, 0], mtab[k, 1], mtab[k, 2], mtab[k, 3]
        while m_cur < m:  # Re/Im (x + iy)^(m+1) from those of (x + iy)^m
            for t in range(cnt):
                c_new = x[t] * cm[t] - y[t] * sm[t]
                sm[t] = x[t] * sm[t] + y[t] * cm[t]
                cm[t] = c_new
            m_cur += 1
        for i in range(nj):
            j = jtab[k, i]
            if j == 0:
                for t in range(cnt):
                    Phi[rc + i, t] = cm[t]
                    Phi[rs + i, t] = sm[t]
            else:
                for t in range(cnt):
                    Phi[rc + i, t] = Phi[j, t] * cm[t]
                    Phi[rs + i, t] = Phi[j, t] * sm[t]
    _rows_product(R, Phi, acc, cnt)


@njit(cache=True, fastmath=False, nogil=True)
def shade_range(s0, s1, c, w, n, v, idx, use_idx, rows_d, plan_d, rows_s, plan_s, active, view_tab, use_vc,
                 consts, grid, diffuse, specular):
    """Shade texels s0..s1 of the list (``idx[s0:s1]``, or s0..s1−1) into ``diffuse``/``specular``, in sub-blocks
    of :data:`SUB`; the scratch is allocated once per call. Releases the GIL: callers run ranges in threads."""
    dt = c.dtype
    tiny, one, nodes = consts[0], consts[1], consts[2]
    J = active.shape[0]
    jd, md, jtd = plan_d
    js_, ms, jts = plan_s
    x, y, z = np.empty(SUB, dt), np.empty(SUB, dt), np.empty(SUB, dt)
    xr, yr, zr, ndv_f = np.empty(SUB, dt), np.empty(SUB, dt), np.empty(SUB, dt), np.empty(SUB, dt)
    tex, tex_f = np.empty(SUB, np.int64), np.empty(SUB, np.int64)
    vx, vy, vz = np.empty(SUB, dt), np.empty(SUB, dt), np.empty(SUB, dt)
    Phi = np.empty((max(rows_d.shape[1], rows_s.shape[1]), SUB), dt)
    cm, sm = np.empty(SUB, dt), np.empty(SUB, dt)
    acc_d = np.empty((3, SUB), dt)
    acc_s = np.empty((max(1, rows_s.shape[0]), SUB), dt)
    for b0 in range(s0, s1, SUB):
        cnt = min(SUB, s1 - b0)
        for t in range(cnt):
            i = idx[b0 + t] if use_idx else b0 + t
            tex[t] = i
            s = n[i, 0] * n[i, 0] + n[i, 1] * n[i, 1] + n[i, 2] * n[i, 2]
            s = np.sqrt(max(s, tiny))
            x[t], y[t], z[t] = n[i, 0] / s, n[i, 1] / s, n[i, 2] / s
        _basis_product(x, y, z, cnt, jd, md, jtd, rows_d, acc_d, Phi, cm, sm)
        for t in range(cnt):
            i = tex[t]
            for ch in range(3):
                diffuse[i, ch] = acc_d[ch, t] * c[i, ch]
        if J == 0:
            continue
        # the specular part of the front-facing texels (n·v > 0) only; it is 0 elsewhere
        nf = 0
        for t in range(cnt):
            i = tex[t]
            s = v[i, 0] * v[i, 0] + v[i, 1] * v[i, 1] + v[i, 2] * v[i, 2]
            s = np.sqrt(max(s, tiny))
            vx[t], vy[t], vz[t] = v[i, 0] / s, v[i, 1] / s, v[i, 2] / s
            ndv = x[t] * vx[t] + y[t] * vy[t] + z[t] * vz[t]
            if ndv > 0:
                e = ndv + ndv
                xr[nf], yr[nf], zr[nf] = e * x[t] - vx[t], e * y[t] - vy[t], e * z[t] - vz[t]
                ndv_f[nf] = ndv
                tex_f[nf] = i
                nf += 1
        if nf == 0:
            continue
        _basis_product(xr, yr, zr, nf, js_, ms, jts, rows_s, acc_s, Phi, cm, sm)
        for t in range(nf):
            i = tex_f[t]
            if use_vc:  # ρ_p(n·v), linear on the uniform nodes as specular_view_albedo
                xv = min(ndv_f[t], one) * nodes
                i0 = min(int(xv), view_tab.shape[1] - 2)
                fr = xv - grid[i0]
            for ch in range(3):
                tot = acc_s[ch, t] * 0
                for jj in range(J):
                    wj = w[i, active[jj]]
                    if use_vc:
                        wj = wj * (view_tab[jj, i0] * (one - fr) + view_tab[jj, i0 + 1] * fr)
                    tot = tot + acc_s[3 * jj + ch, t] * wj
                specular[i, ch] = tot
