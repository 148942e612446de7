"""segs.schema.build: the one builder of typed configs (nested dataclasses, renamed keys)."""
from __future__ import annotations

from dataclasses import dataclass

import pytest

from segs.errors import ConfigError
from segs.schema import build


@dataclass
class Inner:
    rate: float
    steps: tuple


@dataclass
class Outer:
    name: str
    inner: Inner
    size: int | None
    flag: bool = False


def test_nested_values_are_built_and_ints_become_floats():
    cfg = build(Outer, {"name": "a", "inner": {"rate": 1, "steps": [1, 2]}, "size": None}, "x")
    assert cfg == Outer("a", Inner(1.0, (1, 2)), None, False) and isinstance(cfg.inner.rate, float)


@pytest.mark.parametrize("values,message", [
    ({"name": "a", "inner": {"rate": 1, "steps": []}, "size": 1, "extra": 2}, "x.extra: unknown key"),
    ({"name": "a", "inner": {"rate": 1}, "size": 1}, "x.inner.steps: missing key"),
    ({"name": "a", "inner": {"rate": "fast", "steps": []}, "size": 1}, "x.inner.rate='fast': expected a number"),
    ({"name": "a", "inner": {"rate": 1, "steps": []}, "size": True}, "x.size=True: expected an integer"),
    ({"name": "a", "inner": 3, "size": 1}, "x.inner=3: expected a group of keys"),
])  # fmt: skip
def test_bad_values_are_one_line_errors_naming_the_key(values, message):
    with pytest.raises(ConfigError) as err:
        build(Outer, values, "x")
    assert str(err.value).startswith(message)


def test_renamed_keys_name_their_new_place_and_null_placeholders_are_dropped():
    base = {"name": "a", "inner": {"rate": 1, "steps": []}, "size": 1}
    with pytest.raises(ConfigError, match=r"^x\.inner\.old was renamed: use x\.inner\.rate$"):
        build(Outer, {**base, "inner": {"rate": 1, "steps": [], "old": 2}}, "x", renamed={"inner.old": "x.inner.rate"})
    values = {**base, "inner": {"rate": 1, "steps": [], "old": None}}
    assert build(Outer, values, "x", renamed={"inner.old": "x.inner.rate"}).inner.rate == 1.0
    assert values["inner"]["old"] is None  # the caller's mapping is not edited
