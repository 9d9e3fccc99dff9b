"""Smooth functions on a triangle mesh: the cotangent Laplacian, its lumped mass matrix and the manifold harmonics
(the Laplacian's lowest eigenfunctions), used to restrict a per-vertex change to smooth ones (finetune/model_solve.py).

Shapes: V vertices, F triangles, Q harmonics.

With the cotangent stiffness matrix ``L`` (symmetric, positive semidefinite, rows summing to 0;
``L_ij = −(cot α_ij + cot β_ij)/2`` for an edge ij with opposite angles α, β) and the lumped mass ``M`` (a third of
the area of the triangles around each vertex), the harmonics solve the generalised eigenproblem

    L φ_q = λ_q M φ_q,        Φᵀ M Φ = I,        0 ≤ λ_1 ≤ … ≤ λ_Q

so that ``Φ c`` is the smoothest function of Q degrees of freedom: ``(Φc)ᵀ L (Φc) = Σ λ_q c_q²``. Vertices that no
triangle uses get a unit mass and no stiffness (they are their own component and stay out of the lowest harmonics
unless Q exceeds the number of components).
"""
from __future__ import annotations

import numpy as np

from reflectmm_cli.errors import ReflectmmError

__all__ = ["cotangent_laplacian", "max_mesh_harmonics", "mesh_harmonics"]


def cotangent_laplacian(vertices, triangles):
    """``(L, M)`` scipy sparse CSR (V, V): the cotangent stiffness matrix and the lumped (diagonal) mass matrix of a
    mesh with vertices (V, 3) and triangles (F, 3) int (module docstring)."""
    import scipy.sparse as sp

    X = np.asarray(vertices, np.float64)
    T = np.asarray(triangles, np.int64)
    if X.ndim != 2 or X.shape[1] != 3 or T.ndim != 2 or T.shape[1] != 3:
        raise ReflectmmError(f"mesh harmonics: vertices (V,3) and triangles (F,3) expected, got {X.shape} and "
                             f"{T.shape}")
    V = X.shape[0]
    if T.size and (T.min() < 0 or T.max() >= V):
        raise ReflectmmError(f"mesh harmonics: a triangle index is outside 0..{V - 1}")
    if not np.isfinite(X).all():
        raise ReflectmmError("mesh harmonics: NaN or inf in the vertices")
    rows, cols, vals = [], [], []
    area = 0.5 * np.linalg.norm(np.cross(X[T[:, 1]] - X[T[:, 0]], X[T[:, 2]] - X[T[:, 0]]), axis=1)
    for k in range(3):  # the angle at corner k is opposite the edge (i, j)
        i, j, o = T[:, (k + 1) % 3], T[:, (k + 2) % 3], T[:, k]
        u, v = X[i] - X[o], X[j] - X[o]
        cross = np.linalg.norm(np.cross(u, v), axis=1)
        cot = (u * v).sum(1) / np.maximum(cross, 1e-300)
        w = np.where(cross > 0, 0.5 * cot, 0.0)
        rows += [i, j, i, j]
        cols += [j, i, i, j]
        vals += [-w, -w, w, w]
    L = sp.coo_matrix((np.concatenate(vals), (np.concatenate(rows), np.concatenate(cols))), shape=(V, V)).tocsr()
    mass = np.zeros(V)
    np.add.at(mass, T.reshape(-1), np.repeat(area / 3.0, 3))
    mass[mass <= 0] = 1.0
    return L, sp.diags(mass).tocsr()


def max_mesh_harmonics(n_vertices: int) -> int:
    """The most manifold harmonics :func:`mesh_harmonics` computes for a mesh of ``n_vertices`` vertices (V − 2: the
    shift-invert eigensolver needs k < V − 1)."""
    return max(int(n_vertices) - 2, 0)


def mesh_harmonics(vertices, triangles, count: int) -> tuple[np.ndarray, np.ndarray]:
    """The ``count`` lowest manifold harmonics of a mesh.

    Args:
        vertices: (V, 3); triangles: (F, 3) int; count: Q, 1 ≤ Q < V.
    Returns:
        ``(Φ (V, Q), λ (Q,))`` float64, eigenvalues ascending, ``Φᵀ M Φ = I`` (M the lumped mass).
    """
    import scipy.sparse.linalg as sla

    L, M = cotangent_laplacian(vertices, triangles)
    V = L.shape[0]
    Q = int(count)
    if not 1 <= Q <= max_mesh_harmonics(V):
        raise ReflectmmError(f"mesh harmonics: count must be in 1..{max_mesh_harmonics(V)}, got {Q}")
    # shift-invert just below 0 (L is only semidefinite), in units of the mesh's typical eigenvalue
    scale = float(L.diagonal().mean() / M.diagonal().mean())
    lam, phi = sla.eigsh(L, k=Q, M=M, sigma=-1e-6 * scale, which="LM", v0=np.ones(V))
    order = np.argsort(lam)
    lam, phi = lam[order], phi[:, order]
    # re-orthonormalise in the M inner product (eigsh's vectors are, up to round-off and degenerate eigenvalues)
    G = phi.T @ (M @ phi)
    R = np.linalg.cholesky(G)
    phi = np.linalg.solve(R, phi.T).T
    phi *= np.where(phi[np.argmax(np.abs(phi), 0), np.arange(Q)] < 0, -1.0, 1.0)  # a fixed sign per harmonic
    return phi, np.maximum(lam, 0.0)
