"""Reading a YAML file with one clear error naming the file (and the line) when it cannot be read
or parsed: launch files and the datasets' calibration files share it."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import yaml

from mogs_node.errors import MogsError


def read_yaml(path: Path, error: type[MogsError], *, mapping: bool = False) -> Any:
    """The YAML document in ``path``; an OpenCV ``%YAML:1.0`` header line is tolerated (EuRoC and
    Kalibr files start with one). Raises ``error`` when the file cannot be read, is not YAML, or
    (``mapping``) is not a mapping at top level."""
    try:
        text = path.read_text()
    except OSError as err:
        raise error(f"{path}: cannot read ({err.strerror or err})") from err
    lines = ["" if ln.startswith("%YAML") else ln for ln in text.splitlines()]
    try:
        data = yaml.safe_load("\n".join(lines))
    except yaml.YAMLError as err:
        mark = getattr(err, "problem_mark", None)
        where = f":{mark.line + 1}" if mark is not None else ""
        raise error(f"{path}{where}: invalid YAML ({err})") from err
    if mapping and not isinstance(data, dict):
        raise error(f"{path}: expected a mapping")
    return data
