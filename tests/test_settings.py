"""The settings machinery every section shares: choices, the generic checks, construction."""
from __future__ import annotations

import dataclasses
import math
from typing import List, Optional

import pytest

from torchfit.errors import ConfigurationError
from torchfit.settings import (Choice, check_values, choice_fields, convert_choices,
                               make_settings, show)


class SettingsError(ConfigurationError):
    pass


class Colour(Choice):
    red = "red"
    blue = "blue"


@dataclasses.dataclass
class Settings:
    colour: Colour = Colour.red
    count: int = 3
    scale: float = 1.0
    flag: bool = False
    label: str = "x"
    sizes: List[int] = dataclasses.field(default_factory=lambda: [1, 2])
    limit: Optional[float] = None


def error_of(**values) -> str:
    settings = Settings(**values)
    with pytest.raises(SettingsError) as caught:
        check_values(settings, "part", SettingsError)
    assert "\n" not in str(caught.value)
    return str(caught.value)


def test_choices_compare_print_and_list_as_their_values():
    assert Colour.red == "red" and str(Colour.blue) == "blue" and f"{Colour.red}" == "red"
    assert Colour.choices() == ["red", "blue"]
    assert choice_fields(Settings) == {"colour": Colour}


def test_check_values_converts_choices_in_place_and_accepts_the_defaults():
    settings = Settings(colour="blue", limit=2)
    check_values(settings, "part", SettingsError)
    assert settings.colour is Colour.blue
    convert_choices(settings, "part", SettingsError)
    assert settings.colour is Colour.blue


@pytest.mark.parametrize("values, message", [
    ({"colour": "green"}, "part.colour=green is not a colour choice; choose one of red, blue"),
    ({"count": 2.5}, "part.count=2.5: must be an integer"),
    ({"count": True}, "part.count=True: must be an integer"),
    ({"scale": "big"}, "part.scale=big: must be a number"),
    ({"scale": math.inf}, "part.scale=inf: every numeric setting must be finite"),
    ({"flag": "yes"}, "part.flag=yes: must be true or false"),
    ({"label": 3}, "part.label=3: must be a string"),
    ({"sizes": [1, 2.5]}, "part.sizes=[1, 2.5]: must be a list of integers"),
    ({"sizes": [1, math.nan]}, "part.sizes=[1, nan]: every numeric setting must be finite"),
    ({"sizes": "1,2"}, "part.sizes=1,2: must be a list of integers"),
    ({"limit": math.nan}, "part.limit=nan: every numeric setting must be finite"),
    ({"limit": "low"}, "part.limit=low: must be a number"),
])
def test_each_bad_value_is_one_line_naming_section_field_value_and_rule(values, message):
    assert error_of(**values).startswith(message)


def test_make_settings_from_defaults_instance_mapping_and_overrides():
    assert make_settings(Settings, None, None, "part", SettingsError) == Settings()
    base = Settings(count=5)
    copy = make_settings(Settings, base, {"scale": 2.0}, "part", SettingsError)
    assert copy == Settings(count=5, scale=2.0) and copy is not base and base.scale == 1.0
    made = make_settings(Settings, {"count": 7, "sizes": (3, 4)}, None, "part", SettingsError)
    assert made.count == 7 and made.sizes == [3, 4]


def test_make_settings_refuses_unknown_keys_other_dataclasses_and_non_mappings():
    with pytest.raises(SettingsError, match=r"unknown setting\(s\) part.colr for Settings; "
                                            r"known: colour, count"):
        make_settings(Settings, {"colr": "red"}, None, "part", SettingsError)

    @dataclasses.dataclass
    class Other:
        x: int = 0

    with pytest.raises(SettingsError, match="a Other was given where a Settings is needed"):
        make_settings(Settings, Other(), None, "part", SettingsError)
    with pytest.raises(SettingsError, match="part settings must be a Settings or a mapping, "
                                            "got int"):
        make_settings(Settings, 3, None, "part", SettingsError)


def test_show_writes_values_as_on_a_command_line():
    assert show(Colour.red) == "red" and show(1.5) == "1.5" and show("a b") == "'a b'"
    assert show([0.0, Colour.blue]) == "[0.0, blue]" and show(None) == "None"
