"""unwrap-uv --flashes and --views: which flash images and views enter the observations."""
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from _sphere_scene import make_scene
from reflectmm_cli.artifacts import read_artifact, write_artifact
from reflectmm_cli.errors import ReflectmmError
from reflectmm_cli.observations.unwrap import landmarked_flashes, reflectance_flashes


def _geometry():
    centers = np.array([[0.0, 0.0, 1300.0], [900.0, 0.0, 900.0], [-900.0, 0.0, 900.0]])
    return {"view_names": np.array(["05_1", "19_0", "08_0"]), "cam_centers": centers,
            "view_evidence": np.array(["landmarks+flash", "rig+flash", "landmarks"]),
            "flash_ids": np.array(["07", "10", "15", "04"]),
            "flash_pos": np.array([centers[0], centers[1], [0.0, 800.0, 900.0], centers[2] + [0.0, 0.0, 1e-3]]),
            "flash_from_view": np.array([True, True, False, True])}


def test_only_flashes_on_cameras_placed_by_landmarks():
    # 07 rides on 05_1 (landmarks): kept; 10 on 19_0 (placed by the rig and its flash images): left out;
    # 15 stands free: left out; 04 claims a view but sits 1 µm from 08_0's centre, so it is not carried: left out
    assert landmarked_flashes(_geometry()) == ["07"]
    g = _geometry()
    g["view_evidence"] = np.array(["landmarks", "landmarks", "landmarks"])
    g["flash_pos"][3] = g["cam_centers"][2]
    assert landmarked_flashes(g) == ["07", "10", "04"]


def test_selection_rules_and_refusals(tmp_path):
    cap = {"flash_ids": np.array(["04", "07", "10", "15"])}
    assert reflectance_flashes(cap, _geometry(), None) is None
    assert reflectance_flashes(cap, _geometry(), "all") is None
    assert reflectance_flashes(cap, _geometry(), "landmarked") == ["07"]
    assert reflectance_flashes(cap, _geometry(), "10,07") == ["10", "07"]
    g = _geometry()
    g["view_evidence"] = np.array(["rig", "rig", "rig"])
    with pytest.raises(ReflectmmError, match="no flash left"):
        reflectance_flashes(cap, g, "landmarked", tmp_path / "g.npz")
    del g["view_evidence"]
    with pytest.raises(ReflectmmError, match="view_evidence.*rerun fit-geometry"):
        reflectance_flashes(cap, g, "landmarked", tmp_path / "g.npz")


def _unwrap(cli, tmp_path, scene, name, *extra):
    ws = tmp_path / "ws"
    out = tmp_path / f"{name}.npz"
    res = cli("unwrap-uv", "--id", "001", "--uv-size", 48, "--face-model", scene["face_model_path"],
              "--workspace", ws, "-o", out, *extra)
    return res, out


def test_unwrap_with_a_flash_subset_equals_the_full_unwrap_restricted(tmp_path, cli):
    scene = make_scene(tmp_path / "mp", tmp_path / "ws")
    res = cli("preprocess-multipie", "--root", tmp_path / "mp", "--id", "001", "--views", ",".join(scene["views"]),
              "--flashes", ",".join(scene["flashes"]), "--workspace", tmp_path / "ws")
    assert res.exit_code == 0, res.stderr
    res, full = _unwrap(cli, tmp_path, scene, "full")
    assert res.exit_code == 0, res.stderr
    # the scene's flash 07 sits on camera 05_1, flash 14 stands free; 05_1 placed by landmarks, 14_0 by the rig
    geo = dict(scene["geometry"])
    geo["view_evidence"] = np.array(["landmarks", "rig"])
    geo["flash_from_view"] = np.array([True, False])
    write_artifact(scene["geometry_path"], "geometry", geo)
    res, sub = _unwrap(cli, tmp_path, scene, "sub", "--flashes", "landmarked")
    assert res.exit_code == 0, res.stderr
    assert "leaving out flash(es) 14" in res.stderr
    a, b = read_artifact(full, "uv-observations"), read_artifact(sub, "uv-observations")
    assert b["flash_ids"].tolist() == ["07"] and b["pair_flash"].tolist() == [0, 0]
    keep = a["pair_flash"] == 0                                     # flash 07 is index 0 of the full unwrap
    for k in ("radiance", "observed", "saturated"):
        np.testing.assert_array_equal(b[k], a[k][keep])
    np.testing.assert_array_equal(b["lit"], a["lit"][:1])
    np.testing.assert_array_equal(b["obs_count"], b["observed"].sum(0))
    assert b.meta["params"]["flashes"] == ["landmarked"]
    assert "flashes" not in a.meta["params"]                          # not recorded unless given
    res, bad = _unwrap(cli, tmp_path, scene, "bad", "--flashes", "09")
    assert res.exit_code != 0 and "flash(es) 09 are not in the capture" in res.stderr and not bad.exists()


