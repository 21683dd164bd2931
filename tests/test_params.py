"""Nested parameter groups: frozen dataclasses all the way down, checked at every level."""

from __future__ import annotations

from dataclasses import dataclass, field

import pytest

from mogs_node.errors import ConfigError
from mogs_node.params import check_choice, group_of, parse_params


@dataclass(frozen=True)
class _Ransac:
    iterations: int = 100
    inlier_m: float = 0.05


@dataclass(frozen=True)
class _Stage:
    enabled: bool = True
    ransac: _Ransac = field(default_factory=_Ransac)


@dataclass(frozen=True)
class _Node:
    rate_hz: float = 10.0
    stage: _Stage = field(default_factory=_Stage)


def test_nested_groups_are_built_from_mappings_and_keep_defaults():
    p = parse_params(_Node, {"stage": {"ransac": {"inlier_m": 1}}})
    assert p == _Node(stage=_Stage(ransac=_Ransac(iterations=100, inlier_m=1.0)))
    assert isinstance(p.stage.ransac.inlier_m, float)
    assert parse_params(_Node, {}) == _Node()


def test_a_group_given_as_its_dataclass_is_taken_as_is():
    group = _Stage(enabled=False)
    assert parse_params(_Node, {"stage": group}).stage is group


@pytest.mark.parametrize(
    ("values", "names"),
    [
        ({"stage": {"ransac": {"iteratons": 5}}}, ["node.stage.ransac", "iteratons", "iterations"]),
        ({"stage": {"ransac": {"iterations": "many"}}}, ["node.stage.ransac.iterations", "int"]),
        ({"stage": 3}, ["node.stage", "_Stage"]),
        ({"stage": {"enabled": 1}}, ["node.stage.enabled", "bool"]),
    ],
)
def test_an_error_deep_in_a_group_names_its_dotted_path(values, names):
    with pytest.raises(ConfigError) as err:
        parse_params(_Node, values, where="node")
    for name in names:
        assert name in str(err.value)


def test_group_of_takes_same_named_fields_and_given_values_win():
    @dataclass(frozen=True)
    class Group:
        a: int = 0
        b: str = ""
        c: float = 1.0

    @dataclass(frozen=True)
    class Flat:
        a: int = 5
        b: str = "flat"
        other: int = 9

    assert group_of(Group, Flat()) == Group(a=5, b="flat", c=1.0)
    assert group_of(Group, Flat(), b="given", c=2.0) == Group(a=5, b="given", c=2.0)


def test_check_choice_names_the_field_and_the_choices():
    check_choice("viz.mode", "save", ("save", "spawn"))
    with pytest.raises(
        ConfigError, match=r"viz.mode: expected one of \('save', 'spawn'\), got 'x'"
    ):
        check_choice("viz.mode", "x", ("save", "spawn"))
