"""coreg_ros.allocator: the memory settings of a command that holds a long recording."""

import subprocess
import sys

import pytest

SCRIPT = """
from coreg_ros.allocator import keep_memory_for_reuse
from numpy._core import multiarray
import numpy as np
print(keep_memory_for_reuse(), keep_memory_for_reuse())
print(multiarray._set_madvise_hugepage(True))  # returns the setting it replaces
x = np.ones((1 << 24,)); del x  # served from the heap now, and kept
y = np.ones((1 << 24,))
print(float(y.sum()))
"""


@pytest.mark.skipif(not sys.platform.startswith('linux'), reason='glibc mallopt: Linux only')
def test_memory_settings_are_taken_once_and_arrays_still_work():
    out = subprocess.run([sys.executable, '-c', SCRIPT], capture_output=True, text=True,
                         check=True).stdout.split()
    assert out[:2] == ['True', 'True']   # glibc took every setting; a second call is a no-op
    assert out[2] == 'False'             # NumPy's huge page advice was off
    assert float(out[3]) == float(1 << 24)
