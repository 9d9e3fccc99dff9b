"""Run every benchmark in this folder in turn and print their markdown tables (see docs/benchmarks.md).

Usage: python benchmarks/run_all.py [NAME ...]   (e.g. `shading recipe`; default: all)
Each benchmark is a separate script with its own options; this only runs them with their defaults.
"""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

HERE = Path(__file__).resolve().parent


def main() -> int:
    wanted = set(sys.argv[1:])
    failed = []
    for script in sorted(HERE.glob("bench_*.py")):
        name = script.stem[len("bench_"):]
        if wanted and name not in wanted:
            continue
        print(f"\n## {name}\n", flush=True)
        if subprocess.run([sys.executable, str(script)]).returncode != 0:
            failed.append(name)
    if failed:
        print(f"failed: {', '.join(failed)}", file=sys.stderr)
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())
