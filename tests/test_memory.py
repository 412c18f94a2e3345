"""fitme_cli.ops.memory: the process-wide allocator policy the fitme commands set."""

from __future__ import annotations

import sys

import numpy as np
import pytest

from fitme_cli.ops.memory import retain_freed_memory


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="glibc mallopt")
def test_retain_freed_memory_applies_and_is_idempotent():
    assert retain_freed_memory() is True
    assert retain_freed_memory() is True
    # allocations still behave: a large zeroed block is zero after freed blocks were reused
    for _ in range(3):
        junk = np.full(2_000_000, 7.0)
        del junk
        assert not np.zeros(2_000_000).any()
