"""Options that set one field of a parameter record (a node's parameters, ``SimConfig``).

The option's ``dest`` is ``prefix + field``, so the record's values are read back from the parsed
arguments by prefix (:func:`fields_from_args`): no second list of the fields to keep in step.
"""

from __future__ import annotations

import argparse
from typing import Any

__all__ = ["field_option", "fields_from_args"]


def field_option(
    g: argparse.ArgumentParser | argparse._ArgumentGroup,
    prefix: str,
    flag: str,
    name: str,
    **kw: Any,
) -> None:
    """Add ``flag`` setting field ``name`` (``dest`` ``prefix + name``); the metavar is the
    flag's (argparse would show the dest's)."""
    if kw.get("action") is None and "choices" not in kw:
        kw.setdefault("metavar", flag[2:].upper().replace("-", "_"))
    g.add_argument(flag, dest=prefix + name, **kw)


def fields_from_args(args: argparse.Namespace, prefix: str) -> dict[str, Any]:
    """``{field: value}`` of every option added by :func:`field_option` with ``prefix``."""
    return {k[len(prefix) :]: v for k, v in vars(args).items() if k.startswith(prefix)}
