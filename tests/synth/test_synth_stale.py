"""An output folder holding an earlier run's files that a new run would not overwrite is refused: preprocess-multipie
and build-light-pca read whole folders, so the two runs' files would be taken as one data set."""
from reflectmm_cli.errors import ReflectmmError


def test_synth_multipie_refuses_an_earlier_runs_other_identities(tmp_path, cli):
    args = ("synth", "multipie", "--out", tmp_path / "syn", "--image-size", "80x60", "--face-vertices", "800",
            "--uv-size", "16", "--cameras", "05_1", "--flashes", "07")
    assert cli(*args, "--identities", "2").exit_code == 0
    assert cli(*args, "--identities", "2").exit_code == 0  # the same run again overwrites every file
    r = cli(*args, "--identities", "1")
    assert r.exit_code == 1 and "holds" in r.stderr and "002" in r.stderr and "would not overwrite" in r.stderr
    # nothing was deleted
    assert (tmp_path / "syn" / "truth" / "002.npz").is_file()


def test_synth_envmaps_refuses_an_earlier_runs_other_maps(tmp_path):
    import pytest

    from reflectmm_cli.synth.envmaps import write_envmaps

    write_envmaps(tmp_path, 3, seed=0, width=16, contact_sheet=False)
    before = sorted(p.name for p in tmp_path.glob("env_*.exr"))
    write_envmaps(tmp_path, 3, seed=0, width=16, contact_sheet=False)
    with pytest.raises(ReflectmmError, match="holds 1 environment map"):
        write_envmaps(tmp_path, 2, seed=0, width=16, contact_sheet=False)
    assert sorted(p.name for p in tmp_path.glob("env_*.exr")) == before


def test_synth_multipie_resumes_beside_a_killed_runs_temporary_file(tmp_path, cli):
    # a kill during an atomic write leaves `.NAME.RANDOM.tmp` beside the image; it is no earlier run's data
    args = ("synth", "multipie", "--out", tmp_path / "syn", "--image-size", "80x60", "--face-vertices", "800",
            "--uv-size", "16", "--cameras", "05_1", "--flashes", "07", "--identities", "1")
    assert cli(*args).exit_code == 0
    image = next((tmp_path / "syn" / "data").rglob("*_07.png"))
    leftover = image.parent / f".{image.name}.k0mimpu_.tmp"
    leftover.write_bytes(b"partial")
    r = cli(*args)
    assert r.exit_code == 0, r.stderr
    assert leftover.exists()  # not ours to delete: the rerun only does not take it for data
