"""Versioned, self-describing, atomically written artifacts (docs/design.md §5).

An artifact is one file:

* NPZ: arrays plus a ``__meta__`` entry holding a JSON string; always read with
  ``allow_pickle=False``.  The zip container is written with fixed timestamps and a
  fixed member order, so the same arrays and meta give byte-identical files.
* EXR (through OpenImageIO): named float16/float32 channels plus the same JSON in
  the header attribute ``reflectmm:meta``.

The meta has ``schema: "reflectmm.<kind>/<major>"``, ``producer`` (stage, stage
version, tool version), resolved ``params``, ``inputs`` (role, path relative to the
artifact, sha256, schema) and ``cache_key``.  No timestamps or host names.

Readers asked for kind X refuse kind Y, and refuse a major version newer than this
release reads.  Writes go to a temporary file in the same folder, are fsynced and
renamed over the target, so an interrupted run leaves the old file or none.
"""

from __future__ import annotations

import errno
import hashlib
import io
import json
import os
import struct
import tempfile
import tokenize
import zipfile
import zlib
from contextlib import contextmanager
from contextvars import ContextVar
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Collection, Iterator, Mapping

import numpy as np

from reflectmm_cli import __version__
from reflectmm_cli.errors import ArtifactError, ReflectmmError

META_KEY = "__meta__"
EXR_META_ATTR = "reflectmm:meta"

#: Current major schema version of every artifact kind this release writes and reads.
#: A reader refuses a file whose major version is newer than the one listed here.
SCHEMA_MAJOR: dict[str, int] = {
    "checksum": 1,
    "face-model": 1,
    "synth-truth": 1,
    "capture": 1,
    "geometry": 1,
    "uv-observations": 1,
    "reflectance-maps": 1,
    "reflectance-model": 1,
    "light-model": 1,
    "render": 1,
    "evaluation": 1,
    "envmap": 1,
    "wild-shard": 1,
    "wild-truth": 1,
    "wild-manifest": 1,
    "viewer": 1,
}

_ZIP_EPOCH = (1980, 1, 1, 0, 0, 0)


@dataclass
class Artifact:
    """An artifact in memory: its kind, arrays and meta."""

    kind: str
    arrays: dict[str, np.ndarray]
    meta: dict[str, Any] = field(default_factory=dict)
    path: Path | None = None

    def __getitem__(self, name: str) -> np.ndarray:
        try:
            return self.arrays[name]
        except KeyError:
            raise ArtifactError(f"{self.kind} artifact has no array '{name}' "
                                f"(has: {', '.join(sorted(self.arrays))})", self.path) from None

    def __contains__(self, name: object) -> bool:
        return name in self.arrays

    def keys(self):
        return self.arrays.keys()

    def get(self, name: str, default: Any = None) -> Any:
        """The array ``name``, or ``default`` when the artifact has none (as ``dict.get``)."""
        return self.arrays.get(name, default)

    @property
    def params(self) -> dict[str, Any]:
        return self.meta.get("params", {})


# --------------------------------------------------------------------------- hashing

def sha256_file(path: str | Path, chunk: int = 1 << 20) -> str:
    """Hex sha256 of a file's content."""
    h = hashlib.sha256()
    try:
        with open(path, "rb") as f:
            for block in iter(lambda: f.read(chunk), b""):
                h.update(block)
    except FileNotFoundError:
        raise ReflectmmError("file not found", path) from None
    except IsADirectoryError:
        raise ReflectmmError("is a directory, expected a file", path) from None
    return h.hexdigest()


def canonical_json(obj: Any) -> str:
    """Deterministic JSON (sorted keys, no spaces) used in meta and cache keys."""
    return json.dumps(_jsonable(obj), sort_keys=True, separators=(",", ":"), allow_nan=False)


