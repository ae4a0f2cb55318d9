"""The process's memory policy: freed memory kept for the front end, handed back for the mapper."""

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
print(kept, rss_mb([os.getpid()]))
"""


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="glibc's malloc options (Linux)")
def test_memory_kept_for_the_front_end_is_handed_back_for_the_mapper():
    """With the front end's policy, 400 MB freed in blocks stays resident; once handed back, what is
    resident is what is still held (8 MB of the blocks, and the interpreter)."""
    out = subprocess.run([sys.executable, "-c", SCRIPT], capture_output=True, text=True, check=True).stdout
    kept, handed_back = map(float, out.split())
    assert kept > 400
    assert handed_back < kept - 350
