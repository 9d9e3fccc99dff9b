"""CLI verbs: click wrappers over the stages of :mod:`reflectmm_cli.stages` (and a few verbs that are not stages:
``run``, ``inspect``, ``face-model export/info``).  Each module exposes its click commands in ``COMMANDS``;
:mod:`reflectmm_cli.cli` lists the modules explicitly.  Nothing else imports these modules."""
