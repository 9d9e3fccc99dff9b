"""The parts of a face model the geometry fit needs, as plain arrays (numpy in, torch for the optimiser)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from reflectmm_cli.errors import ReflectmmError


@dataclass
class ShapeModel:
    """Linear shape + expression model: ``v = mean + Σ_k α_k S_k + Σ_k β_k E_k`` (model space, mm).

    Attributes:
        mean: (N, 3) mean shape.
        shape_basis: (Ks, N, 3); shape_sigma: (Ks,) prior standard deviation of each coefficient.
        exp_basis: (Ke, N, 3); exp_sigma: (Ke,).
        triangles: (T, 3) int vertex ids, counter-clockwise seen from outside.
        landmarks: (68,) vertex ids of the iBUG-68 landmarks.
        skin_mask: (N,) bool, vertices used by the photometric term (None → all).
        mean_tex: (N, 3) linear mean albedo, or None.
    """

    mean: np.ndarray
    shape_basis: np.ndarray
    shape_sigma: np.ndarray
    exp_basis: np.ndarray
    exp_sigma: np.ndarray
    triangles: np.ndarray
    landmarks: np.ndarray
    skin_mask: np.ndarray | None = None
    mean_tex: np.ndarray | None = None

    def __post_init__(self) -> None:
        self.mean = np.asarray(self.mean, dtype=np.float64)
        n = self.mean.shape[0]
        if self.mean.ndim != 2 or self.mean.shape[1] != 3:
            raise ReflectmmError(f"face model mean shape must be (N, 3), got {self.mean.shape}")
        self.shape_basis = np.asarray(self.shape_basis, dtype=np.float64).reshape(-1, n, 3)
        self.exp_basis = np.asarray(self.exp_basis, dtype=np.float64).reshape(-1, n, 3)
        self.shape_sigma = np.asarray(self.shape_sigma, dtype=np.float64).reshape(-1)
        self.exp_sigma = np.asarray(self.exp_sigma, dtype=np.float64).reshape(-1)
        if self.shape_sigma.shape[0] != self.shape_basis.shape[0]:
            raise ReflectmmError(f"face model: {self.shape_basis.shape[0]} shape bases but "
                                 f"{self.shape_sigma.shape[0]} sigmas")
        if self.exp_sigma.shape[0] != self.exp_basis.shape[0]:
            raise ReflectmmError(f"face model: {self.exp_basis.shape[0]} expression bases but "
                                 f"{self.exp_sigma.shape[0]} sigmas")
        self.triangles = np.asarray(self.triangles, dtype=np.int64)
        self.landmarks = np.asarray(self.landmarks, dtype=np.int64).reshape(-1)
        if self.landmarks.shape[0] != 68:
            raise ReflectmmError(f"face model has {self.landmarks.shape[0]} landmark indices, expected 68")
        if self.landmarks.min() < 0 or self.landmarks.max() >= n:
            raise ReflectmmError("face model landmark indices are out of range")
        if self.skin_mask is not None:
            self.skin_mask = np.asarray(self.skin_mask, dtype=bool).reshape(-1)
        if self.mean_tex is not None:
            self.mean_tex = np.asarray(self.mean_tex, dtype=np.float64).reshape(n, 3)

    @property
    def n_vertices(self) -> int:
        return self.mean.shape[0]

    @property
    def n_shape(self) -> int:
        return self.shape_basis.shape[0]

    @property
    def n_exp(self) -> int:
        return self.exp_basis.shape[0]

    @classmethod
    def from_face_model(cls, fm) -> "ShapeModel":
        """From a ``reflectmm_cli.geometry.FaceModel`` (or anything with the same attributes)."""
        skin = getattr(fm, "skin_mask", None)
        tex = getattr(fm, "mean_tex", None)
        return cls(mean=fm.mean_shape, shape_basis=fm.shape_basis, shape_sigma=fm.shape_sigma,
                   exp_basis=fm.exp_basis, exp_sigma=fm.exp_sigma, triangles=fm.triangles,
                   landmarks=fm.landmarks, skin_mask=skin, mean_tex=tex)

    def vertices(self, shape_coeffs=None, exp_coeffs=None) -> np.ndarray:
        """(N, 3) vertices for the given coefficients (zeros when None)."""
        v = self.mean.copy()
        if shape_coeffs is not None and self.n_shape:
            v += np.tensordot(np.asarray(shape_coeffs, dtype=np.float64), self.shape_basis, axes=1)
        if exp_coeffs is not None and self.n_exp:
            v += np.tensordot(np.asarray(exp_coeffs, dtype=np.float64), self.exp_basis, axes=1)
        return v

    def torch_parts(self, dtype: torch.dtype, device: str) -> "TorchShape":
        return TorchShape(self, dtype, device)


class TorchShape:
    """Torch views of a :class:`ShapeModel` for the optimiser (bases flattened to (K, 3N))."""

    def __init__(self, m: ShapeModel, dtype: torch.dtype, device: str):
        def tt(a):
            return torch.as_tensor(np.ascontiguousarray(a), dtype=dtype, device=device)

        n = m.n_vertices
        self.n = n
        self.mean = tt(m.mean.reshape(-1))
        # sigma-scaled bases: coefficients are optimised in units of their prior standard deviation.
        self.S = tt((m.shape_basis * m.shape_sigma[:, None, None]).reshape(m.n_shape, 3 * n))
        self.E = tt((m.exp_basis * m.exp_sigma[:, None, None]).reshape(m.n_exp, 3 * n))
        self.triangles = torch.as_tensor(m.triangles, dtype=torch.long, device=device)
        self.landmarks = torch.as_tensor(m.landmarks, dtype=torch.long, device=device)
        cols = (m.landmarks[:, None] * 3 + np.arange(3)[None]).reshape(-1)
        self.lm_mean = self.mean[torch.as_tensor(cols, device=device)]
        self.lm_S = self.S[:, cols]
        self.lm_E = self.E[:, cols]

    def vertices(self, zs: torch.Tensor, ze: torch.Tensor) -> torch.Tensor:
        v = self.mean
        if zs.numel():
            v = v + zs @ self.S
        if ze.numel():
            v = v + ze @ self.E[:ze.numel()]
        return v.reshape(self.n, 3)

    def subset(self, ids: np.ndarray) -> "TorchShape":
        """The model restricted to vertices ``ids`` (no triangles): ``subset(ids).vertices(zs, ze)`` equals
        ``vertices(zs, ze)[ids]`` at a fraction of the cost."""
        sub = object.__new__(TorchShape)
        cols = torch.as_tensor((np.asarray(ids)[:, None] * 3 + np.arange(3)[None]).reshape(-1),
                               device=self.mean.device)
        sub.n = len(ids)
        sub.mean, sub.S, sub.E = self.mean[cols], self.S[:, cols], self.E[:, cols]
        return sub

    def landmark_vertices(self, zs: torch.Tensor, ze: torch.Tensor) -> torch.Tensor:
        """(68, 3) landmark vertices only (cheap: the landmark-only stage never builds the full mesh)."""
        v = self.lm_mean
        if zs.numel():
            v = v + zs @ self.lm_S
        if ze.numel():
            v = v + ze @ self.lm_E[:ze.numel()]
        return v.reshape(-1, 3)
