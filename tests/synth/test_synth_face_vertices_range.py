"""Issue 24 §6: `synth wild --face-vertices 200` was refused although its help said the minimum was 200. The
declared range of both synth verbs now starts at the procedural model's own minimum, and that minimum builds."""
import pytest

from reflectmm_cli.geometry.procedural import MIN_VERTICES, procedural_face_model


@pytest.mark.parametrize("verb", ["synth-wild", "synth-multipie"])
def test_declared_minimum_is_the_models_minimum(verb, cli, tmp_path):
    from reflectmm_cli.stages import get_stage

    p = {q.name: q for q in get_stage(verb).params}["face_vertices"]
    assert p.range[0] == MIN_VERTICES
    fm = procedural_face_model(n_vertices=MIN_VERTICES)
    assert fm.n_vertices >= MIN_VERTICES * 0.9
    r = cli(*verb.split("-", 1), "--face-vertices", str(MIN_VERTICES - 1), "--out", tmp_path / "x")
    assert r.exit_code != 0 and f"below the minimum {MIN_VERTICES}" in r.stderr
