"""reflectmm: a 3D morphable face reflectance model toolkit.

The command-line verbs (``reflectmm <verb>``) are thin wrappers around the library
functions in this package; see ``reflectmm_cli.cli``.
"""

__version__ = "0.1.0"

import os as _os

# PyTorch's CPU allocator backs buffers of ≥ 2 MiB with transparent huge pages when THP_MEM_ALLOC_ENABLE is set
# (PyTorch ≥ 2.2; read once, at the first large allocation, so it is set here, before any torch work). Finetuning
# allocates the model's ~34 MB gradients and temporaries every step; with 4 KiB pages their first-touch page faults
# cost more than the arithmetic (docs/benchmarks.md, "Finetuning"). Performance only; an explicit setting wins.
_os.environ.setdefault("THP_MEM_ALLOC_ENABLE", "1")
