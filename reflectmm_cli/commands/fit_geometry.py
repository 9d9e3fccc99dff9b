"""``reflectmm fit-geometry``: click wrapper of the ``fit-geometry`` stage (reflectmm_cli/stages/fit_geometry.py).

Python API: :func:`reflectmm_cli.geometry_fit.identity.fit_identity`.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import click

from reflectmm_cli.commands._common import (device_option, emit, given_params, id_callback, json_option,
                                            output_option, param_options, run_stage_cli, workspace_option)
from reflectmm_cli.errors import ReflectmmError
from reflectmm_cli.geometry_fit.landmarks import format_group_weights
from reflectmm_cli.stages.defaults import default_inputs
from reflectmm_cli.stages.fit_geometry import PARAMS, STAGE, VERB
from reflectmm_cli.progress import log
from reflectmm_cli.workspace import (CALIBRATED_RIG_FLASH_ROUNDS, CALIBRATED_RIG_SIGMAS, calibrated_rig,
                                     resolve_workspace, rig_calibration)


@click.command(VERB)
@click.option("--id", "identity", callback=id_callback, required=True, help="Identity (e.g. 042).")
@click.option("--capture", type=click.Path(dir_okay=False, path_type=Path), default=None,
              help="capture artifact (default <ws>/preprocess-multipie/<id>.npz).")
@click.option("--face-model", type=click.Path(dir_okay=False, path_type=Path), default=None,
              help="face model: face-model artifact or BFM09/Deep3DFaceRecon .mat (default: the one the workspace's "
                   "calibrated rig was made with, else face_model.npz of the capture's dataset folder, else "
                   "<ws>/face_model.npz).")
@click.option("--rig", type=click.Path(dir_okay=False, path_type=Path), default=None,
              help="rig table TOML (default: the workspace's calibrated rig <ws>/calibrate-rig/rig.toml with "
                   "--rig-sigma 3 --rig-rot-sigma 0.3, with flash images --photo-rounds 0 --flash-rounds 3, and "
                   "its calibration's face model and landmark weights, each unless given; else rig.toml of the "
                   "capture's dataset folder, else the packaged Multi-PIE rig; stderr says which).")
@click.option("--landmarks", "landmarks_dir", type=click.Path(file_okay=False, path_type=Path), default=None,
              help="folder with landmark files <view>.{pts,txt,npy} or *_<CCC>_00_lm.{pts,txt,npy} "
                   "(full-frame pixels; default: the landmarks stored in the capture).")
@click.option("--iters", type=click.IntRange(0, None), default=None,
              help="L-BFGS iterations of the landmark stage (default 400; the photometric rounds scale with it).")
@click.option("--truth", "truth", type=click.Path(dir_okay=False, path_type=Path), default=None,
              help="synth-truth artifact to report errors against (default: <dataset>/truth/<id>.npz if present).")
@click.option("--from-truth", "from_truth", type=click.Path(dir_okay=False, path_type=Path), default=None,
              help="write the ground-truth geometry of this synth-truth artifact (or of a registered scan .ply/.obj "
                   "with --rig CAMERAS.toml) instead of fitting.")
@param_options(PARAMS)
@device_option
@workspace_option
@output_option
@json_option
def fit_geometry_cmd(identity, capture, face_model, rig, landmarks_dir, iters, truth, from_truth, device, workspace,
                     output, as_json, **kw):
    """Fit one identity's shape, expression and per-view cameras to its landmarks and room-light images.

    Writes the `geometry` artifact (<ws>/fit-geometry/<id>.npz) and one overlay PNG per view.
    """
    ws = resolve_workspace(workspace)
    params: dict[str, Any] = given_params(kw, PARAMS)
    given = {"capture": [capture], "face_model": [face_model], "rig": [rig], "landmarks": [landmarks_dir]}
    if from_truth is not None:  # the capture and its face model only where they are found; the rig only if given
        inputs = default_inputs(STAGE, ws, {**given, "truth": [from_truth], "landmarks": []}, identity=identity,
                                roles=("capture", "face_model"), required=False)
        params["from_truth"] = True
        paths = run_stage_cli(VERB, workspace=ws, identity=identity, params=params, inputs=inputs, output=output,
                              device=device)
        emit(paths, as_json)
        return
    # the workspace's calibrated rig, the default rig when it exists, brings the landmark definition it was made
    # with: its face model and landmark weights, unless given (stages/fit_geometry.check_rig_landmarks)
    cal = None
    if rig is None and calibrated_rig(ws).is_file():
        try:
            cal = rig_calibration(calibrated_rig(ws))
        except ReflectmmError:
            if face_model is None or "landmark_weights" not in params:
                raise  # the defaults would come from a calibration that cannot be read
            # both given: the stage says that it cannot compare them with the calibration
    if cal is not None and face_model is None and cal.face_model_problem:
        raise ReflectmmError(f"{cal.face_model_problem}: run calibrate-rig again, or give --face-model (the same "
                             "model)", cal.artifact)
    took = []
    if cal is not None and face_model is None and cal.face_model is not None:
        given["face_model"] = [cal.face_model]
        took.append(f"face model {cal.face_model}")
    if cal is not None and "landmark_weights" not in params and format_group_weights(cal.landmark_weights):
        params["landmark_weights"] = dict(cal.landmark_weights)
        took.append(f"landmark weights {format_group_weights(cal.landmark_weights)}")
    inputs = default_inputs(STAGE, ws, {**given, "truth": [truth]}, identity=identity)
    if rig is None:  # the default rig: the calibrated one brings its soft constraints; stderr says which
        rig = (inputs.get("rig") or [None])[0]
        if rig is not None and rig == calibrated_rig(ws):
            for k, v in CALIBRATED_RIG_SIGMAS.items():
                params.setdefault(k, v)
            rounds = ""
            if _has_flash_images(inputs["capture"][0]):
                for k, v in CALIBRATED_RIG_FLASH_ROUNDS.items():
                    params.setdefault(k, v)
                rounds = f", {params['photo_rounds']} room-light and {params['flash_rounds']} flash rounds"
            log.info("fit-geometry: rig: the workspace's calibrated rig %s (σ %g mm, %g°%s%s)", rig,
                     params["rig_sigma_mm"], params["rig_rot_sigma_deg"], rounds,
                     "; its calibration's " + ", ".join(took) if took else "")
        else:
            log.info("fit-geometry: rig: %s", f"the capture dataset's {rig}" if rig is not None
                     else "the packaged Multi-PIE rig")
    if iters is not None:
        params["landmark_iters"] = iters
        params["photo_iters"] = max(1, iters // 10) if iters else 0
    paths = run_stage_cli(VERB, workspace=ws, identity=identity, params=params, inputs=inputs, output=output,
                          device=device)
    emit(paths, as_json)


def _has_flash_images(capture: Path) -> bool:
    """Whether the capture holds flash images (a flash id; an unreadable file is the stage's to refuse)."""
    from reflectmm_cli.artifacts import read_artifact

    try:
        return bool(len(read_artifact(capture, "capture", members=("flash_ids",)).arrays.get("flash_ids", ())))
    except (ReflectmmError, OSError):
        return False


COMMANDS = [fit_geometry_cmd]
