"""The solution cache: solutions with their factors, found again, and the warm-start choice.

A :class:`Solution` keeps ``x*`` ``(F, n_dofs)``, the factors of the exact tangent there,
Newton's iteration counts, the cold start's residual norms and (built lazily) the model's
parameter derivative. :meth:`SolutionCache.lookup` finds a solution again by its parameters
and Dirichlet values while it is among the ``size`` most recently used ones *or* while an
autograd graph (or a linearisation) that used it is alive, so evaluating other points in
between never forces a refactorisation.

Warm start (:meth:`SolutionCache.warm_source`): a new point with the same Dirichlet values
starts from the solution derivatives were last taken at (the *anchor*, a solver's
linearisation point) while it is alive, else from the most recently used solution that may
seed (the *seed*). A solution from :meth:`SolutionCache.independent` (a simulation beside
the solver's sequence: a synthetic target, a report's homogeneous baseline) starts cold and
is never a seed, nor does it displace one: when such a simulation happens (at the first
iteration, or first after a resume) does not change where the next solve starts.

What a warm start reads is the cache's *seed state* (:meth:`SolutionCache.seed_solutions`:
the anchor and the seed, with which is the anchor); a run's
checkpoint keeps it (:meth:`~.equilibrium.Equilibrium.warm_start_state`) so that a resumed
process's next solve starts where the uninterrupted one's did.
"""
from __future__ import annotations

import contextlib
import dataclasses
import weakref
from typing import Any, Iterator

import torch
from torch import Tensor

from ...linalg import Factor


@dataclasses.dataclass(eq=False)  # identity semantics: kept in a WeakSet
class Solution:
    """One equilibrium: parameters, Dirichlet values, positions and what derivatives need."""

    params: Tensor
    fixed_values: Tensor
    x: Tensor                  # (F, n_dofs), full positions
    factors: list[Factor]      # one shared factor (linear model) or one per frame
    newton_iterations: list[int]
    reference: Tensor | None = None        # (F,) residual norms of the cold start
    param_derivative: Any = None           # model.param_derivative at x*, built lazily
    warm_started: bool = False
    seeds: bool = True         # may warm-start another point (False: an independent() solve)


