"""Scoped thread limits for torch work on small problems or shared CPUs."""

from __future__ import annotations

from contextlib import contextmanager
from typing import Iterator


@contextmanager
def torch_threads(n: int | None) -> Iterator[None]:
    """Run the block with ``torch.set_num_threads(n)`` and restore the previous count after.

    ``n`` None or ≤ 0 leaves the thread count as it is.  Small problems lose more to thread
    start-up and contention than they gain, so callers pass 1 for them.
    """
    import torch

    prev = torch.get_num_threads()
    if n is not None and n > 0:
        torch.set_num_threads(n)
    try:
        yield
    finally:
        torch.set_num_threads(prev)
