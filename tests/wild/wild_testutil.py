"""Helpers shared by the tests of tests/wild."""
import numpy as np


def head_rotation(yaw_deg: float, pitch_deg: float = 0.0, roll_deg: float = 0.0) -> np.ndarray:
    """Model → OpenCV camera rotation of the Deep3DFaceRecon camera with the head turned (degrees), built with
    scipy (independently of reflectmm_cli.synth.wild.head_pose_rotation)."""
    from scipy.spatial.transform import Rotation

    Rh = Rotation.from_euler("yxz", [yaw_deg, pitch_deg, roll_deg], degrees=True).as_matrix()
    return np.diag([1.0, -1.0, -1.0]) @ Rh
