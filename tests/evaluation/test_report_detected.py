"""The report's "Landmarks from a detector" section: fits from a detector's landmarks against the main fits of the
same identities, each number computed again here from the arrays."""
from __future__ import annotations

import numpy as np

from reflectmm_cli.artifacts import read_artifact, write_artifact
from reflectmm_cli.evaluation.report import build_report

NAMES = ["09_0", "13_0", "05_1", "19_0"]


def _geometry(path, ident, verts, centres, evidence):
    return write_artifact(path, "geometry", {
        "vertices": verts.astype(np.float32), "cam_centers": centres, "view_names": np.array(NAMES),
        "view_evidence": np.array(evidence)}, extra_meta={"identity": ident})


def test_detected_section_against_the_main_fits(tmp_path):
    rng = np.random.default_rng(0)
    truth, main, det = {}, [], []
    expect = {}
    for k, ident in enumerate(("005", "006")):
        vt = rng.normal(0, 50, (40, 3))
        ct = rng.normal(0, 1000, (4, 3))
        truth[ident] = {"vertices": vt.astype(np.float32), "camera_names": np.array(NAMES), "cam_centers": ct}
        vm = vt + rng.normal(0, 1.0, vt.shape)
        vd = vt + rng.normal(0, 2.0 + k, vt.shape)
        cd = ct + rng.normal(0, 30, ct.shape)
        main.append(_geometry(tmp_path / "main" / f"{ident}.npz", ident, vm, ct + 5, ["landmarks"] * 4))
        det.append(_geometry(tmp_path / "det" / f"{ident}.npz", ident, vd, cd,
                             ["rig+flash", "landmarks+flash", "landmarks", "rig"]))
        rms = lambda v: np.sqrt(((v.astype(np.float32).astype(np.float64) - vt.astype(np.float32)) ** 2)
                                .sum(1).mean())
        d = np.linalg.norm(cd - ct, axis=1)
        expect[ident] = (rms(vd) / rms(vm), max(d[1], d[2]), max(d[0], d[3]))
    read = lambda paths: [(p, read_artifact(p, "geometry")) for p in paths]
    text, doc = build_report(tmp_path, tmp_path / "report.md", geometry=read(main), truth=truth,
                             detected=read(det))
    assert "## Landmarks from a detector" in text
    got = doc["detected"]["identities"]
    for ident, (ratio, with_lm, without) in expect.items():
        assert np.isclose(got[ident]["ratio"], ratio, rtol=1e-6)
        assert np.isclose(got[ident]["camera_max_with_landmarks_mm"], with_lm)
        assert np.isclose(got[ident]["camera_max_without_landmarks_mm"], without)
        assert got[ident]["views_with_landmarks"] == 2 and f"| {ident} | 2 / 4 |" in text
    assert np.isclose(doc["detected"]["median_ratio"], np.median([e[0] for e in expect.values()]))
    # without detector fits the section is not there
    text, doc = build_report(tmp_path, tmp_path / "report.md", geometry=read(main), truth=truth)
    assert "Landmarks from a detector" not in text and "detected" not in doc


def test_detected_fit_without_view_evidence_counts_every_view_as_annotated(tmp_path):
    """A geometry artifact from before views without landmarks has no view_evidence: every view had landmarks."""
    rng = np.random.default_rng(1)
    vt = rng.normal(0, 50, (20, 3))
    ct = rng.normal(0, 1000, (4, 3))
    truth = {"001": {"vertices": vt.astype(np.float32), "camera_names": np.array(NAMES), "cam_centers": ct}}
    p = write_artifact(tmp_path / "001.npz", "geometry", {
        "vertices": (vt + 1).astype(np.float32), "cam_centers": ct + 2, "view_names": np.array(NAMES)},
        extra_meta={"identity": "001"})
    art = read_artifact(p, "geometry")
    text, doc = build_report(tmp_path, tmp_path / "r.md", geometry=[(p, art)], truth=truth, detected=[(p, art)])
    got = doc["detected"]["identities"]["001"]
    assert got["views_with_landmarks"] == 4 and got["camera_max_without_landmarks_mm"] is None
    assert np.isclose(got["ratio"], 1.0) and np.isclose(got["camera_max_with_landmarks_mm"], 2 * np.sqrt(3))


def test_detected_section_against_a_reference_set(tmp_path):
    """The demo's shape: the main fits are the detector's, and a reference set (landmarks on every view) of some
    of the identities gives the ratios; an identity without a reference fit has none."""
    rng = np.random.default_rng(2)
    truth, det, ref, expect = {}, [], [], {}
    for k, ident in enumerate(("001", "002", "003")):
        vt = rng.normal(0, 50, (30, 3))
        ct = rng.normal(0, 1000, (4, 3))
        truth[ident] = {"vertices": vt.astype(np.float32), "camera_names": np.array(NAMES), "cam_centers": ct}
        vd = vt + rng.normal(0, 2.0, vt.shape)
        det.append(_geometry(tmp_path / "det" / f"{ident}.npz", ident, vd, ct + 7,
                             ["rig", "landmarks", "landmarks", "rig+flash"]))
        if ident != "003":
            vr = vt + rng.normal(0, 1.0 + k, vt.shape)
            ref.append(_geometry(tmp_path / "ref" / f"{ident}.npz", ident, vr, ct, ["landmarks"] * 4))
            rms = lambda v: np.sqrt(((v.astype(np.float32).astype(np.float64) - vt.astype(np.float32)) ** 2)
                                    .sum(1).mean())
            expect[ident] = rms(vd) / rms(vr)
    read = lambda paths: [(p, read_artifact(p, "geometry")) for p in paths]
    text, doc = build_report(tmp_path, tmp_path / "report.md", geometry=read(det), truth=truth,
                             detected=read(det), reference=read(ref))
    got = doc["detected"]["identities"]
    for ident, ratio in expect.items():
        assert np.isclose(got[ident]["ratio"], ratio, rtol=1e-6)
    assert np.isnan(got["003"]["ratio"]) and got["003"]["vertex_rms_all_landmarks_mm"] is None
    assert np.isclose(doc["detected"]["median_ratio"], np.median(list(expect.values())))
    assert "annotated reference" in text and set(doc["reference_geometry"]) == {"001", "002"}
