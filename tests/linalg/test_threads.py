"""torchfit.linalg.threads: ``set_threads`` limits torch and keeps MKL's dynamic threading on.

In a fresh process each (thread pools are process-wide)."""
from __future__ import annotations

import subprocess
import sys

import pytest

PROBE = """
import ctypes, os, sys, torch
from torchfit.linalg import set_threads
library = ctypes.CDLL(os.path.join(os.path.dirname(torch.__file__), "lib", "libtorch_cpu.so"))
dynamic = library.mkl_serv_get_dynamic
dynamic.restype = ctypes.c_int
if sys.argv[1] == "torch":
    torch.set_num_threads(2)
else:
    set_threads(2)
torch.sqrt(torch.rand(100_000, dtype=torch.float64))     # work after the setting
print(torch.get_num_threads(), dynamic())
"""


def _probe(how: str) -> tuple[int, int]:
    out = subprocess.run([sys.executable, "-c", PROBE, how], capture_output=True, text=True,
                         check=True)
    threads, dynamic = out.stdout.split()
    return int(threads), int(dynamic)


def test_set_threads_keeps_mkl_dynamic_where_torch_alone_turns_it_off():
    """``torch.set_num_threads`` switches MKL's dynamic threading off (every tiny VML call
    then runs on all threads: ms instead of us on a loaded machine); ``set_threads`` sets
    the same thread count and switches it back on."""
    try:
        torch_alone = _probe("torch")
    except (subprocess.CalledProcessError, AttributeError, ValueError):
        pytest.skip("this torch build exports no MKL service functions")
    assert torch_alone == (2, 0)
    assert _probe("torchfit") == (2, 1)
