"""Issue 13 defaults: captures keep the raised cameras of the raised flashes (geometry), unwrap-uv leaves them
out (the paper's 9 views for reflectance)."""

import os

from _capture_tree import make_tree
from reflectmm_cli.capture.layout import DEFAULT_VIEWS, default_views
from reflectmm_cli.observations.unwrap import reflectance_views


def test_default_views_add_the_raised_camera_of_a_used_raised_flash(tmp_path):
    make_tree(tmp_path / "mp", views=("13_0", "08_1"), flashes=("07", "14"), size=(16, 12))
    views, notes = default_views(tmp_path / "mp", "001", ("07", "14"))
    assert views == DEFAULT_VIEWS + ("08_1",) and notes == []
    views, _ = default_views(tmp_path / "mp", "001", ("07",))          # no raised flash: the paper's 9
    assert views == DEFAULT_VIEWS
    # flash 18 is used but 19_1 has no shots: left out, loudly
    views, notes = default_views(tmp_path / "mp", "001", ("14", "18"))
    assert views == DEFAULT_VIEWS + ("08_1",)
    assert len(notes) == 1 and "19_1" in notes[0] and "rig table" in notes[0]
    # 08_1 without its landmark file (no detector finds a face looking down): kept with a note, fit-geometry
    # places it by the rig and its images
    for p in (tmp_path / "mp").rglob("*_081_00_lm.pts"):
        os.remove(p)
    views, notes = default_views(tmp_path / "mp", "001", ("14",))
    assert views == DEFAULT_VIEWS + ("08_1",) and "no landmarks" in notes[0] and "places it by the rig" in notes[0]


def test_reflectance_views_leave_out_the_raised_cameras():
    cap = {"view_names": ["09_0", "05_1", "08_1", "19_1"]}
    assert reflectance_views(cap) == ["09_0", "05_1"]
    assert reflectance_views(cap, "all") == ["09_0", "05_1", "08_1", "19_1"]
    assert reflectance_views(cap, "05_1,08_1") == ["05_1", "08_1"]
    assert reflectance_views({"view_names": ["08_1"]}) == ["08_1"]  # nothing else to use


def test_reflectance_views_landmarked_keeps_the_views_landmarks_placed():
    import numpy as np
    import pytest

    from reflectmm_cli.errors import ReflectmmError

    cap = {"view_names": ["09_0", "05_1", "04_1", "08_1"]}
    geo = {"view_names": np.array(["05_1", "09_0", "08_1", "04_1"]),   # the geometry's own order
           "view_evidence": np.array(["landmarks+flash", "rig+flash", "landmarks", "landmarks"])}
    # the capture's order; 09_0 was registered by its flash (left out), 08_1 is raised (left out)
    assert reflectance_views(cap, "landmarked", geo) == ["05_1", "04_1"]
    with pytest.raises(ReflectmmError, match="needs the geometry"):
        reflectance_views(cap, "landmarked")
    none = {"view_names": geo["view_names"], "view_evidence": np.array(["rig", "rig+flash", "landmarks", "rig"])}
    with pytest.raises(ReflectmmError, match="no view left to unwrap"):
        reflectance_views(cap, "landmarked", none)
    with pytest.raises(ReflectmmError, match="view_evidence"):
        reflectance_views(cap, "landmarked", {"view_names": geo["view_names"]})
