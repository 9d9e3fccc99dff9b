import pytest


@pytest.fixture(scope="session")
def small_face():
    from reflectmm_cli.geometry import procedural_face_model

    return procedural_face_model(grid=(61, 51), n_shape=6, n_exp=4, seed=2)