def _registered_geometry():
    """Five views: two placed by landmarks, three without; every view carries one flash."""
    centers = np.array([[0.0, 0.0, 1300.0], [300.0, 0.0, 1250.0], [900.0, 0.0, 900.0], [-900.0, 0.0, 900.0],
                        [0.0, 500.0, 1200.0]])
    return {"view_names": np.array(["05_1", "14_0", "19_0", "08_0", "19_1"]), "cam_centers": centers,
            "view_evidence": np.array(["landmarks+flash", "landmarks+flash", "rig+flash", "rig+flash", "rig"]),
            "center_sigma_mm": np.array([np.nan, np.nan, 6.0, 6.0, 5.2]),
            "flash_residual": np.array([0.004, 0.006, 0.012, 0.012, 0.001]),
            "flash_ids": np.array(["07", "08", "10", "04", "18"]), "flash_pos": centers.copy(),
            "flash_from_view": np.ones(5, bool)}


def test_trusted_flashes_keep_registered_cameras_that_check_out():
    from reflectmm_cli.observations.unwrap import trusted_flashes

    g = _registered_geometry()
    # the landmarked median residual is 0.005: 0.012 is 2.4x, within 3x; 19_1 was placed by the rig alone
    assert trusted_flashes(g) == ["07", "08", "10", "04"]
    assert trusted_flashes(g, max_residual_ratio=2.0) == ["07", "08"]
    g["center_sigma_mm"][2] = 12.0                                   # 19_0's centre is loose: its flash goes
    assert trusted_flashes(g) == ["07", "08", "04"]
    assert trusted_flashes(g, max_center_sigma_mm=15.0) == ["07", "08", "10", "04"]
    g["center_sigma_mm"][3] = np.inf                                 # no curvature at all: never trusted
    assert trusted_flashes(g, max_center_sigma_mm=1e9) == ["07", "08", "10"]
    g["flash_residual"][2] = np.nan
    assert trusted_flashes(g, max_center_sigma_mm=1e9) == ["07", "08"]
    # no landmarked view with a finite residual to compare with: only the landmarked flashes stay
    g = _registered_geometry()
    g["flash_residual"][:2] = np.nan
    assert trusted_flashes(g) == ["07", "08"]
    # a free-standing flash is never trusted, whatever its nearest camera
    g = _registered_geometry()
    g["flash_from_view"][2] = False
    assert trusted_flashes(g) == ["07", "08", "04"]


def test_trusted_selection_through_reflectance_flashes(tmp_path, capfd):
    cap = {"flash_ids": np.array(["04", "07", "08", "10", "18"])}
    g = _registered_geometry()
    assert reflectance_flashes(cap, g, "trusted") == ["04", "07", "08", "10"]
    assert "leaving out flash(es) 18" in capfd.readouterr().err
    assert reflectance_flashes(cap, g, "trusted", max_residual_ratio=2.0) == ["07", "08"]
    g["view_evidence"] = np.array(["rig+flash"] * 4 + ["rig"])
    with pytest.raises(ReflectmmError, match="no flash left.*registered well"):
        reflectance_flashes(cap, g, "trusted", tmp_path / "g.npz")
    g = _registered_geometry()
    del g["center_sigma_mm"]
    with pytest.raises(ReflectmmError, match="center_sigma_mm.*rerun fit-geometry"):
        reflectance_flashes(cap, g, "trusted", tmp_path / "g.npz")


@pytest.mark.parametrize("flag,value", [("--trust-center-sigma", "0"), ("--trust-residual-ratio", "-1")])
def test_trust_bounds_out_of_range_are_refused(cli, tmp_path, flag, value):
    res = cli("unwrap-uv", "--id", "001", "--flashes", "trusted", flag, value, "--workspace", tmp_path / "ws")
    assert res.exit_code != 0 and flag in res.stderr
    assert not (tmp_path / "ws" / "unwrap-uv").exists()


