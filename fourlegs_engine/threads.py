"""Scoped torch thread counts."""
from __future__ import annotations

from contextlib import contextmanager
from typing import Iterator, Optional

import torch


@contextmanager
def torch_threads(count: Optional[int]) -> Iterator[None]:
    """Run the block with ``count`` torch intra-op threads (None or < 1: leave torch's setting), then
    restore the previous setting."""
    before = torch.get_num_threads()
    if count is not None and count >= 1:
        torch.set_num_threads(int(count))
    try:
        yield
    finally:
        torch.set_num_threads(before)
