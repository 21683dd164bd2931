"""What a message field may be, and its checks: scalar kinds, array specs, size limits.

Pure functions of a field's kind or spec and its value; the message classes (``schema``) and the
wire codec (``codec``) both use them. Every check raises :class:`MessageError` naming the field.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np

from mogs_node.errors import MessageError

DEFAULT_MAX_MESSAGE_BYTES = 256 * 1024 * 1024
MAX_HEADER_BYTES = 64 * 1024
MAX_DIM = 1 << 20  # no single dimension beyond 1M elements
MAX_TOPIC_CHARS = 256


@dataclass(frozen=True)
class ArraySpec:
    """What an array field may be.

    ``shapes`` lists accepted shape patterns; a pattern entry is an int (exact size) or a symbol
    (str) bound consistently across all arrays of the message (e.g. ``"H"``, ``"N"``).
    """

    dtypes: tuple[str, ...]
    shapes: tuple[tuple[int | str, ...], ...]
    finite: bool = False
    optional: bool = False


# scalar kinds: "int", "float", "str", "bool", "vec3" (3 finite floats), "dict_num" (str -> number),
# "dict_any" (str -> int/float/str/bool or nested dict of those, depth 2)
_SCALAR_KINDS = {"int", "float", "str", "bool", "vec3", "dict_num", "dict_any", "float_or_nan"}


_INT_MIN, _INT_MAX = -(1 << 63), (1 << 63) - 1


def _check_scalar(kind: str, name: str, value: Any) -> Any:
    # fast paths for the common, valid cases (the codec runs per message on every topic)
    tv = type(value)
    if tv is int and kind == "int" and _INT_MIN <= value <= _INT_MAX:
        return value
    if tv is float and kind == "float" and math.isfinite(value):
        return value
    if tv is str and kind == "str" and len(value) <= 4096:
        return value
    if (tv is tuple or tv is list) and kind == "vec3" and len(value) == 3:
        a, b, c = value
        if type(a) is float and type(b) is float and type(c) is float and math.isfinite(a + b + c):
            return (a, b, c)
    if kind == "int":
        if isinstance(value, bool) or not isinstance(value, int | np.integer):
            raise MessageError(f"expected int, got {type(value).__name__}", field=name)
        if not _INT_MIN <= int(value) <= _INT_MAX:
            raise MessageError("integer out of int64 range", field=name)
        return int(value)
    if kind in ("float", "float_or_nan"):
        if isinstance(value, bool) or not isinstance(value, int | float | np.floating | np.integer):
            raise MessageError(f"expected float, got {type(value).__name__}", field=name)
        v = float(value)
        if not math.isfinite(v) and not (kind == "float_or_nan" and math.isnan(v)):
            raise MessageError("non-finite value", field=name)
        return v
    if kind == "str":
        if not isinstance(value, str):
            raise MessageError(f"expected str, got {type(value).__name__}", field=name)
        if len(value) > 4096:
            raise MessageError("string longer than 4096 characters", field=name)
        return value
    if kind == "bool":
        if not isinstance(value, bool):
            raise MessageError(f"expected bool, got {type(value).__name__}", field=name)
        return value
    if kind == "vec3":
        if not isinstance(value, list | tuple | np.ndarray) or len(value) != 3:
            raise MessageError("expected 3 floats", field=name)
        out = tuple(_check_scalar("float", f"{name}[{i}]", v) for i, v in enumerate(value))
        return out
    if kind == "dict_num":
        if not isinstance(value, dict) or len(value) > 4096:
            raise MessageError("expected a dict of str -> number (at most 4096 keys)", field=name)
        out_d: dict[str, float | int] = {}
        for k, v in value.items():
            if not isinstance(k, str):
                raise MessageError("dict key is not a str", field=name)
            if isinstance(v, bool) or not isinstance(v, int | float | np.integer | np.floating):
                raise MessageError(f"value of {k!r} is not a number", field=name)
            out_d[k] = v.item() if isinstance(v, np.generic) else v
        return out_d
    if kind == "dict_any":
        return _check_dict_any(name, value, depth=0)
    raise MessageError(f"unknown scalar kind {kind}", field=name)  # pragma: no cover


def _check_dict_any(name: str, value: Any, depth: int) -> dict[str, Any]:
    if not isinstance(value, dict) or len(value) > 4096 or depth > 2:
        raise MessageError("expected a (nested, depth <= 2) dict of str -> scalars", field=name)
    out: dict[str, Any] = {}
    for k, v in value.items():
        if not isinstance(k, str):
            raise MessageError("dict key is not a str", field=name)
        if isinstance(v, dict):
            out[k] = _check_dict_any(f"{name}.{k}", v, depth + 1)
        elif isinstance(v, bool | int | float | str):
            out[k] = v
        elif isinstance(v, np.generic):
            out[k] = v.item()
        else:
            raise MessageError(
                f"value of {k!r} has unsupported type {type(v).__name__}", field=name
            )
    return out


def _match_shape(
    name: str, spec: ArraySpec, shape: tuple[int, ...], symbols: dict[str, int]
) -> None:
    errors = []
    for pattern in spec.shapes:
        if len(pattern) != len(shape):
            errors.append(f"ndim {len(shape)} != {len(pattern)}")
            continue
        bound = dict(symbols)
        ok = True
        for want, got in zip(pattern, shape):
            if isinstance(want, int):
                if want != got:
                    ok = False
                    errors.append(f"size {got} != {want}")
                    break
            elif want in bound and bound[want] != got:
                ok = False
                errors.append(f"{want}={got} disagrees with {want}={bound[want]} of another array")
                break
            else:
                bound[want] = got
        if ok:
            symbols.update(bound)
            return
    pats = " or ".join("[" + ",".join(str(p) for p in pat) + "]" for pat in spec.shapes)
    raise MessageError(
        f"shape {list(shape)} does not match {pats} ({'; '.join(errors)})", field=name
    )


def _check_array(name: str, spec: ArraySpec, arr: Any, symbols: dict[str, int]) -> np.ndarray:
    if not isinstance(arr, np.ndarray):
        raise MessageError(f"expected a numpy array, got {type(arr).__name__}", field=name)
    dt = arr.dtype
    if dt.str not in spec.dtypes and dt.newbyteorder("<").str not in spec.dtypes:
        raise MessageError(f"dtype {dt.str} not in {list(spec.dtypes)}", field=name)
    _match_shape(name, spec, arr.shape, symbols)
    if spec.finite and dt.kind == "f" and arr.size and not np.isfinite(arr).all():
        raise MessageError("contains NaN or inf", field=name)
    return arr


def _check_scalars(table: tuple[tuple[str, str], ...], values: dict[str, Any]) -> dict[str, Any]:
    """The scalar fields of ``table`` taken from ``values``, checked (the reference checker)."""
    out: dict[str, Any] = {}
    for name, kind in table:
        try:
            value = values[name]
        except KeyError:
            raise MessageError("missing field", field=name) from None
        out[name] = _check_scalar(kind, name, value)
    return out


# Inline acceptance tests of the common valid case of each scalar kind, for the generated fast
# checkers below: each accepts a subset of what _check_scalar accepts and returns it unchanged.
_FAST_CONDITIONS = {
    "int": "type({v}) is int and {lo} <= {v} <= {hi}",
    "float": "type({v}) is float and {v} - {v} == 0.0",  # inf - inf and nan - nan are nan
    "float_or_nan": "type({v}) is float and ({v} - {v} == 0.0 or {v} != {v})",
    "str": "type({v}) is str and len({v}) <= 4096",
    "bool": "type({v}) is bool",
    "vec3": (
        "(type({v}) is list or type({v}) is tuple) and len({v}) == 3"
        " and type({v}[0]) is float and type({v}[1]) is float and type({v}[2]) is float"
        " and {v}[0] - {v}[0] == 0.0 and {v}[1] - {v}[1] == 0.0 and {v}[2] - {v}[2] == 0.0"
    ),
}
_FAST_VALUES = {"vec3": "({v}[0], {v}[1], {v}[2])"}


def _make_fast_scalars(
    table: tuple[tuple[str, str], ...],
) -> Callable[[dict[str, Any]], dict[str, Any] | None]:
    """A checker specialised to one message type's scalar fields, generated once per type.

    It returns the checked fields when every field is present and in the common valid form
    (exact types, finite floats, in-range ints), and None otherwise (keys beyond the fields are
    the caller's business, as in :func:`_check_scalars`); the caller then runs the
    reference :func:`_check_scalars`, which converts what may be converted or raises naming the
    field. Straight-line code per type beats walking the table per message (one IMU sample's
    fields: 0.95 -> 0.65 us CPU), which adds up on 200 Hz-and-up topics.
    """
    conds, items = [], []
    for i, (name, kind) in enumerate(table):
        v = f"v{i}"
        cond = _FAST_CONDITIONS.get(kind)
        if cond is not None:
            conds.append(cond.format(v=v, lo=_INT_MIN, hi=_INT_MAX))
            items.append(f"{name!r}: " + _FAST_VALUES.get(kind, "{v}").format(v=v))
        else:  # dict kinds: the reference check (it raises naming the field, in field order)
            items.append(f"{name!r}: _check_scalar({kind!r}, {name!r}, {v})")
    fetch = "; ".join(f"v{i} = f[{name!r}]" for i, (name, _) in enumerate(table))
    src = (
        "def fast(f):\n"
        "    try:\n"
        f"        {fetch}\n"
        "    except KeyError:\n"
        "        return None\n"
        + (f"    if not ({' and '.join(conds)}):\n        return None\n" if conds else "")
        + f"    return {{{', '.join(items)}}}\n"
    )
    namespace: dict[str, Any] = {"_check_scalar": _check_scalar}
    exec(compile(src, f"<mogs fast scalars {table[:1]}...>", "exec"), namespace)  # noqa: S102
    return namespace["fast"]


def _check_arrays(cls: Any, arrays: dict[str, Any], out: dict[str, Any]) -> None:
    """Check the arrays of ``cls`` (in spec order, so symbols bind in a fixed order) into ``out``."""
    symbols: dict[str, int] = {}
    for name, spec in cls.ARRAYS.items():
        arr = arrays.get(name)
        if arr is None:
            if not spec.optional:
                raise MessageError("missing array", field=name)
            out[name] = None
            continue
        out[name] = _check_array(name, spec, arr, symbols)
