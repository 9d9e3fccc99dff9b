"""Workspace conventions in one place: default paths and the discovery rules every verb shares.

* The workspace: ``--workspace``, else ``$REFLECTMM_WORKSPACE``, else the current directory.
* A stage's output: ``<workspace>/<stage>/<id>.npz`` (``<stage>/<stage>.npz`` for a stage that is not per
  identity) — :func:`stage_output`; recipes name stages after verbs so both agree.
* An identity (``--id``, ``--ids``, an ids file, a recipe's ``foreach``, a discovered id) names files, so it must
  be a *safe id* (:data:`ID_RULE`, checked by :func:`check_id` — the one place that says what an id may be), and a
  path the conventions compose must stay inside the workspace (:func:`check_inside`).  Paths the user gives
  explicitly (``--input``, ``-o``) are the user's choice and are not checked.
* Face model (one search order, first hit wins — :func:`find_face_model`): the face model a geometry artifact
  records → ``face_model.npz`` of the capture's dataset folder → ``<ws>/face_model.npz`` →
  ``<ws>/synth/face_model.npz`` → ``<ws>/synth-multipie/face_model.npz``.
* Rig: ``rig.toml`` of the capture's dataset folder, else None (the packaged Multi-PIE rig). A per-identity fit
  (``fit-geometry``) takes the workspace's calibrated rig (``calibrate-rig/rig.toml``) first, with the soft
  constraints that go with it (:data:`CALIBRATED_RIG_SIGMAS`) and, for a capture with flash images, the flash
  rounds (:data:`CALIBRATED_RIG_FLASH_ROUNDS`), and says on stderr which rig it took.  A
  calibrated rig also brings the landmark definition it was calibrated with (:func:`rig_calibration`): the
  command's default face model and landmark weights are the calibration's, and a fit on that rig with others is
  warned about.
* In-the-wild images (:func:`find_wild_truth`, :func:`wild_face_model`): the ``synth wild`` folder of an
  images folder is its parent when that holds ``manifest.npz``; the face model defaults to that folder's
  ``face_model.npz``.
* Ground truth (one rule — :func:`find_truth_dir`): ``truth/`` of the capture's dataset folder → ``<ws>/truth``
  → ``<ws>/synth/truth`` → ``<ws>/synth-multipie/truth``; per identity ``<dir>/<id>.npz``.

A command's default inputs are these rules applied to each input role as the stage declares it
(``Input(..., default=Default(...))``, :func:`reflectmm_cli.stages.defaults.default_inputs`).

No click here: stages, the planner, the report and the commands all import this module.
"""

from __future__ import annotations

import os
import re
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

__all__ = ["ID_RULE", "check_id", "check_inside", "default_workspace", "resolve_workspace", "stage_dir",
           "stage_output", "capture_root",
           "face_model_from_geometry", "find_face_model", "find_rig", "calibrated_rig", "find_fit_rig",
           "CALIBRATED_RIG_SIGMAS", "CALIBRATED_RIG_FLASH_ROUNDS", "RigCalibration", "rig_calibration",
           "find_truth_dir",
           "files_in", "walk_files", "check_given_once", "list_artifacts", "face_model_recorded_by", "find_wild_truth",
           "wild_face_model", "FACE_MODEL_NAME", "WORKSPACE_FACE_MODELS", "WORKSPACE_TRUTH_DIRS"]

#: File name of a dataset's / workspace's face model.
FACE_MODEL_NAME = "face_model.npz"
#: Where a face model is looked for inside a workspace (after the geometry's and the dataset's own).
WORKSPACE_FACE_MODELS = ("face_model.npz", "synth/face_model.npz", "synth-multipie/face_model.npz")
#: Where ground truth (synth-truth ``<id>.npz``) is looked for inside a workspace (after the dataset's own).
WORKSPACE_TRUTH_DIRS = ("truth", "synth/truth", "synth-multipie/truth")

#: What an identity may be: it becomes a file name (``<workspace>/<stage>/<id>.npz``), so no path separator, no
#: ``..``, no leading ``/``, no space or shell character (Multi-PIE's ``001``, ``w001_000024``, ``shard_00000``).
ID_RULE = "a safe id is 1-128 letters, digits, '_' or '-' (e.g. 001, w001_000024, shard_00000)"
_ID_RE = re.compile(r"[A-Za-z0-9_-]{1,128}")


