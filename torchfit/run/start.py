"""Where a fit starts: the problem's initial guess, a given ``theta``, or an earlier run's.

``init=`` of a run names an earlier run (its directory or its ``params.pt``): a start, not a
resume; only that file is read. :func:`digest` is how a checkpoint remembers the start.
"""
from __future__ import annotations

import hashlib
from pathlib import Path

import torch
from torch import Tensor

from ..problems import InverseProblem, parameter_meaning
from ..reporting import PARAMS_FILE
from .options import FitConfigError


def initial_theta(problem: InverseProblem, init: Tensor | str | Path | None = None) -> Tensor:
    """Where the fit starts: ``problem.theta0`` (``init=None``), a given ``theta``, or the
    ``theta`` of an earlier run (its directory or its ``params.pt``).

    An earlier run is a start, not a resume: any problem and solver settings may differ
    (other frames, another mesh of the same body, another solver) as long as the
    parameterisation is the same: ``(n_params,)`` and, where ``params.pt`` records them, the
    field's name and transform. Raises :class:`FitConfigError` naming the file and what
    differs; nothing is read but that file.
    """
    if init is None:
        return problem.theta0.detach().clone()
    n = problem.parameterization.n_params
    where = "init"
    if isinstance(init, Tensor):
        theta = init.detach()
    else:
        path = Path(init).expanduser()
        if path.is_dir():
            path = path / PARAMS_FILE
        where = f"init={path}"
        if not path.is_file():
            raise FitConfigError(f"{where}: no such file; give the directory of a finished run "
                                 f"(it holds {PARAMS_FILE}) or the {PARAMS_FILE} itself")
        saved = read_params(path, where)
        theta = saved["theta"]
        name = problem.parameterization.name
        for key, ours in (("field_name", problem.field_name),
                          ("transform", problem.parameterization.transform)):
            if key in saved and saved[key] != ours:
                raise FitConfigError(f"{where} holds a {name} with {key} {saved[key]!r}, but "
                                     f"{problem.name}'s is {ours!r}; start from a run of the "
                                     "same parameterisation")
        meaning = saved.get("meaning")
        if isinstance(meaning, dict):       # params.pt of 2026-11-26 on
            for key, ours in parameter_meaning(problem).items():
                if key in meaning and meaning[key] != ours:
                    raise FitConfigError(
                        f"{where} holds the parameters of another problem ({key} "
                        f"{meaning[key]!r} there, {ours!r} here), though their count may "
                        f"agree; start from a run of {problem.name} with the same parameters")
    if theta.shape != (n,):
        raise FitConfigError(f"{where} has {tuple(theta.shape)} parameters, but {problem.name}'s "
                             f"parameterisation has ({n},); start from a run with the same "
                             "parameters (problem.parameters, problem.grid)")
    if not bool(torch.isfinite(theta).all()):
        bad = int(torch.nonzero(~torch.isfinite(theta))[0, 0])
        raise FitConfigError(f"{where}: parameter {bad} is {float(theta[bad])}; a start must "
                             "be finite")
    return theta.to(dtype=problem.theta0.dtype, device=problem.theta0.device).clone()


def read_params(path: Path, where: str) -> dict:
    """The content of a ``params.pt`` (``theta`` a tensor checked); :class:`FitConfigError`
    naming ``where`` for a truncated, foreign or corrupt file."""
    try:
        with open(path, "rb") as f:
            saved = torch.load(f, map_location="cpu", weights_only=True)
        if not isinstance(saved["theta"], Tensor):
            raise TypeError("its theta is not a tensor")
    except Exception as e:  # noqa: BLE001  (truncated, foreign or corrupt file)
        first = (str(e).strip().splitlines() or [type(e).__name__])[0][:120]
        raise FitConfigError(f"{where} is not a torchfit {PARAMS_FILE} ({first}); give the "
                             "directory of a finished run") from None
    return saved


def digest(theta: Tensor) -> str:
    """A short hash of ``theta``'s bytes (a checkpoint remembers where its run started)."""
    data = theta.detach().cpu().to(torch.float64).contiguous().numpy().tobytes()
    return hashlib.sha256(data).hexdigest()[:16]