def _jsonable(obj: Any) -> Any:
    if isinstance(obj, Mapping):
        return {str(k): _jsonable(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_jsonable(v) for v in obj]
    if isinstance(obj, Path):
        return str(obj)
    if isinstance(obj, np.generic):
        return obj.item()
    if isinstance(obj, np.ndarray):
        return obj.tolist()
    if isinstance(obj, float) and not np.isfinite(obj):
        return repr(obj)
    return obj


def schema_of(path: str | Path) -> str | None:
    """The schema string of an artifact file, or None if the file is not an artifact."""
    try:
        return read_meta(path).get("schema")
    except ReflectmmError:
        return None


def path_for_meta(path: str | Path, artifact: str | Path) -> str:
    """``path`` as stored in the meta of the artifact at ``artifact``: relative to the artifact's folder, with
    forward slashes, so the same workspace in two places gives the same bytes (see :func:`input_ref`)."""
    return Path(os.path.relpath(Path(path).absolute(), Path(artifact).absolute().parent)).as_posix()


def input_ref(role: str, path: str | Path, relative_to: str | Path | None = None) -> dict[str, Any]:
    """Provenance record of one input file: role, path, sha256 and schema (if an artifact).

    ``path`` is stored relative to ``relative_to`` (the artifact's folder) when given, so
    the same workspace layout in two places gives identical meta.
    """
    p = Path(path)
    shown = os.path.relpath(p, relative_to) if relative_to is not None else p.name
    ref = {"role": role, "path": shown, "sha256": sha256_file(p)}
    if p.suffix.lower() in (".npz", ".exr"):
        sch = schema_of(p)
        if sch:
            ref["schema"] = sch
    return ref


# --------------------------------------------------------------------------- atomic files

@contextmanager
def atomic_path(path: str | Path, suffix: str | None = None) -> Iterator[Path]:
    """Yield a temporary path next to ``path``; on success fsync it and rename it over ``path``.

    On any exception the temporary file is removed and ``path`` is untouched.
    """
    target = Path(path)
    try:
        target.parent.mkdir(parents=True, exist_ok=True)
        fd, tmp = tempfile.mkstemp(prefix=f".{target.name}.", suffix=(suffix if suffix is not None else ".tmp"),
                                   dir=target.parent)
        os.close(fd)
    except OSError as exc:
        _raise_write_error(exc, target)
        raise
    tmp_path = Path(tmp)
    try:
        try:
            yield tmp_path
        except OSError as exc:  # the caller's write into tmp_path (disk full, quota...)
            _raise_write_error(exc, target)
            raise
        try:
            with open(tmp_path, "rb+") as f:
                os.fsync(f.fileno())
            os.chmod(tmp_path, 0o666 & ~_UMASK)  # mkstemp makes 0600; give the file the usual permissions
            staged = _STAGED.get()
            if staged is not None:  # inside committed_together(): renamed when the whole group has succeeded
                staged.append((tmp_path, target))
                return
            os.replace(tmp_path, target)
        except OSError as exc:
            _raise_write_error(exc, target)
            raise
        _fsync_dir(target.parent)
    except BaseException:
        try:
            tmp_path.unlink()
        except FileNotFoundError:
            pass
        raise


def _fsync_dir(folder: Path) -> None:
    try:
        dfd = os.open(folder, os.O_RDONLY)
        try:
            os.fsync(dfd)
        finally:
            os.close(dfd)
    except OSError:
        pass


#: the (temporary file, target) pairs of the innermost :func:`committed_together` block, else None
_STAGED: ContextVar[list[tuple[Path, Path]] | None] = ContextVar("reflectmm_staged_writes", default=None)


@contextmanager
def committed_together(last: str | Path | None = None) -> Iterator[None]:
    """Commit every atomic write of the block (:func:`write_artifact`, :func:`write_png`, :func:`write_exr`,
    :func:`atomic_write_bytes` ...) together, only when the whole block succeeds.

    Inside the block each file is written to its temporary file as usual but not renamed; at the end the targets
    are checked (none may be a folder) and renamed one after the other, in the order written, except ``last``
    (a stage's primary output, the file whose cache key says the outputs are up to date), which is renamed after
    all the others.  If anything in the block raises, no target is touched and the temporary files are removed: a
    run's outputs never mix files of a failed run with the previous run's.  If the renames themselves are cut short
    (a kill, a file that cannot be replaced), ``last`` is still the previous run's, so its key calls for a rerun.
    A nested block joins the outer one (and its ``last``).
    """
    if _STAGED.get() is not None:
        yield
        return
    staged: list[tuple[Path, Path]] = []
    token = _STAGED.set(staged)
    try:
        yield
        for _, target in staged:
            if target.is_dir():
                raise ReflectmmError("cannot write: a folder is in the way", target)
        if last is not None:
            final = os.path.abspath(last)
            staged.sort(key=lambda pair: os.path.abspath(pair[1]) == final)  # stable: the others keep their order
        for i, (tmp, target) in enumerate(staged):
            try:
                os.replace(tmp, target)
            except OSError as exc:
                _raise_write_error(exc, target)
                raise
            staged[i] = (target, target)
    finally:
        _STAGED.reset(token)
        for tmp, target in staged:
            if tmp != target:
                tmp.unlink(missing_ok=True)
    for folder in dict.fromkeys(t.parent for _, t in staged):
        _fsync_dir(folder)


@contextmanager
def written_at_once() -> Iterator[None]:
    """Inside :func:`committed_together`, a block whose atomic writes are renamed at once, as outside it: the work
    files of a long run (finetune's checkpoints and log), which a resumed run reads after a kill and the run itself
    reads back.  The block's own outputs can still be grouped by a :func:`committed_together` inside it."""
    token = _STAGED.set(None)
    try:
        yield
    finally:
        _STAGED.reset(token)


# errors of the file system, not of the data: reported as one line naming the file being written
_WRITE_ERRNOS = {errno.ENOSPC, errno.EDQUOT, errno.EROFS, errno.EACCES, errno.EPERM, errno.EFBIG, errno.EIO,
                 errno.ENOTDIR, errno.EISDIR, errno.ENAMETOOLONG}


def _raise_write_error(exc: OSError, target: Path) -> None:
    """Re-raise a file-system error of an atomic write as a ReflectmmError naming ``target`` (not the
    hidden temporary file); other errors are left to the caller."""
    if exc.errno in _WRITE_ERRNOS:
        what = {errno.ENOSPC: "no space left on the device", errno.EDQUOT: "disk quota exceeded",
                errno.EROFS: "read-only file system"}.get(exc.errno, exc.strerror or str(exc))
        where = "" if exc.errno in (errno.ENOSPC, errno.EDQUOT, errno.EROFS) else f" ({target.parent})"
        raise ReflectmmError(f"cannot write: {what[:1].lower() + what[1:]}{where} [errno {exc.errno}]",
                             target) from None


def _read_umask() -> int:
    mask = os.umask(0o022)
    os.umask(mask)
    return mask


_UMASK = _read_umask()  # read once at import: os.umask is process-wide and not thread-safe


def atomic_write_bytes(path: str | Path, data: bytes) -> Path:
    with atomic_path(path) as tmp:
        tmp.write_bytes(data)
    return Path(path)


def atomic_write_text(path: str | Path, text: str) -> Path:
    return atomic_write_bytes(path, text.encode("utf-8"))


# --------------------------------------------------------------------------- meta

def make_meta(kind: str, *, params: Mapping[str, Any] | None = None, inputs: list[dict] | None = None,
              producer: Mapping[str, Any] | None = None, cache_key: str | None = None,
              extra: Mapping[str, Any] | None = None) -> dict[str, Any]:
    major = SCHEMA_MAJOR.get(kind, 1)
    prod = {"tool": "reflectmm", "version": __version__}
    if producer:
        prod.update(producer)
    meta: dict[str, Any] = {
        "schema": f"reflectmm.{kind}/{major}",
        "producer": prod,
        "params": dict(params or {}),
        "inputs": list(inputs or []),
        "cache_key": cache_key,
    }
    if extra:
        meta.update(extra)
    return json.loads(canonical_json(meta))


def parse_schema(schema: Any, path: str | Path | None = None) -> tuple[str, int]:
    if not isinstance(schema, str) or not schema.startswith("reflectmm.") or "/" not in schema:
        raise ArtifactError(f"not a reflectmm artifact (schema {schema!r})", path)
    name, _, major = schema[len("reflectmm."):].rpartition("/")
    try:
        return name, int(major)
    except ValueError:
        raise ArtifactError(f"malformed schema {schema!r}", path) from None


def check_schema(meta: Mapping[str, Any], kind: str | None, path: str | Path | None) -> str:
    """Return the artifact kind; refuse a wrong kind or a newer major version."""
    found, major = parse_schema(meta.get("schema"), path)
    if kind is not None and found != kind:
        raise ArtifactError(f"is a '{found}' artifact, expected a '{kind}' artifact", path)
    supported = SCHEMA_MAJOR.get(found)
    if supported is not None and major > supported:
        prod = meta.get("producer", {})
        raise ArtifactError(
            f"schema reflectmm.{found}/{major} is newer than this reflectmm {__version__} reads "
            f"(up to /{supported}); it was written by {prod.get('tool', 'reflectmm')} "
            f"{prod.get('version', '?')} — upgrade reflectmm to read it", path)
    return found


# --------------------------------------------------------------------------- NPZ

def _npy_bytes(arr: np.ndarray) -> bytes:
    buf = io.BytesIO()
    arr = arr if arr.flags.c_contiguous else np.ascontiguousarray(arr)  # keeps 0-d arrays 0-d
    np.lib.format.write_array(buf, arr, allow_pickle=False)
    return buf.getvalue()


def artifact_identity(art: "Artifact") -> str | None:
    """The identity a per-identity artifact was made for (``meta.report.identity``, else ``meta.identity``)."""
    rep = art.meta.get("report")
    ident = rep.get("identity") if isinstance(rep, dict) else None
    ident = ident if ident is not None else art.meta.get("identity")
    return None if ident is None else str(ident)


def check_identity(art: "Artifact", identity: str | None) -> "Artifact":
    """Refuse an input artifact made for another identity than the task's (``--id 999`` given 001's files
    would otherwise label 001's data 999). Artifacts that record no identity pass."""
    have = artifact_identity(art)
    if identity is not None and have is not None and have != str(identity):
        raise ArtifactError(f"is identity {have}'s {art.kind}, but this task is for identity {identity}; "
                            f"pass the matching file or --id {have}", art.path)
    return art


def refuse_newer_target(path: str | Path) -> None:
    """Refuse to overwrite an artifact whose schema is newer than this release writes (a newer reflectmm made
    it; replacing it with an older format would lose data). Files that are not artifacts are not looked at."""
    p = Path(path)
    if not p.is_file() or p.suffix.lower() not in (".npz", ".exr"):
        return
    try:
        meta = read_meta(p)
        found, major = parse_schema(meta.get("schema"), p)
    except ReflectmmError:
        return  # not an artifact (or corrupt): an ordinary rewrite replaces it
    supported = SCHEMA_MAJOR.get(found)
    if supported is not None and major > supported:
        prod = meta.get("producer") or {}
        raise ArtifactError(
            f"holds schema reflectmm.{found}/{major}, written by {prod.get('tool', 'reflectmm')} "
            f"{prod.get('version', '?')}; this reflectmm {__version__} writes /{supported} and refuses to overwrite "
            f"it — upgrade reflectmm, or move the file away", p)


def write_artifact(path: str | Path, kind: str, arrays: Mapping[str, Any], *,
                   params: Mapping[str, Any] | None = None, inputs: list[dict] | None = None,
                   producer: Mapping[str, Any] | None = None, cache_key: str | None = None,
                   extra_meta: Mapping[str, Any] | None = None, compress: bool = True) -> Path:
    """Write an NPZ artifact atomically and deterministically; return its path.

    ``arrays`` maps names to array-likes (object arrays are refused).  Members are
    written in sorted name order with a fixed timestamp.
    """
    path = Path(path)
    meta = make_meta(kind, params=params, inputs=inputs, producer=producer, cache_key=cache_key,
                     extra=extra_meta)
    members: list[tuple[str, bytes]] = []
    for name in sorted(arrays):
        if name == META_KEY:
            raise ReflectmmError(f"array name {META_KEY!r} is reserved", path)
        arr = np.asarray(arrays[name])
        if arr.dtype.hasobject:
            raise ReflectmmError(f"array '{name}' has dtype object; artifacts hold numeric/string arrays only",
                                 path)
        members.append((name, _npy_bytes(arr)))
    members.append((META_KEY, _npy_bytes(np.array(canonical_json(meta)))))
    method = zipfile.ZIP_DEFLATED if compress else zipfile.ZIP_STORED
    refuse_newer_target(path)
    with atomic_path(path) as tmp:
        with zipfile.ZipFile(tmp, "w", compression=method, allowZip64=True) as zf:
            for name, data in members:
                info = zipfile.ZipInfo(name + ".npy", date_time=_ZIP_EPOCH)
                info.compress_type = method
                info.external_attr = 0o644 << 16
                info.create_system = 3
                zf.writestr(info, data, compress_type=method, compresslevel=6 if compress else None)
    return path


#: What a damaged NPZ (zip, deflate or .npy header) makes the zipfile and numpy readers raise: each is turned into
#: a one-line error naming the file.
CORRUPT_ERRORS = (zipfile.BadZipFile, zipfile.LargeZipFile, EOFError, OSError, ValueError, SyntaxError, zlib.error,
                  struct.error, UnicodeDecodeError, KeyError, NotImplementedError, OverflowError, MemoryError,
                  tokenize.TokenError)


def _open_npz(path: Path):
    if not path.exists():
        raise ArtifactError("file not found", path)
    if path.is_dir():
        raise ArtifactError("is a directory, expected an artifact file", path)
    if not zipfile.is_zipfile(path):
        with open(path, "rb") as f:
            head = f.read(4)
        if head.startswith(b"PK"):
            raise ArtifactError("truncated or corrupt NPZ (zip directory missing)", path)
        raise ArtifactError("not an NPZ artifact (not a zip archive)", path)
    try:
        return np.load(path, allow_pickle=False)
    except CORRUPT_ERRORS as exc:
        raise ArtifactError(f"truncated or corrupt NPZ ({type(exc).__name__}: {exc})", path) from None


def _npz_member(npz, name: str, path: Path) -> np.ndarray:
    """One array of an open NPZ.  A member whose .npy header is damaged comes back from numpy as raw bytes: that
    is a corrupt member, said in one line naming the file."""
    a = npz[name]
    if not isinstance(a, np.ndarray):
        raise ArtifactError(f"truncated or corrupt NPZ member '{name}' (not an .npy array)", path)
    return a


def _meta_from_npz(npz, path: Path) -> dict[str, Any]:
    if META_KEY not in npz.files:
        raise ArtifactError("not a reflectmm artifact (no __meta__ entry)", path)
    try:
        meta = json.loads(str(_npz_member(npz, META_KEY, path).reshape(-1)[0]))
    except CORRUPT_ERRORS as exc:
        raise ArtifactError(f"corrupt __meta__ entry ({exc})", path) from None
    if not isinstance(meta, dict):
        raise ArtifactError("corrupt __meta__ entry (not a JSON object)", path)
    return meta


#: The element of an HTML document (a viewer page) that holds its meta as JSON.
HTML_META_ID = "reflectmm-meta"


def html_meta_element(meta: Mapping[str, Any]) -> str:
    """``<script type="application/json" id="reflectmm-meta">…</script>`` for ``meta`` (``</`` escaped)."""
    return (f'<script type="application/json" id="{HTML_META_ID}">'
            + canonical_json(meta).replace("</", "<\\/") + "</script>")


def _meta_from_html(path: Path) -> dict[str, Any]:
    if not path.exists():
        raise ArtifactError("file not found", path)
    try:
        with open(path, "r", encoding="utf-8") as f:
            head = f.read(1 << 16)  # the meta element comes first in <head>
    except (OSError, UnicodeDecodeError) as exc:
        raise ArtifactError(f"cannot read HTML document ({exc})", path) from None
    start = head.find(f'id="{HTML_META_ID}">')
    end = head.find("</script>", start)
    if start < 0 or end < 0:
        raise ArtifactError("not a reflectmm document (no reflectmm-meta element)", path)
    try:
        meta = json.loads(head[start + len(HTML_META_ID) + 6:end].replace("<\\/", "</"))
    except ValueError as exc:
        raise ArtifactError(f"corrupt reflectmm-meta element ({exc})", path) from None
    if not isinstance(meta, dict):
        raise ArtifactError("corrupt reflectmm-meta element (not a JSON object)", path)
    return meta


def read_meta(path: str | Path) -> dict[str, Any]:
    """Read only the meta of an NPZ or EXR artifact or an HTML document (cheap; used by planners and
    ``inspect``)."""
    path = Path(path)
    if path.suffix.lower() == ".exr":
        return read_exr(path, meta_only=True)[1]
    if path.suffix.lower() in (".html", ".htm"):
        return _meta_from_html(path)
    with _open_npz(path) as npz:
        return _meta_from_npz(npz, path)


def read_artifact(path: str | Path, kind: str | None = None, members: Collection[str] | None = None) -> Artifact:
    """Read an NPZ (or EXR) artifact, refusing a wrong ``kind`` or a too-new schema.

    ``members``: read only these arrays of an NPZ (those it has; the others are not decompressed), e.g. a capture's
    landmarks without its image stack.  EXR files are always read whole."""
    path = Path(path)
    if path.suffix.lower() == ".exr":
        channels, meta = read_exr(path)
        found = check_schema(meta, kind, path)
        return Artifact(found, channels, meta, path)
    with _open_npz(path) as npz:
        meta = _meta_from_npz(npz, path)
        found = check_schema(meta, kind, path)
        arrays = {}
        wanted = None if members is None else set(members)
        try:
            for name in npz.files:
                if name != META_KEY and (wanted is None or name in wanted):
                    arrays[name] = _npz_member(npz, name, path)
        except CORRUPT_ERRORS as exc:
            raise ArtifactError(f"truncated or corrupt NPZ member ({type(exc).__name__}: "
                                f"{str(exc).splitlines()[0] if str(exc) else ''})", path) from None
    return Artifact(found, arrays, meta, path)


# --------------------------------------------------------------------------- images (OpenImageIO)

def _oiio():
    try:
        import OpenImageIO as oiio
    except ImportError as exc:  # pragma: no cover - dependency is mandatory
        raise ReflectmmError(f"OpenImageIO is required for EXR/HDR I/O: {exc}") from None
    return oiio


def write_exr(path: str | Path, channels: Mapping[str, np.ndarray], meta: Mapping[str, Any] | None = None,
              half: bool = False) -> Path:
    """Write named 2-D channels (each H×W) to an EXR atomically, with ``meta`` as a header attribute.

    Channel names follow the ``layer.channel`` convention (``albedo.R``, ``weight.p8``).
    """
    oiio = _oiio()
    path = Path(path)
    names = list(channels)
    if not names:
        raise ReflectmmError("no channels to write", path)
    planes = [np.asarray(channels[n], dtype=np.float32) for n in names]
    shape = planes[0].shape
    for n, p in zip(names, planes):
        if p.ndim != 2 or p.shape != shape:
            raise ReflectmmError(f"channel '{n}' has shape {p.shape}, expected 2-D {shape}", path)
    data = np.ascontiguousarray(np.stack(planes, axis=-1))
    h, w = shape
    spec = oiio.ImageSpec(w, h, len(names), "half" if half else "float")
    spec.channelnames = tuple(names)
    spec.attribute("compression", "zip")
    # OpenImageIO stamps the write time (capDate) unless a DateTime is given: fix it for byte-identical reruns
    spec.attribute("DateTime", "1980:01:01 00:00:00")
    if meta is not None:
        spec.attribute(EXR_META_ATTR, canonical_json(meta))
    refuse_newer_target(path)
    with atomic_path(path, suffix=".exr") as tmp:
        out = oiio.ImageOutput.create(str(tmp))
        if out is None:
            raise ReflectmmError(f"cannot create EXR writer: {oiio.geterror()}", path)
        if not out.open(str(tmp), spec):
            raise ReflectmmError(f"cannot open EXR for writing: {out.geterror()}", path)
        ok = out.write_image(data)
        closed = out.close()
        if not (ok and closed):
            _raise_exr_write_error(_oiio_error(out), tmp, path, data.nbytes)
    return path


def _raise_exr_write_error(msg: str, tmp: Path, target: Path, nbytes: int) -> None:
    """A failed OpenImageIO write of ``tmp`` (the temporary file of ``target``) as one line naming ``target``.

    OpenImageIO reports a full disk as text ("Failed to write pixel data ...") without the errno, so the folder's
    free space is looked at while the partial file still holds its share: less than the uncompressed pixels
    (an upper bound of what the write needed) is the documented ``no space left on the device [errno 28]``."""
    try:
        st = os.statvfs(tmp.parent)
        free = (st.f_bfree if os.geteuid() == 0 else st.f_bavail) * st.f_frsize
    except (OSError, AttributeError):  # pragma: no cover - no statvfs: report OpenImageIO's text
        free = None
    if free is not None and free < nbytes:
        _raise_write_error(OSError(errno.ENOSPC, os.strerror(errno.ENOSPC)), target)
    text = " ".join(_first_line(msg).replace(str(tmp), str(target)).split())
    raise ReflectmmError(f"cannot write EXR: {text}", target)


def _oiio_error(obj) -> str:
    """OpenImageIO's last error message; a message that is not UTF-8 (it may quote a damaged header) is not one."""
    try:
        return obj.geterror()
    except UnicodeDecodeError:
        return "error message not readable (damaged header text)"


def _first_line(msg: str) -> str:
    """OpenImageIO errors can span lines and repeat the path; keep one short line."""
    lines = [ln.strip() for ln in (msg or "").splitlines() if ln.strip()]
    return (lines[-1] if lines else "unknown error")[:300]


def read_exr(path: str | Path, meta_only: bool = False) -> tuple[dict[str, np.ndarray], dict[str, Any]]:
    """Read an EXR: (channels by name as float32 H×W, meta dict — empty if none)."""
    oiio = _oiio()
    path = Path(path)
    if not path.exists():
        raise ArtifactError("file not found", path)
    try:
        inp = oiio.ImageInput.open(str(path))
    except UnicodeDecodeError:  # a damaged header string reaches Python as bytes that are not text
        raise ArtifactError("unreadable or corrupt EXR (a header string is not text)", path) from None
    if inp is None:
        raise ArtifactError(f"unreadable or corrupt EXR ({_first_line(_oiio_error(oiio))})", path)
    try:
        spec = inp.spec()
        try:
            raw = spec.getattribute(EXR_META_ATTR)
        except UnicodeDecodeError:
            raise ArtifactError("corrupt reflectmm:meta header attribute (not text)", path) from None
        meta: dict[str, Any] = {}
        if raw is not None and not isinstance(raw, str):
            raise ArtifactError("corrupt reflectmm:meta header attribute (not text)", path)
        if raw:
            try:
                meta = json.loads(raw)
            except ValueError:
                raise ArtifactError("corrupt reflectmm:meta header attribute", path) from None
        if meta_only:
            return {}, meta
        pixels = inp.read_image(0, 0, 0, spec.nchannels, "float")
        if pixels is None or (hasattr(pixels, "size") and pixels.size == 0):
            raise ArtifactError(f"truncated or corrupt EXR pixel data ({_first_line(_oiio_error(inp))})", path)
        try:
            pixels = np.asarray(pixels, dtype=np.float32).reshape(spec.height, spec.width, spec.nchannels)
        except ValueError:
            raise ArtifactError("corrupt EXR (pixel data do not match the header's size)", path) from None
        channels = {name: pixels[..., i].copy() for i, name in enumerate(spec.channelnames)}
    finally:
        inp.close()
    return channels, meta


def read_image(path: str | Path) -> np.ndarray:
    """Read any image OpenImageIO understands (EXR, HDR, PNG, TIFF...) as float32 H×W×C.

    8/16-bit files come back in [0, 1] (values as stored: no linearisation).
    Raises ReflectmmError naming the file when it is missing or unreadable.
    """
    oiio = _oiio()
    path = Path(path)
    if not path.exists():
        raise ReflectmmError("file not found", path)
    try:
        inp = oiio.ImageInput.open(str(path))
    except UnicodeDecodeError:
        raise ReflectmmError("not a readable image (a header string is not text)", path) from None
    if inp is None:
        raise ReflectmmError(f"not a readable image ({_first_line(_oiio_error(oiio))})", path)
    try:
        spec = inp.spec()
        pixels = inp.read_image(0, 0, 0, spec.nchannels, "float")
        if pixels is None or (hasattr(pixels, "size") and pixels.size == 0):
            raise ReflectmmError(f"truncated or corrupt image ({_first_line(_oiio_error(inp))})", path)
    finally:
        inp.close()
    return np.asarray(pixels, dtype=np.float32).reshape(spec.height, spec.width, spec.nchannels)


#: File endings read as images by the in-the-wild verbs (``prepare-wild``, ``detect-landmarks``).
IMAGE_EXTENSIONS = (".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff", ".webp")


def read_image_u8(path: str | Path) -> np.ndarray:
    """Read a photograph / label image as RGB uint8 (H, W, 3) with OpenCV, values as stored (no linearisation).

    16-bit files are scaled to 8 bits, grey images repeated to 3 channels, alpha dropped.  Raises
    ReflectmmError naming the file when it is unreadable or not an image.
    """
    import cv2

    img = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if img is None:
        raise ReflectmmError("cannot read image (unreadable or not an image)", path)
    if img.dtype == np.uint16:
        img = (img // 257).astype(np.uint8)
    if img.ndim == 2:
        img = np.repeat(img[..., None], 3, -1)
    if img.shape[2] == 4:
        img = img[..., :3]
    return np.ascontiguousarray(img[..., ::-1])


def write_png(path: str | Path, image: np.ndarray) -> Path:
    """Write a display image (H×W or H×W×3/4, float in [0,1] or uint8) as an 8-bit PNG atomically."""
    import cv2

    path = Path(path)
    img = np.asarray(image)
    if img.dtype != np.uint8:
        img = np.clip(np.nan_to_num(img.astype(np.float32)) * 255.0 + 0.5, 0, 255).astype(np.uint8)
    if img.ndim == 3 and img.shape[2] == 3:
        img = img[..., ::-1]
    elif img.ndim == 3 and img.shape[2] == 4:
        img = img[..., [2, 1, 0, 3]]
    ok, buf = cv2.imencode(".png", np.ascontiguousarray(img))
    if not ok:
        raise ReflectmmError("cannot encode PNG", path)
    return atomic_write_bytes(path, buf.tobytes())
