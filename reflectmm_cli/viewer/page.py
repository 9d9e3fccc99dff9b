"""The viewer page: the bundle of :mod:`.bundle` and the page's own script and style in one HTML file.

The file is self-contained: it loads nothing (its Content-Security-Policy forbids every request) and works from
``file://``. The script (``static/viewer.js``) is the project's own WebGL2 code, with no library: the page needs
orbit, zoom and a light drag, which take a few dozen lines, and a library such as three.js would add about
600 kB and its own shading model beside the project's.
"""
from __future__ import annotations

import json
import re
from importlib import resources
from typing import Any, Mapping

__all__ = ["render_page", "read_bundle", "EXTERNAL_URL", "DATA_ID"]

#: The element that holds the bundle.
DATA_ID = "reflectmm-data"

#: What no page may contain: a URL that a browser could fetch.
EXTERNAL_URL = re.compile(r"(?:https?|wss?|ftp)://|//[a-z0-9.-]+\.[a-z]{2,}/", re.IGNORECASE)


def _static(name: str) -> str:
    return resources.files("reflectmm_cli.viewer").joinpath("static", name).read_text(encoding="utf-8")


def _escape_title(text: str) -> str:
    return text.replace("&", "&amp;").replace("<", "&lt;").replace(">", "&gt;")


def render_page(doc: Mapping[str, Any], meta: Mapping[str, Any] | None = None) -> str:
    """The HTML text of a page showing bundle ``doc``, with the artifact ``meta`` in its head (read back by
    :func:`reflectmm_cli.artifacts.read_meta`). ``</`` in the JSON is escaped, so no string in the bundle can close
    its script element."""
    from reflectmm_cli.artifacts import html_meta_element

    data = json.dumps(doc, separators=(",", ":"), allow_nan=False).replace("</", "<\\/")
    html = _static("viewer.html")
    parts = {"@META@": html_meta_element(meta) if meta is not None else "", "@TITLE@": _escape_title(str(doc.get("title") or "reflectmm model")), "@STYLE@": _static("viewer.css"),
             "@SCRIPT@": _static("viewer.js"), "@DATA@": data}
    # one pass, so that no inserted text is searched for the next placeholder
    return re.sub("|".join(re.escape(k) for k in parts), lambda m: parts[m.group(0)], html)


def read_bundle(path) -> dict[str, Any] | None:
    """The bundle of a page written by :func:`render_page` (None if the file has no bundle element); a one-line
    :class:`~reflectmm_cli.errors.ArtifactError` for a corrupt one."""
    from pathlib import Path

    from reflectmm_cli.errors import ArtifactError

    m = re.search(rf'<script type="application/json" id="{DATA_ID}">(.*?)</script>',
                  Path(path).read_text("utf-8"), re.S)
    if m is None:
        return None
    try:
        return json.loads(m.group(1))
    except ValueError as exc:
        raise ArtifactError(f"corrupt {DATA_ID} element ({exc})", path) from None
