"""CLI verbs.  Each module exposes its click commands in a list ``COMMANDS``; the CLI
and the recipe runner discover them automatically (modules starting with ``_`` are helpers)."""
