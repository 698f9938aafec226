"""Problem settings: the choices, :class:`ProblemConfig` and the checks every problem shares.

* :class:`ProblemConfig` holds the settings every problem has (``name``, ``noise``,
  ``seed``, ``transform``, ``backend``, ``device``, ``dtype``); a problem's config
  dataclass extends it. Choice settings are :class:`~torchfit.settings.Choice` enums
  (``str`` subclasses, so ``cfg.data == "dense"`` holds), which lets OmegaConf reject a bad
  value when Hydra composes the config; plain strings are converted on construction.
* :func:`validate_config` checks what is generic (every numeric setting finite, the
  types of the numbers, ``noise >= 0``, the device exists here, a direct solver only on
  the CPU); every error is one line of :class:`ProblemConfigError` naming the setting as
  ``problem.<field>=<value>`` and what is allowed (:func:`setting_error`,
  :func:`require_setting` for a problem's own checks).
* :func:`make_config`: a config from ``None``, an instance or a mapping, overrides applied.
"""
from __future__ import annotations

import dataclasses
import re
from collections.abc import Mapping
from typing import Any

import torch

from .. import settings
from ..errors import ConfigurationError
from ..linalg import amg_available, cudss_available, pardiso_available
from ..linalg.backends import AMG_EXTRA, CUDA_EXTRA, PARDISO_EXTRA
from ..settings import Choice, check_values, convert_choices, make_settings


class ProblemConfigError(ConfigurationError):
    """A problem setting is invalid; the message (one line) names the setting and what to do."""

    def __init__(self, message: str) -> None:
        super().__init__(" ".join(str(message).split()))


def require(condition: bool, message: str) -> None:
    if not condition:
        raise ProblemConfigError(message)


# -- choices ---------------------------------------------------------------------------
class DataMode(Choice):
    """Which part of the state is observed."""

    dense = "dense"
    sparse = "sparse"


class Transform(Choice):
    """``field = exp(theta)`` (positivity) or ``field = theta``."""

    exp = "exp"
    identity = "identity"


class Backend(Choice):
    """Linear-solve backend: ``scipy`` (CPU direct, SuperLU), ``ldl`` (CPU sparse
    ``L D L^T`` with the analysis reused, SPD; SuperLU otherwise), ``banded`` (CPU banded
    Cholesky), ``pardiso`` (CPU, MKL PARDISO, the optional extra ``torchfit[pardiso]``),
    ``amg`` (CPU, CG preconditioned by pyamg's smoothed-aggregation AMG, SPD, the optional
    extra ``torchfit[amg]``; direct fallback otherwise), ``cudss`` (CUDA sparse direct,
    the optional extra ``torchfit[cuda]``), ``cg`` (torch Jacobi-CG, any device); ``auto``
    lets the problem choose (3-D: pardiso where installed, else scipy, and amg above
    ``AMG_MIN_DOFS`` free dofs for a use with few solves per factorisation; on CUDA cudss
    where installed, else cg)."""

    scipy = "scipy"
    ldl = "ldl"
    banded = "banded"
    pardiso = "pardiso"
    amg = "amg"
    cudss = "cudss"
    cg = "cg"
    auto = "auto"


class DType(Choice):
    """Floating-point precision of the problem's tensors."""

    float64 = "float64"
    float32 = "float32"


#: Backends that factorise on the CPU (a problem on another device needs ``cg``).
_CPU_BACKENDS = (Backend.scipy, Backend.ldl, Backend.banded, Backend.pardiso, Backend.amg)
#: Device names understood by :func:`resolve_device` (``cuda:N`` picks a GPU).
_DEVICE_CHOICES = ("cpu", "cuda", "cuda:N", "mps")
_DEVICE = re.compile(r"^(cpu|cuda|mps)(?::(\d+))?$")


@dataclasses.dataclass
class ProblemConfig:
    """Settings every problem has (a problem's config dataclass extends this one).

    ``name`` is the config name; ``noise`` the standard deviation of the i.i.d. Gaussian
    noise added to every observed value (seeded by ``seed``); ``transform`` maps
    ``theta`` to the field; ``backend`` does the linear solves; ``device`` and ``dtype``
    place and type every tensor of the problem.
    """

    name: str = "problem"
    noise: float = 0.0                  # sigma of the Gaussian noise on every observed value
    seed: int = 0                       # of the noise
    transform: Transform = Transform.exp    # exp (field = exp(theta)) | identity
    backend: Backend = Backend.scipy    # linear solves: scipy (CPU direct) | ldl | banded |
                                        # pardiso | amg | cudss | cg (torch) | auto
                                        # (see Backend)
    device: str = "cpu"                 # cpu | cuda | cuda:N | mps
    dtype: DType = DType.float64        # float64 | float32 (every tensor of the problem)

    def __post_init__(self) -> None:
        convert_choices(self, "problem", ProblemConfigError)


def setting_error(key: str, value: Any, allowed: str) -> ProblemConfigError:
    """``problem.<key>=<value>: <allowed>`` as a :class:`ProblemConfigError`."""
    return settings.setting_error(ProblemConfigError, f"problem.{key}", value, allowed)


def require_setting(condition: bool, cfg: Any, key: str, allowed: str) -> None:
    """Raise :func:`setting_error` for ``cfg.<key>`` unless ``condition``."""
    if not condition:
        raise setting_error(key, getattr(cfg, key), allowed)


