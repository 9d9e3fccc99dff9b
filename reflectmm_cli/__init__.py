"""reflectmm: a 3D morphable face reflectance model toolkit.

The command-line verbs (``reflectmm <verb>``) are thin wrappers around the library
functions in this package; see ``reflectmm_cli.cli``.
"""

__version__ = "0.1.0"