class SolutionCache:
    """Recently used and still referenced solutions, the anchor, and the warm-start rule.

    Args:
        size: number of solutions kept by recency; 2 lets a Levenberg-Marquardt trial
            point be evaluated without dropping the current point's factorisation.
        warm_start: whether :meth:`warm_source` offers an earlier solution at all.
    """

    def __init__(self, size: int = 2, warm_start: bool = True) -> None:
        self.size = size
        self.warm_start = bool(warm_start)
        self._entries: list[Solution] = []
        # Solutions still referenced by a live autograd graph (ctx.solution).
        self._alive: weakref.WeakSet[Solution] = weakref.WeakSet()
        # The solution derivatives were last taken at (the first choice of a warm start).
        self._anchor: weakref.ref[Solution] | None = None
        # The most recently used solution that may seed (held: an independent solve after
        # it must not make the next warm start depend on the recency list's length).
        self._seed: Solution | None = None
        self._independent = False     # inside independent(): cold starts, no seeds

    @property
    def is_independent(self) -> bool:
        """Whether an :meth:`independent` block is open."""
        return self._independent

    def lookup(self, params: Tensor, fixed_values: Tensor) -> Solution | None:
        """The solution at exactly these parameters and Dirichlet values (promoted to most
        recently used), or ``None``."""
        def same(sol: Solution) -> bool:
            return (sol.params.shape == params.shape and sol.fixed_values.shape == fixed_values.shape
                    and torch.equal(sol.params, params) and torch.equal(sol.fixed_values, fixed_values))

        for i, sol in enumerate(self._entries):
            if same(sol):
                self._entries.append(self._entries.pop(i))  # most recently used last
                self._note_seed(sol)
                return sol
        for sol in list(self._alive):
            if same(sol):
                self.remember(sol)
                return sol
        return None

    def remember(self, sol: Solution) -> None:
        """Keep ``sol`` as the most recently used solution (dropping the oldest)."""
        self._entries.append(sol)
        self._alive.add(sol)
        self._note_seed(sol)
        while len(self._entries) > self.size:
            self._entries.pop(0)

    def _note_seed(self, sol: Solution) -> None:
        """A use of ``sol`` outside :meth:`independent` makes it the seed (a point a solver
        asks for again is the solver's, even if an independent simulation found it first);
        a use inside changes nothing."""
        if not self._independent:
            sol.seeds = True
            self._seed = sol

    def contains(self, solution: Solution) -> bool:
        """Whether this very solution is among the recently used ones."""
        return any(sol is solution for sol in self._entries)

    def restore(self, solution: Solution) -> None:
        """Put a solution found earlier back (with its factors and parameter derivative)."""
        if not self.contains(solution):
            self.remember(solution)

    def adopt(self, params: Tensor, fixed_values: Tensor, x: Tensor,
              factors: list[Factor]) -> Solution:
        """Register a known solution ``x`` (full, Dirichlet values in place) of ``(params,
        fixed_values)`` with its factors: no Newton iteration was run for it."""
        sol = Solution(params.clone(), fixed_values.clone(), x, list(factors),
                       [0] * x.shape[0])
        self.remember(sol)
        return sol

    def anchor(self, solution: Solution) -> None:
        """Derivatives are taken at ``solution``: the first choice of a warm start while it
        is alive."""
        self._anchor = weakref.ref(solution)

    def is_anchor(self, solution: Solution | None) -> bool:
        """Whether ``solution`` is the (live) anchor."""
        return solution is not None and self._anchor is not None and self._anchor() is solution

    def seed_solutions(self) -> tuple[list[Solution], int]:
        """What :meth:`warm_source` reads: the anchor (while alive) and the seed (once each,
        the anchor first), and the anchor's index (``-1``: none)."""
        anchor = self._anchor() if self._anchor is not None else None
        chosen = [] if anchor is None else [anchor]
        if self._seed is not None and self._seed is not anchor:
            chosen.append(self._seed)
        return chosen, 0 if anchor is not None else -1

    def restore_seed_state(self, solutions: list[Solution], anchor: int) -> None:
        """Put back what :meth:`seed_solutions` returned in another process: ``solutions``
        (rebuilt, their ``seeds`` flags as saved) become the most recently used, the one at
        index ``anchor`` (``-1``: none) the anchor, the last that seeds the seed."""
        for sol in solutions:
            if not self.contains(sol):
                self._entries.append(sol)
                self._alive.add(sol)
        while len(self._entries) > self.size:
            self._entries.pop(0)
        seeds = [sol for sol in solutions if sol.seeds]
        if seeds:
            self._seed = seeds[-1]
        if anchor >= 0:
            self.anchor(solutions[anchor])

    def clear(self) -> None:
        self._entries.clear()
        self._alive = weakref.WeakSet()
        self._anchor = None
        self._seed = None

    def warm_source(self, fixed_values: Tensor) -> Solution | None:
        """The solution derivatives were last taken at, else the seed (the most recently
        used solution not from :meth:`independent`), if it has the same Dirichlet values;
        ``None`` inside :meth:`independent` or without warm starts."""
        if not self.warm_start or self._independent:
            return None
        anchor = self._anchor() if self._anchor is not None else None
        for sol in ([anchor] if anchor is not None else []) + \
                ([self._seed] if self._seed is not None else []):
            if sol.fixed_values.shape == fixed_values.shape and sol.reference is not None \
                    and torch.equal(sol.fixed_values, fixed_values):
                return sol
        return None

    @contextlib.contextmanager
    def independent(self) -> Iterator[None]:
        """Within: :meth:`warm_source` offers nothing, and the caller marks new solutions as
        no seed (``Solution.seeds = False``)."""
        before = self._independent
        self._independent = True
        try:
            yield
        finally:
            self._independent = before
