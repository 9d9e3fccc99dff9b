"""Landmark files: formats, counts, lookup by view, weights."""

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from reflectmm_cli.errors import ReflectmmError
from reflectmm_cli.geometry_fit.landmarks import (
    DEFAULT_GROUP_WEIGHTS,
    GROUPS,
    find_landmark_file,
    landmark_weights,
    write_pts,
)
from reflectmm_cli.landmarks import read_landmarks


def _pts(n=68, seed=0):
    return np.random.default_rng(seed).uniform(0, 640, size=(n, 2)).round(4)


def test_formats_round_trip(tmp_path):
    lm = _pts()
    write_pts(tmp_path / "a.pts", lm)
    np.savetxt(tmp_path / "b.txt", lm)
    (tmp_path / "c.txt").write_text("\n".join(f"{x},{y}" for x, y in lm))
    np.save(tmp_path / "d.npy", lm)
    for name in ("a.pts", "b.txt", "c.txt", "d.npy"):
        assert np.allclose(read_landmarks(tmp_path / name), lm, atol=1e-4), name


def test_wrong_count_names_file(tmp_path):
    write_pts(tmp_path / "short.pts", _pts(60))
    with pytest.raises(ReflectmmError, match=r"short\.pts.*expected 68 landmarks, found 60"):
        read_landmarks(tmp_path / "short.pts")
    np.save(tmp_path / "bad.npy", np.zeros((68, 3)))
    with pytest.raises(ReflectmmError, match=r"bad\.npy.*68×2"):
        read_landmarks(tmp_path / "bad.npy")
    (tmp_path / "hdr.pts").write_text("version: 1\nn_points: 68\n{\n1 2\n}\n")
    with pytest.raises(ReflectmmError, match="n_points: 68 but 1"):
        read_landmarks(tmp_path / "hdr.pts")
    with pytest.raises(ReflectmmError, match="not found"):
        read_landmarks(tmp_path / "missing.pts")


def test_find_by_view_name_and_multipie_name(tmp_path):
    write_pts(tmp_path / "05_1.pts", _pts())
    sub = tmp_path / "001" / "01" / "08_0"
    sub.mkdir(parents=True)
    write_pts(sub / "001_01_01_080_00_lm.pts", _pts(seed=2))
    assert find_landmark_file(tmp_path, "05_1") == tmp_path / "05_1.pts"
    assert find_landmark_file(tmp_path, "08_0") == sub / "001_01_01_080_00_lm.pts"
    assert find_landmark_file(tmp_path, "19_0") is None


def test_weights_by_group():
    w = landmark_weights()
    assert w.shape == (68,)
    assert w[0] == DEFAULT_GROUP_WEIGHTS["jaw"] and w[16] == DEFAULT_GROUP_WEIGHTS["jaw"]
    assert w[30] == DEFAULT_GROUP_WEIGHTS["nose_bridge"] and w[67] == DEFAULT_GROUP_WEIGHTS["mouth_inner"]
    assert w[:17].max() < w[27:].min()  # jaw line lower than inner face
    assert landmark_weights({"jaw": 0.0})[:17].sum() == 0.0
    with pytest.raises(ReflectmmError, match="unknown landmark group"):
        landmark_weights({"ears": 1.0})


def test_landmark_weights_reach_both_stages_configs():
    """fit-geometry and calibrate-rig take --landmark-weights (CLI or recipe) into their configs' group weights;
    a bad group is refused the same way in both."""
    from reflectmm_cli.params import resolve_params
    from reflectmm_cli.stages import calibrate_rig, fit_geometry

    for stage in (fit_geometry, calibrate_rig):
        p = resolve_params(stage.PARAMS, {"landmark_weights": ["jaw=0", "eyes=3"]})
        assert stage.config_from_params(p).group_weights == {"jaw": 0.0, "eyes": 3.0}
        p = resolve_params(stage.PARAMS, {"landmark_weights": {"jaw": 0}})  # a recipe's inline table
        assert stage.config_from_params(p).group_weights == {"jaw": 0.0}
        assert not stage.config_from_params(resolve_params(stage.PARAMS, {})).group_weights
        with pytest.raises(Exception, match="unknown group 'chin'"):
            resolve_params(stage.PARAMS, {"landmark_weights": ["chin=1"]})
        with pytest.raises(Exception,
                           match="landmark_weights: the weight must be a finite number ≥ 0; group jaw has -1"):
            resolve_params(stage.PARAMS, {"landmark_weights": {"jaw": -1}})  # the group is named, as on the CLI


def test_a_bad_landmark_weight_in_a_recipe_names_the_file_and_stage(recipe_error):
    line = recipe_error("fit-geometry", 'foreach = ["001"]\ninputs = { capture = "c.npz", face_model = "f.npz" }\n'
                                        'params = { landmark_weights = { chin = 0 } }\n')
    assert "landmark_weights: unknown group 'chin'" in line


@given(st.dictionaries(st.sampled_from(sorted(GROUPS)), st.sampled_from([0.0, 0.5, 1.0, 2.0, 3.0, 0.25])))
def test_format_group_weights_is_read_back_to_the_same_weights(gw):
    # what format_group_weights writes, --landmark-weights reads back to the same per-landmark weights; the groups
    # at their default weight are left out, so the defaults are ""
    from reflectmm_cli.geometry_fit.landmarks import format_group_weights, parse_group_weights

    text = format_group_weights(gw)
    back = parse_group_weights([text]) if text else {}
    assert np.array_equal(landmark_weights(back), landmark_weights(gw))
    assert all(DEFAULT_GROUP_WEIGHTS[k] != v for k, v in back.items())
    assert format_group_weights(dict(DEFAULT_GROUP_WEIGHTS)) == ""
