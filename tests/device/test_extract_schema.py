"""The wire schema of the extraction settings (lamina_shared.ops) against the device's own.

``EXTRACT_FIELDS`` lives in lamina-shared, which may not import the device, so it is
written out by hand beside ``ExtractSettings``: this test fails as soon as the two drift.
"""

from __future__ import annotations

import dataclasses
import typing

from lamina_device.extract import METHODS, RUN_CHOICES, ExtractSettings
from lamina_shared.ops import EXTRACT_FIELDS, Problems, check_extract

KIND_OF_TYPE = {
    "float | None": "number-or-null",
    "float": "number",
    "int": "int",
    "bool": "bool",
}
"""The JSON kind each Python annotation of a setting travels as."""
CHOICES = {"method": METHODS, "run_choice": RUN_CHOICES}
"""Text settings and the options the device accepts for each."""


def test_every_setting_has_its_wire_kind_and_nothing_else_is_on_the_wire():
    hints = typing.get_type_hints(ExtractSettings)
    names = [f.name for f in dataclasses.fields(ExtractSettings)]
    assert list(EXTRACT_FIELDS) == names
    for name in names:
        annotation = str(hints[name]).replace("typing.Optional[float]", "float | None")
        annotation = annotation.replace("<class '", "").replace("'>", "")
        expected = name if name in CHOICES else KIND_OF_TYPE[annotation]
        assert EXTRACT_FIELDS[name] == expected, name


def test_the_defaults_pass_the_wire_check_unchanged():
    problems = Problems()
    defaults = dataclasses.asdict(ExtractSettings())
    changes = check_extract(defaults, "extract", problems)
    assert problems.items == [] and changes is not None
    assert changes.as_dict() == defaults
    for name, options in CHOICES.items():
        assert getattr(ExtractSettings(), name) in options
