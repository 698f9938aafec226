"""TensorBoard tags of a run's values and the HParams values of its settings.

``fit/<key>``: what is minimised (``misfit``, ``objective``, ``tv``, ``penalty``);
``metrics/<key>``: the metrics of docs/problems.md and any ``*_err*`` key, and the fitted
damping of a dynamic problem; ``solver/<key>``: everything else a record carries
(``step_norm``, ``cg_iterations``, ``damping``, ``accepted``, counters, ``wall_time`` and
solver-specific extras); a key with a ``/`` is its own tag; ``final/<key>``: per-run values
of the HParams session (``iterations``, ``wall_s``).
"""
from __future__ import annotations

from typing import Any, Mapping

FIT_KEYS = ("misfit", "objective", "tv", "penalty")
#: Keys of docs/problems.md's metric table (``misfit`` is also the solver's own value).
METRIC_KEYS = ("u_err_inf", "u_err_2", "k_err_inf", "k_err_2", "k_err_rel",
               "k_err_rel_aligned", "misfit")
#: fitted scalars reported as metrics (dynamic problems: the Rayleigh damping coefficients)
PARAMETER_KEYS = ("alpha_damping", "beta_damping")


def tag_for(key: str) -> str:
    """TensorBoard tag of a record scalar (see the module docstring)."""
    if "/" in key:
        return key
    if key in FIT_KEYS:
        return f"fit/{key}"
    if key in METRIC_KEYS or "_err" in key or key in PARAMETER_KEYS:
        return f"metrics/{key}"
    return f"solver/{key}"


def flatten(config: Mapping[str, Any], prefix: str = "") -> dict[str, Any]:
    """``{'solver': {'tau': 1.5}} -> {'solver.tau': 1.5}`` (lists stay whole)."""
    out: dict[str, Any] = {}
    for key, value in config.items():
        name = f"{prefix}{key}"
        if isinstance(value, Mapping):
            out.update(flatten(value, f"{name}."))
        else:
            out[name] = value
    return out


def metric_tag(key: str) -> str:
    """Tag of a final metric of the HParams session: the per-iteration tag of a record key
    (``misfit`` -> ``fit/misfit``, ``k_err_rel`` -> ``metrics/k_err_rel``), else
    ``final/<key>`` (``iterations``, ``wall_s``: one value per run)."""
    if "/" in key or key in FIT_KEYS or key in METRIC_KEYS or key in PARAMETER_KEYS:
        return tag_for(key)
    return f"final/{key}"


def hparam_values(hparams: Mapping[str, Any]) -> dict[str, bool | int | float | str]:
    """Flattened settings as HParams values: bools, numbers and strings as they are,
    other values (lists) as their text; ``None`` ("automatic", e.g. Split Bregman's
    ``mu``) is left out, so that a sweep mixing ``None`` and numbers keeps a numeric
    column (blank where automatic)."""
    out: dict[str, bool | int | float | str] = {}
    for key, value in flatten(hparams).items():
        if value is None:
            continue
        out[key] = value if isinstance(value, (bool, int, float, str)) else str(value)
    return out