# -- generic validation ---------------------------------------------------------------
def check_newton_settings(cfg: Any) -> None:
    """``0 <= newton_rtol < 1``, ``newton_atol > 0``, ``newton_max_iter >= 1`` (elastic
    problems)."""
    require_setting(0 <= cfg.newton_rtol < 1, cfg, "newton_rtol", "must be in [0, 1): the "
                    "fraction of the starting residual Newton reduces it to (1e-10); at 1 or "
                    "more Newton takes no step and the predictor passes as the equilibrium")
    require_setting(cfg.newton_atol > 0, cfg, "newton_atol", "must be > 0")
    require_setting(cfg.newton_max_iter >= 1, cfg, "newton_max_iter", "must be >= 1")


def check_device(key: str, value: Any) -> torch.device:
    """The torch device named by a ``device`` setting, if it exists on this machine."""
    name = str(value).strip().lower()
    match = _DEVICE.match(name)
    if match is None:
        raise setting_error(key, value, "is not a device; choose one of "
                            f"{', '.join(_DEVICE_CHOICES)} (N = GPU index)")
    kind, index = match.group(1), match.group(2)
    if kind == "cuda":
        if not torch.cuda.is_available():
            built = "without CUDA" if torch.version.cuda is None else \
                f"with CUDA {torch.version.cuda} but sees no GPU"
            raise setting_error(key, value, f"this torch ({torch.__version__}, built {built}) "
                                "has no CUDA here (torch.cuda.is_available() is False); "
                                "use problem.device=cpu")
        count = torch.cuda.device_count()
        if index is not None and int(index) >= count:
            raise setting_error(key, value, f"there are {count} CUDA device(s) here; "
                                f"choose cuda:0..cuda:{count - 1}")
    if kind == "mps" and not (getattr(torch.backends, "mps", None) is not None
                              and torch.backends.mps.is_available()):
        raise setting_error(key, value, "this torch has no MPS device here; use "
                            "problem.device=cpu")
    return torch.device(name)


def resolve_backend(choice: Backend, device: torch.device, dim: int,
                    n_dofs: int | None = None, solves_per_factor: int = 1) -> str:
    """The backend name of a ``backend`` setting: ``auto`` is
    :func:`torchfit.linalg.backends.choice.default_backend` (3-D CPU: ``pardiso`` where installed,
    else ``scipy``, and ``amg`` above its size threshold when ``n_dofs`` is given and the
    use makes few ``solves_per_factor``; CUDA: ``cudss`` where installed, else ``cg``).
    The rigged bodies give no size: their fits solve a Jacobian column per parameter
    (192 on the arm) with every factor, where PARDISO wins at every size measured."""
    if choice != Backend.auto:
        return choice.value
    from ..linalg.backends import default_backend

    return default_backend(dim, device, n_dofs, solves_per_factor)


def dtype_of(choice: DType | str) -> torch.dtype:
    """``torch.float64`` or ``torch.float32``."""
    return {DType.float64: torch.float64, DType.float32: torch.float32}[DType(choice)]


def validate_config(cfg: ProblemConfig) -> None:
    """Generic checks of a problem config (one-line :class:`ProblemConfigError` each).

    Choice settings are members of their enum; every numeric setting is a number of the
    declared type and finite (recursively in lists: ``inf`` is as wrong as ``nan``);
    ``noise >= 0``; the device exists here; the direct backends run on the CPU only;
    ``pardiso`` and ``amg`` are installed where chosen.
    """
    check_values(cfg, "problem", ProblemConfigError)
    require_setting(cfg.noise >= 0, cfg, "noise", "must be >= 0 (the standard deviation "
                    "of the noise; 0 for none)")
    device = check_device("device", cfg.device)
    require_setting(device.type == "cpu" or cfg.backend not in _CPU_BACKENDS, cfg, "backend",
                    f"runs on the CPU only; with problem.device={cfg.device} use "
                    "problem.backend=auto (cudss where installed, else cg), cudss or cg")
    require_setting(cfg.backend != Backend.cudss or device.type == "cuda", cfg, "backend",
                    f"runs on CUDA only; with problem.device={cfg.device} use "
                    "problem.backend=scipy, pardiso or auto")
    require_setting(cfg.backend != Backend.cudss or cudss_available(), cfg, "backend",
                    f"needs nvmath-python with cuDSS, which is not installed here: "
                    f"{CUDA_EXTRA}, or use problem.backend=cg")
    require_setting(cfg.backend != Backend.pardiso or pardiso_available(), cfg, "backend",
                    f"needs MKL PARDISO, which is not installed here: {PARDISO_EXTRA} "
                    "(x86-64 only, about 700 MB), or use problem.backend=scipy")
    require_setting(cfg.backend != Backend.amg or amg_available(), cfg, "backend",
                    f"needs pyamg, which is not installed here: {AMG_EXTRA}, or use "
                    "problem.backend=pardiso or scipy")


def make_config(config_class: type[ProblemConfig], cfg: Any = None,
                overrides: Mapping[str, Any] | None = None) -> ProblemConfig:
    """A ``config_class`` instance from ``None`` (defaults), an instance, or a mapping
    (dict, OmegaConf node), with ``overrides`` applied; unknown settings are errors."""
    return make_settings(config_class, cfg, overrides, "problem", ProblemConfigError)