def check_id(identity: Any, where: str = "id") -> str:
    """``identity`` as a str if it is a safe id (:data:`ID_RULE`); else a one-line error naming ``where`` it came
    from (``--id``, ``[stages.x] foreach``, ``ids.txt: line 3``), the id and the rule.  Every way an identity
    enters (options, id files, recipes, discovery, :class:`~reflectmm_cli.stages.StageContext`) calls this."""
    from reflectmm_cli.errors import ReflectmmError

    text = identity if isinstance(identity, str) else str(identity)
    if not (text.isascii() and _ID_RE.fullmatch(text)):
        raise ReflectmmError(f"{where}: id {text!r} refused: {ID_RULE}")
    return text


def check_inside(path: Path | str, workspace: Path | str) -> Path:
    """``path`` (a path composed by the workspace conventions) if it lies inside ``workspace`` once ``.`` and
    ``..`` are resolved; else a one-line error.  The check is on the path as written (a symlink the user put
    inside the workspace is the user's choice)."""
    from reflectmm_cli.errors import ReflectmmError

    ws = os.path.normpath(os.path.abspath(workspace))
    p = os.path.normpath(os.path.abspath(path))
    if os.path.commonpath([ws, p]) != ws:
        raise ReflectmmError(f"resolves outside the workspace {ws}; a workspace path may not leave it", path)
    return Path(path)


def default_workspace() -> Path:
    """``$REFLECTMM_WORKSPACE`` or the current directory (absolute)."""
    return Path(os.environ.get("REFLECTMM_WORKSPACE") or ".").resolve()


def resolve_workspace(workspace: Path | str | None) -> Path:
    """The given workspace (absolute) or :func:`default_workspace`."""
    return Path(workspace).resolve() if workspace is not None else default_workspace()


def stage_dir(workspace: Path, stage: str) -> Path:
    """``<workspace>/<stage>/``: the folder a stage writes into."""
    return Path(workspace) / stage


def stage_output(workspace: Path, stage: str, name: str | None = None, suffix: str = ".npz") -> Path:
    """``<workspace>/<stage>/<name><suffix>`` (name = the identity, or the stage name for an aggregate); a
    one-line error if it would lie outside the workspace (:func:`check_inside`)."""
    return check_inside(stage_dir(workspace, stage) / f"{name if name is not None else stage}{suffix}", workspace)


def files_in(folder: Path, suffix: str = ".npz") -> list[Path]:
    """The ``*<suffix>`` files of a folder (sorted; hidden temp files left out); none if it is not a folder."""
    folder = Path(folder)
    return sorted(p for p in folder.glob(f"*{suffix}") if not p.name.startswith(".")) if folder.is_dir() else []


def walk_files(folder: Path) -> list[Path]:
    """Files under ``folder``, recursively, sorted; hidden files and hidden folders (``.reflectmm/``,
    temporary ``.name.*.tmp`` files of atomic writes) are skipped."""
    folder = Path(folder)
    return sorted(q for q in folder.rglob("*")
                  if q.is_file() and not any(part.startswith(".") for part in q.relative_to(folder).parts))


def check_given_once(paths, reason: str, where: str = "") -> None:
    """Refuse a file given twice once the paths are resolved (a folder and one of its files, one file twice, a link
    to it), where it would count twice: ``<path>: <where>given twice (also as <first path>): <reason>``."""
    from reflectmm_cli.errors import ReflectmmError

    seen: dict[Path, Path] = {}
    for p in paths:
        key = Path(p).resolve()
        if key in seen:
            raise ReflectmmError(f"{where}given twice (also as {seen[key]}): {reason}", p)
        seen[key] = Path(p)


def list_artifacts(workspace: Path, stage: str, suffix: str = ".npz") -> list[Path]:
    """The ``*<suffix>`` a stage wrote in ``<workspace>/<stage>/`` (sorted; hidden temp files left out)."""
    return files_in(stage_dir(workspace, stage), suffix)


def _meta_of(artifact: Any) -> tuple[dict, Path | None]:
    """(meta, path) of an Artifact or of an artifact path."""
    if isinstance(artifact, (str, Path)):
        from reflectmm_cli.artifacts import read_meta

        return read_meta(Path(artifact)), Path(artifact)
    return artifact.meta, (Path(artifact.path) if artifact.path is not None else None)


def capture_root(capture: Any) -> Path | None:
    """The dataset folder a capture artifact (Artifact or path) was made from — its meta input of role
    ``root`` — if it exists."""
    meta, path = _meta_of(capture)
    for ref in meta.get("inputs", []):
        if ref.get("role") == "root" and path is not None:
            p = (path.parent / ref.get("path", "")).resolve()
            if p.is_dir():
                return p
    return None


