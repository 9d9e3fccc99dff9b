import numpy as np
import pytest


def head_rotation(yaw_deg: float, pitch_deg: float = 0.0, roll_deg: float = 0.0) -> np.ndarray:
    """Model → OpenCV camera rotation of the Deep3DFaceRecon camera with the head turned (degrees)."""
    from scipy.spatial.transform import Rotation

    Rh = Rotation.from_euler("yxz", [yaw_deg, pitch_deg, roll_deg], degrees=True).as_matrix()
    return np.diag([1.0, -1.0, -1.0]) @ Rh


@pytest.fixture(scope="session")
def small_face():
    from reflectmm_cli.geometry import procedural_face_model

    return procedural_face_model(grid=(61, 51), n_shape=6, n_exp=4, seed=2)
