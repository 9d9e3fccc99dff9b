import math

import numpy as np
import pytest


def template_landmark_uv() -> np.ndarray:
    """A parametric iBUG-68 layout in UV space (u right, v down), independent of any face model."""
    p = np.zeros((68, 2))
    t = np.linspace(math.pi, 0, 17)
    p[0:17] = np.stack([0.5 + 0.38 * np.cos(t), 0.42 + 0.5 * np.sin(t)], 1)
    p[17:22] = np.stack([np.linspace(0.2, 0.45, 5), 0.33 - 0.03 * np.sin(np.linspace(0, math.pi, 5))], 1)
    p[22:27] = np.stack([1 - p[17:22, 0][::-1], p[17:22, 1][::-1]], 1)
    p[27:31] = np.stack([np.full(4, 0.5), np.linspace(0.38, 0.56, 4)], 1)
    p[31:36] = np.stack([[0.43, 0.46, 0.5, 0.54, 0.57], [0.60, 0.61, 0.62, 0.61, 0.60]], 1)
    for start, cx in ((36, 0.33), (42, 0.67)):
        a = np.linspace(math.pi, -math.pi, 7)[:6]
        p[start:start + 6] = np.stack([cx + 0.06 * np.cos(a), 0.42 - 0.02 * np.sin(a)], 1)
    a = np.linspace(math.pi, -math.pi, 13)[:12]
    p[48:60] = np.stack([0.5 + 0.11 * np.cos(a), 0.75 - 0.045 * np.sin(a)], 1)
    a = np.linspace(math.pi, -math.pi, 9)[:8]
    p[60:68] = np.stack([0.5 + 0.07 * np.cos(a), 0.75 - 0.015 * np.sin(a)], 1)
    return p


@pytest.fixture
def landmark_uv():
    return template_landmark_uv()
