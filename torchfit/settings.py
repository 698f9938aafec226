"""Settings dataclasses: choices, generic validation and construction, for problems, solvers and runs.

A section's settings (``problem``, ``solver``, a run's options) are one dataclass whose
field defaults are the only place a default is written; Hydra's schemas are those
dataclasses. This module holds what every section shares:

* :class:`Choice`: a setting with a fixed set of values, a ``str`` enum whose member names
  equal their values, so OmegaConf rejects a bad value when Hydra composes the config
  (with the list of choices) and ``cfg.data == "dense"`` holds.
* :func:`check_values`: the generic checks of a settings instance against its annotations
  (choices are members, ``bool``/``int``/``float``/``str`` have their type, lists hold
  their element type, every number, in lists too, is finite); the first failure raises the section's
  error with one line ``<section>.<field>=<value>: <what is allowed>``.
* :func:`make_settings`: an instance from ``None`` (the defaults), an instance, or a
  mapping (dict, OmegaConf node) plus overrides; an unknown key is an error naming it.
"""
from __future__ import annotations

import dataclasses
import enum
import functools
import math
import numbers
import typing
from collections.abc import Mapping, Sequence
from typing import Any

from .errors import ConfigurationError


class Choice(str, enum.Enum):
    """A setting with a fixed set of values. Member names equal their values (OmegaConf
    converts a string by name); ``str()`` and f-strings give the value."""

    def __str__(self) -> str:
        return self.value

    @classmethod
    def choices(cls) -> list[str]:
        return [member.value for member in cls]


def show(value: Any) -> str:
    """A setting's value as written on a command line (``inf``, ``dense``, ``[0.0, 1.0]``)."""
    if isinstance(value, enum.Enum):
        return str(value.value)
    if isinstance(value, str):
        return value if value and not any(c.isspace() for c in value) else repr(value)
    if isinstance(value, Sequence):
        return "[" + ", ".join(show(v) for v in value) + "]"
    return repr(value) if not isinstance(value, float) else str(value)


def setting_error(error: type[ConfigurationError], path: str, value: Any,
                  allowed: str) -> ConfigurationError:
    """``<path>=<value>: <allowed>`` as an ``error`` (``path`` is ``section.field``)."""
    return error(f"{path}={show(value)}: {allowed}")


@functools.cache
def choice_fields(config_class: type) -> dict[str, type[Choice]]:
    """``{field: Choice subclass}`` of the choice settings of a settings dataclass (read
    from its type hints once per class)."""
    hints = typing.get_type_hints(config_class)
    return {f.name: hints[f.name] for f in dataclasses.fields(config_class)
            if isinstance(hints.get(f.name), type) and issubclass(hints[f.name], Choice)}


def to_choice(kind: type[Choice], path: str, value: Any,
              error: type[ConfigurationError]) -> Choice:
    """``value`` (a member, its value or its name) as a member of ``kind``, else an
    ``error`` listing the choices."""
    if isinstance(value, kind):
        return value
    if isinstance(value, enum.Enum):
        value = value.value
    if isinstance(value, str):
        try:
            return kind(value)
        except ValueError:
            pass
    key = path.rsplit(".", 1)[-1]
    raise error(f"{path}={show(value)} is not a {key} choice; "
                f"choose one of {', '.join(kind.choices())}")


def convert_choices(cfg: Any, section: str, error: type[ConfigurationError]) -> None:
    """Replace every choice setting of ``cfg`` by its member (in place)."""
    for key, kind in choice_fields(type(cfg)).items():
        setattr(cfg, key, to_choice(kind, f"{section}.{key}", getattr(cfg, key), error))


def _is_number(value: Any) -> bool:
    return isinstance(value, numbers.Real) and not isinstance(value, bool)


def _is_sequence(value: Any) -> bool:
    return isinstance(value, Sequence) and not isinstance(value, str) or \
        type(value).__name__ == "ListConfig"


def _non_finite(value: Any) -> bool:
    """Some number in ``value`` (recursively in lists) is NaN or infinite."""
    if _is_number(value):
        return not math.isfinite(float(value))
    return _is_sequence(value) and any(_non_finite(v) for v in value)


def _check_value(path: str, value: Any, hint: Any, error: type[ConfigurationError]) -> None:
    """The type of one value against its annotation (and of a list's elements)."""
    origin = typing.get_origin(hint)
    if origin is typing.Union:                       # Optional[X]
        args = typing.get_args(hint)
        if value is None and type(None) in args:
            return
        inner = [a for a in args if a is not type(None)]
        if len(inner) == 1:
            _check_value(path, value, inner[0], error)
        return
    if origin in (list, tuple, Sequence, typing.List, typing.Tuple):
        element = (typing.get_args(hint) or (Any,))[0]
        noun = {int: "integers", float: "numbers", str: "strings"}.get(element, "values")
        if not _is_sequence(value):
            raise setting_error(error, path, value, f"must be a list of {noun}")
        for item in value:
            if element in (int, float) and not (
                    _is_number(item) and (element is float or isinstance(item, numbers.Integral))):
                raise setting_error(error, path, value, f"must be a list of {noun}")
        return
    if hint is bool and not isinstance(value, bool):
        raise setting_error(error, path, value, "must be true or false")
    if hint is int and not (_is_number(value) and isinstance(value, numbers.Integral)):
        raise setting_error(error, path, value, "must be an integer")
    if hint is float and not _is_number(value):
        raise setting_error(error, path, value, "must be a number")
    if hint is str and not isinstance(value, str):
        raise setting_error(error, path, value, "must be a string")


def check_values(cfg: Any, section: str, error: type[ConfigurationError]) -> None:
    """The generic checks of a settings instance (choices converted in place)."""
    hints = typing.get_type_hints(type(cfg))
    choices = choice_fields(type(cfg))
    for f in dataclasses.fields(cfg):
        path = f"{section}.{f.name}"
        value = getattr(cfg, f.name)
        if f.name in choices:
            setattr(cfg, f.name, to_choice(choices[f.name], path, value, error))
            continue
        if _non_finite(value):
            raise setting_error(error, path, value, "every numeric setting must be finite "
                                "(no inf, -inf or nan)")
        _check_value(path, value, hints.get(f.name, Any), error)


def make_settings(config_class: type, cfg: Any, overrides: Mapping[str, Any] | None,
                  section: str, error: type[ConfigurationError]) -> Any:
    """A ``config_class`` instance from ``None`` (defaults), an instance, or a mapping
    (dict, OmegaConf node), with ``overrides`` applied; unknown settings are errors."""
    overrides = dict(overrides or {})
    names = {f.name for f in dataclasses.fields(config_class)}
    if cfg is None or isinstance(cfg, config_class):
        values: dict[str, Any] = {}
    elif dataclasses.is_dataclass(cfg):
        raise error(f"a {type(cfg).__name__} was given where a "
                    f"{config_class.__name__} is needed")
    else:
        try:
            values = dict(cfg)
        except (TypeError, ValueError):
            raise error(f"{section} settings must be a {config_class.__name__} or a "
                        f"mapping, got {type(cfg).__name__}") from None
    values.update(overrides)
    unknown = sorted(set(values) - names)
    if unknown:
        raise error(f"unknown setting(s) {', '.join(f'{section}.{k}' for k in unknown)}"
                    f" for {config_class.__name__}; known: {', '.join(sorted(names))}")
    values = {k: (list(v) if _is_sequence(v) else v) for k, v in values.items()}
    if isinstance(cfg, config_class):
        return dataclasses.replace(cfg, **values)
    return config_class(**values)
