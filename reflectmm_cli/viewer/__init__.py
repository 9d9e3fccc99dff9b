"""Interactive viewer of reflectance models: one self-contained HTML page (docs/viewer.md).

:mod:`.bundle` gathers the data (mesh, per-vertex models, lighting, the shading constants of
:mod:`reflectmm_cli.shading`); :mod:`.page` writes it into the page with the project's WebGL2 script.
"""
from .bundle import (
    ENCODINGS,
    FORMAT,
    MAX_LOBES,
    LightData,
    ModelData,
    ViewerOptions,
    build_bundle,
    bundle_size,
    decode_blob,
    envmap_data,
    iter_blobs,
    light_model_data,
    model_data,
)
from .page import DATA_ID, EXTERNAL_URL, read_bundle, render_page

__all__ = ["ENCODINGS", "FORMAT", "MAX_LOBES", "LightData", "ModelData", "ViewerOptions", "build_bundle",
           "bundle_size", "decode_blob", "envmap_data", "iter_blobs", "read_bundle", "DATA_ID", "light_model_data", "model_data", "render_page",
           "EXTERNAL_URL"]
