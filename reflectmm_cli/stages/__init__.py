"""Stages: one module per verb's unit of work (options → read artifacts → library call → write artifacts).

* :mod:`.base` — :class:`Stage`, :class:`StageContext`, cache keys, :func:`check_no_overwrite`;
* :mod:`.registry` — the explicit verb → module list (:func:`get_stage`, :func:`all_stages`) and
  :func:`run_stage` (which looks a verb up; registry imports base, never the reverse);
* one module per stage (``fit_reflectance.py`` ...), each defining ``PARAMS`` and ``STAGE``.

Writing a stage: docs/architecture.md.
"""

from reflectmm_cli.stages.base import (CACHE_HASH_VERSION, NON_INVALIDATING, Input, Stage, StageContext, cache_key_doc,
                                       check_no_overwrite, compute_cache_key, expand_pattern_paths, file_digest,
                                       key_of_doc, resolve_device, run_committed, walk_files)
from reflectmm_cli.stages.registry import STAGE_MODULES, all_stages, get_stage, register_stage, run_stage
from reflectmm_cli.workspace import default_workspace

__all__ = ["CACHE_HASH_VERSION", "NON_INVALIDATING", "STAGE_MODULES", "Input", "Stage", "StageContext", "all_stages",
           "cache_key_doc", "check_no_overwrite", "compute_cache_key", "default_workspace", "expand_pattern_paths",
           "file_digest", "get_stage", "key_of_doc",
           "register_stage", "resolve_device", "run_committed", "run_stage", "walk_files"]