def test_trusted_views_follow_the_same_rule_and_leave_out_raised_cameras(tmp_path):
    from reflectmm_cli.observations.unwrap import reflectance_views, trusted_views

    g = _registered_geometry()
    assert trusted_views(g) == ["05_1", "14_0", "19_0", "08_0"]        # 19_1: the rig alone
    g["center_sigma_mm"][2] = 12.0
    assert trusted_views(g) == ["05_1", "14_0", "08_0"]
    cap = {"view_names": np.array(["08_0", "05_1", "19_0", "14_0", "19_1"])}
    assert reflectance_views(cap, "trusted", g) == ["08_0", "05_1", "14_0"]        # the capture's order
    assert reflectance_views(cap, "trusted", g, max_center_sigma_mm=15.0) == ["08_0", "05_1", "19_0", "14_0"]
    g["view_evidence"][4] = "rig+flash"                                    # 19_1 registered and checking out,
    g["center_sigma_mm"][4] = 5.0                                          # but raised: still left out
    assert "19_1" in trusted_views(g) and "19_1" not in reflectance_views(cap, "trusted", g)
    g["view_evidence"][:] = "rig"
    with pytest.raises(ReflectmmError, match="no view left to unwrap"):
        reflectance_views(cap, "trusted", g, tmp_path / "g.npz")
    with pytest.raises(ReflectmmError, match="needs the geometry"):
        reflectance_views(cap, "trusted")


_finite_or_not = st.one_of(st.floats(0.0, 50.0), st.just(float("nan")), st.just(float("inf")))


@settings(max_examples=60, deadline=None)
@given(evidence=st.lists(st.sampled_from(["landmarks", "landmarks+flash", "rig", "rig+flash", "rig+flash+room"]),
                         min_size=5, max_size=5),
       sigma=st.lists(_finite_or_not, min_size=5, max_size=5),
       resid=st.lists(_finite_or_not, min_size=5, max_size=5),
       bounds=st.tuples(st.floats(0.1, 30.0), st.floats(0.1, 10.0), st.floats(1.0, 3.0)))
def test_trusted_contains_landmarked_and_grows_with_the_bounds(evidence, sigma, resid, bounds):
    from reflectmm_cli.observations.unwrap import landmarked_flashes, trusted_flashes, trusted_views

    g = _registered_geometry()
    g["view_evidence"] = np.array(evidence)
    g["center_sigma_mm"], g["flash_residual"] = np.array(sigma), np.array(resid)
    s, r, grow = bounds
    views, flashes = trusted_views(g, s, r), trusted_flashes(g, s, r)
    names = [str(v) for v in g["view_names"]]
    assert set(landmarked_flashes(g)) <= set(flashes)
    assert {n for n, e in zip(names, evidence) if e.startswith("landmarks")} <= set(views)
    assert set(views) <= set(trusted_views(g, s * grow, r * grow))            # wider bounds never drop a view
    for v in set(views) - {n for n, e in zip(names, evidence) if e.startswith("landmarks")}:
        i = names.index(v)                                                   # each added view checks out
        assert evidence[i] != "rig" and np.isfinite(sigma[i]) and sigma[i] <= s and np.isfinite(resid[i])


def test_views_and_flashes_that_only_the_rig_placed_are_named(capfd):
    # evidence exactly "rig": no landmarks and no image registration that held.  Only those are named, among the
    # views and flashes that the unwrap takes; a registered camera ("rig+flash") and a landmarked one are not.
    from reflectmm_cli.observations.unwrap import rig_placed, warn_rig_placed

    g = _registered_geometry()  # 19_1 (flash 18) only the rig placed
    all_views = ["05_1", "14_0", "19_0", "08_0", "19_1"]
    assert rig_placed(g, all_views, ["07", "08", "10", "04", "18"]) == (["19_1"], ["18"])
    assert rig_placed(g, all_views, None) == (["19_1"], ["18"])  # None: every flash, as reflectance_flashes says
    assert rig_placed(g, all_views[:4], ["07", "18"]) == ([], ["18"])  # its flash lights the others
    assert rig_placed(g, all_views[:4], ["07", "08"]) == ([], [])
    g["view_evidence"][2] = "rig"  # 19_0's registration did not hold
    assert rig_placed(g, all_views, ["10"]) == (["19_0", "19_1"], ["10"])
    warn_rig_placed(g, all_views, ["07", "10"], "001")
    err = capfd.readouterr().err
    assert len(err.strip().splitlines()) == 1 and "view(s) 19_0, 19_1" in err and "flash(es) 10" in err
    assert "--views trusted --flashes trusted" in err
    warn_rig_placed(g, ["05_1", "14_0"], ["07"], "001")
    assert capfd.readouterr().err == ""
    del g["view_evidence"]  # a geometry written before fit-geometry recorded the evidence: nothing to say
    assert rig_placed(g, all_views, ["10"]) == ([], [])
