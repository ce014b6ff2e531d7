"""artrack/realtime.py: glibc keeps freed memory (the particle filter's steady frame cost)."""

import ctypes.util
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest

SRC = Path(__file__).resolve().parents[1] / "src" / "artrack_nodes"


@pytest.mark.skipif(not (sys.platform.startswith("linux") and ctypes.util.find_library("c")), reason="glibc only")
def test_repeated_large_arrays_stop_costing_fresh_pages():
    """A frame of the particle filter holds several ~13 MB temporaries at once. After
    keep_freed_memory, 20 such rounds take no new page faults after the first; without it glibc
    returns the freed top of the heap to the system and every round faults the pages in again."""
    code = textwrap.dedent(f"""
        import resource, sys
        sys.path.insert(0, {str(SRC)!r})
        import numpy as np
        from artrack.realtime import keep_freed_memory
        if sys.argv[1] == "keep":
            assert keep_freed_memory()
        def frame():
            arrays = [np.ones(1_600_000) for _ in range(4)]    # 4 x 12.8 MB alive together
            return sum(float(a.sum()) for a in arrays)
        frame()
        before = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
        for _ in range(20):
            frame()
        print(resource.getrusage(resource.RUSAGE_SELF).ru_minflt - before)
    """)
    faults = {mode: int(subprocess.run([sys.executable, "-c", code, mode], capture_output=True, text=True,
                                       check=True).stdout.split()[-1]) for mode in ("keep", "default")}
    pages = 12_800_000 // 4096
    assert faults["keep"] < pages // 10, faults
    assert faults["default"] > 5 * pages, faults
