"""Split Bregman for total variation: ``min |D theta|_1 + mu/2 ||r(theta)||^2``.

The solver (:mod:`.solver`) alternates an inner least-squares solve, a shrinkage of ``d``
and a Bregman update of ``b``; its settings (:mod:`.settings`), the TV weights
(:mod:`.weights`) and the stages of a continuation in ``mu`` (:mod:`.stages`).
"""
from .settings import SplitBregmanConfig
from .solver import SplitBregman, split_bregman

__all__ = ["SplitBregman", "SplitBregmanConfig", "split_bregman"]
