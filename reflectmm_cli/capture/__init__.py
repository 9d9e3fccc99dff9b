"""Reading Multi-PIE-layout captures into linear OLAT stacks (``preprocess-multipie``)."""

from reflectmm_cli.capture.images import read_image
from reflectmm_cli.capture.layout import (DEFAULT_FLASHES, DEFAULT_VIEWS, camera_code, camera_name,
                                          discover_identities, plan_identity, resolve_session, sessions_of)
from reflectmm_cli.capture.preprocess import CaptureOptions, MissingShotsError, parse_rotate, preprocess_identity
from reflectmm_cli.capture.transfer import Transfer, parse_transfer

__all__ = ["DEFAULT_FLASHES", "DEFAULT_VIEWS", "CaptureOptions", "MissingShotsError", "Transfer", "camera_code",
           "camera_name", "discover_identities", "parse_rotate", "parse_transfer", "plan_identity",
           "preprocess_identity", "read_image", "resolve_session", "sessions_of"]
