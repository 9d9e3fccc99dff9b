"""Reflectance morphable model: PCA of fitted maps with specular transfer (DESIGN.md §1 step 5).

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

__all__ = [
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
