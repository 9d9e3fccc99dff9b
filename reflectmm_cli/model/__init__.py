"""Statistical models: the reflectance morphable model (PCA of fitted maps with specular transfer, docs/design.md §1
step 5, :mod:`.pca`) and the light model (PCA of SH lighting, step 6, :mod:`.light`).

See docs/model.md. numpy in → numpy out; :func:`sample_model` also takes a torch β (differentiable).
"""
from .pca import (
    MODEL_KIND,
    ReflectanceModel,
    add_vertex_model,
    fit_reflectance_pca,
    model_arrays,
    model_from_arrays,
    model_to_torch,
    project_maps,
    sample_model,
    sample_uv_bilinear,
)
from .light import LightModel, build_light_model, light_from_coeffs

__all__ = [
    "LightModel",
    "build_light_model",
    "light_from_coeffs",
    "MODEL_KIND",
    "ReflectanceModel",
    "add_vertex_model",
    "fit_reflectance_pca",
    "model_arrays",
    "model_from_arrays",
    "model_to_torch",
    "project_maps",
    "sample_model",
    "sample_uv_bilinear",
]
