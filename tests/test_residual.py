"""torchfit.residual: the one-time warm-up of torch's derivative machinery."""
from __future__ import annotations

import subprocess
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]


def test_warm_up_pays_the_first_vector_jacobian_products_import():
    """The first ``autograd.grad`` given ``grad_outputs`` imports sympy (through
    ``symbolic_shapes``): about a second that the first backward of a fit paid inside the
    solver's clock (the "first backward" of issue 39) until the warm-up passed
    ``grad_outputs`` too. In a fresh process: loaded by the warm-up, not before."""
    code = ("import sys, torch\n"
            "from torchfit.residual import warm_up_autograd\n"
            "name = 'torch.fx.experimental.symbolic_shapes'\n"
            "before = name in sys.modules\n"
            "warm_up_autograd()\n"
            "print(before, name in sys.modules)\n")
    out = subprocess.run([sys.executable, "-c", code], cwd=REPO, capture_output=True,
                         text=True, timeout=120, env={"PYTHONPATH": str(REPO),
                                                      "PATH": "/usr/bin:/bin"})
    assert out.returncode == 0, out.stderr[-2000:]
    assert out.stdout.split() == ["False", "True"]