def _recorded_inputs(artifact: Any, is_role):
    """The inputs an artifact (Artifact or path) records under a role that ``is_role`` accepts (``-`` read as
    ``_``): (its meta reference, the path it resolves to), in the recorded order."""
    meta, path = _meta_of(artifact)
    if path is None:
        return
    for ref in meta.get("inputs", []):
        if is_role(str(ref.get("role", "")).replace("-", "_")):
            yield ref, (path.parent / ref.get("path", "")).resolve()


def face_model_recorded_by(artifact: Any, is_face_model_role=lambda role: role == "face_model") -> Path | None:
    """The face model an artifact (Artifact or path) records among its inputs (a role that
    ``is_face_model_role`` accepts, ``-`` read as ``_``), if that file is present."""
    return next((p for _, p in _recorded_inputs(artifact, is_face_model_role) if p.is_file()), None)


def face_model_from_geometry(geometry: Any) -> Path | None:
    """The face model a geometry artifact (Artifact or path) was fitted with, if recorded and present (its role is
    ``face_model``, ``model`` or names a face)."""
    return face_model_recorded_by(geometry, lambda role: role in ("face_model", "model") or "face" in role)


def find_face_model(workspace: Path, capture: Any = None, geometry: Any = None) -> Path | None:
    """The face model by the one search order (module docstring); None if there is none."""
    if geometry is not None:
        found = face_model_from_geometry(geometry)
        if found is not None:
            return found
    candidates: list[Path] = []
    if capture is not None:
        root = capture_root(capture)
        if root is not None:
            candidates.append(root / FACE_MODEL_NAME)
    candidates += [Path(workspace) / c for c in WORKSPACE_FACE_MODELS]
    return next((p for p in candidates if p.is_file()), None)


def find_rig(capture: Any) -> Path | None:
    """``rig.toml`` of the capture's dataset folder, if present (else the caller uses the packaged rig)."""
    root = capture_root(capture) if capture is not None else None
    if root is not None and (root / "rig.toml").is_file():
        return root / "rig.toml"
    return None


#: The soft rig constraints that go with a calibrated rig (docs/fit-geometry.md): camera centres within 3 mm and
#: aims within 0.3° of the calibrated table, moved rigidly.
CALIBRATED_RIG_SIGMAS = {"rig_sigma_mm": 3.0, "rig_rot_sigma_deg": 0.3}

#: The rounds that go with a calibrated rig when the capture has flash images: its flashes sit on its cameras,
#: placed to a few millimetres, so the flash term shapes the face instead of the room-light rounds, and registers
#: the views without landmarks (docs/fit-geometry.md, "Flash term").
CALIBRATED_RIG_FLASH_ROUNDS = {"photo_rounds": 0, "flash_rounds": 3}


def calibrated_rig(workspace: Path) -> Path:
    """``<ws>/calibrate-rig/rig.toml``: where ``calibrate-rig`` writes the rig table a per-identity fit takes first."""
    return Path(workspace) / "calibrate-rig" / "rig.toml"


@dataclass(frozen=True)
class RigCalibration:
    """What a per-identity fit on a calibrated rig must share with the calibration: its landmark definition.

    The calibration placed the cameras from landmarks on the vertices of ``face_model`` (None: not recorded or not
    found) weighted by ``landmark_weights`` (per group, as its params recorded them; the groups not named keep
    their default weight); a fit with another face model or other weights (a detector's jaw points on the model's
    fixed jaw vertices) puts its face in another frame than the rig's."""

    artifact: Path
    face_model: Path | None
    face_model_problem: str = ""   # the recorded face model is gone or changed since (empty: it is as recorded)
    face_model_sha256: str = ""    # the recorded face model's sha256 (empty: not recorded)
    landmark_weights: dict = field(default_factory=dict)


CALIBRATED_RIG_HEADER = "Rig calibrated by calibrate-rig"
"""The first line of a rig table that ``calibrate-rig`` wrote (after the TOML comment sign)."""


def written_by_calibration(rig: Path) -> bool:
    """Whether the rig table ``rig`` says (its first line, :data:`CALIBRATED_RIG_HEADER`) that calibrate-rig
    wrote it."""
    try:
        with open(rig, encoding="utf-8", errors="replace") as f:
            first = f.readline()
    except OSError:
        return False
    return first.lstrip("# ").startswith(CALIBRATED_RIG_HEADER)


