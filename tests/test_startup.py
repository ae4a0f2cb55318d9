"""The process's memory policy: freed memory kept for the next allocation, its free pages handed back after
each of the mapper's global bundle adjustments."""

import subprocess
import sys

import pytest

SCRIPT = """
import numpy as np
from mvrecon.memory import rss_mb
from mvrecon.startup import hand_back_freed_memory, keep_freed_memory
import os
keep_freed_memory()
blocks = [np.ones(50_000) for _ in range(1000)]  # 400 kB each, 400 MB
keep = blocks[::50]
del blocks
kept = rss_mb([os.getpid()])
hand_back_freed_memory()
handed_back = rss_mb([os.getpid()])
blocks = [np.ones(3_200_000) for _ in range(16)]  # 25.6 MB each, larger than any free run of the heap
del blocks
print(kept, handed_back, rss_mb([os.getpid()]))
"""


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="glibc's malloc options (Linux)")
def test_freed_memory_is_kept_until_handed_back_and_kept_again_after():
    """400 MB freed in blocks stays resident; once handed back, what is resident is what is still held (8 MB of
    the blocks, and the interpreter); 400 MB allocated after that in blocks larger than any free run of the heap
    (as a bundle adjustment's linear system), and freed, stays resident again, ready for the next one instead of
    faulted in anew."""
    out = subprocess.run([sys.executable, "-c", SCRIPT], capture_output=True, text=True, check=True).stdout
    kept, handed_back, kept_again = map(float, out.split())
    assert kept > 400
    assert handed_back < kept - 350
    assert kept_again > handed_back + 350
