"""Node parameters: a frozen dataclass per node, built strictly from a launch file's mapping.

A parameter group is itself a frozen dataclass field, nested as deep as needed (a mapping in the
launch file); every level is checked the same way: an unknown key or a value of the wrong type is
one :class:`~mogs_node.errors.ConfigError` that names its dotted path and the known keys.
"""

from __future__ import annotations

import dataclasses
import difflib
import types
import typing
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from typing import Any

from mogs_node.errors import ConfigError

_G = typing.TypeVar("_G")

__all__ = ["EmptyParams", "check_choice", "group_of", "parse_group", "parse_params"]


@dataclass(frozen=True)
class EmptyParams:
    """A node without parameters."""


def parse_params(cls: type, values: Mapping[str, Any] | None, *, where: str = "params") -> Any:
    """Build the frozen params dataclass ``cls`` from a mapping, strictly.

    Unknown keys and values of the wrong type raise :class:`ConfigError` naming the key; ints are
    accepted for float fields, lists for tuple fields.
    """
    if not dataclasses.is_dataclass(cls):
        raise ConfigError(f"{where}: {cls!r} is not a dataclass")
    values = dict(values or {})
    hints = typing.get_type_hints(cls)
    names = {f.name for f in dataclasses.fields(cls) if f.init}
    unknown = set(values) - names
    if unknown:
        close = {u: difflib.get_close_matches(u, names, n=1) for u in sorted(unknown)}
        hint = "; ".join(f"{u!r}: did you mean {c[0]!r}?" for u, c in close.items() if c)
        raise ConfigError(
            f"{where}: unknown parameter(s) {sorted(unknown)}"
            + (f" ({hint})" if hint else "")
            + f"; known: {sorted(names)}"
        )
    kwargs = {}
    for name, value in values.items():
        kwargs[name] = _coerce(hints.get(name, Any), value, f"{where}.{name}")
    try:
        return cls(**kwargs)
    except (TypeError, ValueError) as err:
        raise ConfigError(f"{where}: {err}") from err


def parse_group(cls: type[_G], params: Any, name: str, where: str) -> _G:
    """The nested group ``name`` of a node's ``params`` (a mapping in the launch file) parsed
    strictly as ``cls``; errors name ``where.name``."""
    return parse_params(cls, getattr(params, name), where=f"{where}.{name}")


def check_choice(where: str, value: Any, choices: Any) -> None:
    """Raise :class:`ConfigError` naming ``where`` unless ``value`` is one of ``choices``."""
    if value not in choices:
        raise ConfigError(f"{where}: expected one of {choices}, got {value!r}")


def group_of(cls: type[_G], flat: Any, /, **given: Any) -> _G:
    """The parameter group ``cls`` (a frozen dataclass) filled from the same-named fields of the
    dataclass ``flat`` (a node's flat launch parameters), ``given`` winning (renamed or fixed
    values): launch files keep their flat names, and no conversion re-lists a group's fields."""
    have = {f.name for f in dataclasses.fields(flat)}
    values = {f.name: getattr(flat, f.name) for f in dataclasses.fields(cls) if f.name in have}
    return cls(**{**values, **given})


#: scalar field types: what the error calls them, and which YAML values fit (ints fit floats,
#: bools fit nothing but bools)
_SCALARS: dict[type, tuple[str, Callable[[Any], bool]]] = {
    bool: ("a bool", lambda v: isinstance(v, bool)),
    int: ("an int", lambda v: isinstance(v, int) and not isinstance(v, bool)),
    float: ("a number", lambda v: isinstance(v, int | float) and not isinstance(v, bool)),
    str: ("a string", lambda v: isinstance(v, str)),
}


def _coerce(tp: Any, value: Any, where: str) -> Any:
    origin = typing.get_origin(tp)
    args = typing.get_args(tp)
    if tp is Any:
        return value
    if origin in (typing.Union, types.UnionType):
        for a in args:
            try:
                return _coerce(a, value, where)
            except ConfigError:
                continue
        raise ConfigError(f"{where}: {value!r} does not fit {tp}")
    if tp is type(None):
        if value is None:
            return None
        raise ConfigError(f"{where}: expected null, got {value!r}")
    if origin is typing.Literal:
        if value in args:
            return value
        raise ConfigError(f"{where}: {value!r} is not one of {list(args)}")
    if tp in _SCALARS:
        what, fits = _SCALARS[tp]
        if fits(value):
            return float(value) if tp is float else value
        raise ConfigError(f"{where}: expected {what}, got {value!r}")
    if origin is tuple:
        if not isinstance(value, list | tuple):
            raise ConfigError(f"{where}: expected a list, got {value!r}")
        if len(args) == 2 and args[1] is Ellipsis:
            return tuple(_coerce(args[0], v, f"{where}[{i}]") for i, v in enumerate(value))
        if len(args) != len(value):
            raise ConfigError(f"{where}: expected {len(args)} items, got {len(value)}")
        return tuple(_coerce(a, v, f"{where}[{i}]") for i, (a, v) in enumerate(zip(args, value)))
    if dataclasses.is_dataclass(tp) and isinstance(tp, type):  # a nested parameter group
        if isinstance(value, tp):
            return value
        if not isinstance(value, Mapping):
            raise ConfigError(f"{where}: expected a mapping of {tp.__name__}, got {value!r}")
        return parse_params(tp, value, where=where)
    if origin in (list, dict) or tp in (list, dict):
        if not isinstance(value, origin or tp):
            raise ConfigError(f"{where}: expected a {(origin or tp).__name__}, got {value!r}")
        return value
    return value