def rig_calibration(rig: Path | None) -> RigCalibration | None:
    """The ``calibrate-rig`` artifact that wrote the rig table ``rig``, as a :class:`RigCalibration`: an NPZ of
    schema ``reflectmm.rig`` beside it whose meta names it (``toml``) — ``<stage>/<stage>.npz`` in a workspace,
    else the newest such file in the folder.  None when no calibration wrote it (a nominal or hand-made table).

    A table that says calibrate-rig wrote it but has no readable artifact beside it is a one-line error: its
    landmark definition, which a fit on it must share, is then unknown (the caller may catch it where that
    definition is given explicitly).  A recorded face model that is gone or whose bytes changed since is named in
    ``face_model_problem``."""
    if rig is None or Path(rig).suffix.lower() != ".toml":
        return None
    from reflectmm_cli.artifacts import read_artifact
    from reflectmm_cli.errors import ReflectmmError

    rig = Path(rig)
    first = rig.parent / f"{rig.parent.name}.npz"
    others = sorted((p for p in rig.parent.glob("*.npz") if p != first), key=lambda p: -p.stat().st_mtime)
    unreadable = []
    for art_path in ([first] if first.is_file() else []) + others:
        try:
            art = read_artifact(art_path, "rig", members=())
        except ReflectmmError as e:
            unreadable.append(str(e))
            continue
        if art.meta.get("toml") == rig.name:
            weights = (art.meta.get("params") or {}).get("landmark_weights") or {}
            return RigCalibration(art_path, *_recorded_face_model(art),
                                  landmark_weights={str(k): float(v) for k, v in weights.items()})
    if written_by_calibration(rig):
        why = "; ".join(unreadable) if unreadable else f"no {first.name} beside it"
        raise ReflectmmError(
            f"written by calibrate-rig, but no readable calibration artifact beside it names it ({why}): the face "
            "model and landmark weights it was calibrated with are unknown; run calibrate-rig again, or give "
            "--face-model and --landmark-weights as they were", rig)
    return None


def _recorded_face_model(art: Any) -> tuple[Path | None, str, str]:
    """The face model a calibration artifact records, what is wrong with it and its recorded sha256: (path, "",
    sha) when it is there with the recorded bytes, (None, "", "") when none is recorded, else (path or None, the
    problem, sha)."""
    from reflectmm_cli.artifacts import sha256_file

    for ref, p in _recorded_inputs(art, lambda role: role == "face_model"):
        want = str(ref.get("sha256") or "")
        if not p.is_file():
            return None, f"the face model it was calibrated with, {p}, is gone", want
        if want and sha256_file(p) != want:
            return p, f"the face model it was calibrated with, {p}, has changed since (not the recorded sha256)", want
        return p, "", want
    return None, "", ""


def find_fit_rig(workspace: Path, capture: Any = None) -> tuple[Path | None, str]:
    """The rig a per-identity fit takes by default, and where it comes from: the workspace's calibrated rig
    (``<ws>/calibrate-rig/rig.toml``, written by ``calibrate-rig``) first, then the capture dataset's
    ``rig.toml``, else None (the packaged Multi-PIE rig). Returns ``(path, "calibrated" | "dataset" | "packaged")``.
    """
    cal = calibrated_rig(workspace)
    if cal.is_file():
        return cal, "calibrated"
    found = find_rig(capture)
    return (found, "dataset") if found is not None else (None, "packaged")


def find_truth_dir(workspace: Path | None, capture: Any = None) -> Path | None:
    """The ground-truth folder by the one rule (module docstring); None if there is none."""
    candidates: list[Path] = []
    if capture is not None:
        root = capture_root(capture)
        if root is not None:
            candidates.append(root / "truth")
    if workspace is not None:
        candidates += [Path(workspace) / c for c in WORKSPACE_TRUTH_DIRS]
    return next((p for p in candidates if p.is_dir()), None)


def find_wild_truth(images: Path | None) -> Path | None:
    """The ``synth wild`` folder an images folder belongs to: its parent if that holds ``manifest.npz``."""
    if images is None:
        return None
    parent = Path(images).parent
    return parent if (parent / "manifest.npz").is_file() else None


def wild_face_model(face_model: Path | None, truth: Path | None) -> Path | None:
    """The face model of ``prepare-wild``: the given one, else ``<synth wild folder>/face_model.npz``."""
    if face_model is not None:
        return Path(face_model)
    if truth is not None and (Path(truth) / FACE_MODEL_NAME).is_file():
        return Path(truth) / FACE_MODEL_NAME
    return None
