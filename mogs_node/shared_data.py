"""Where the real recorded data excerpts lie: ``$MOGS_SHARED_DATA`` if set, else ``../shared/data``
beside the project root. Every default data path of the package and its tests is built from here."""

from __future__ import annotations

import os
from pathlib import Path

PROJECT_ROOT = Path(__file__).resolve().parents[1]


def shared_data_dir(sub: str = "") -> Path:
    """The shared-data folder (or ``sub`` inside it); the path may not exist (a user's checkout)."""
    root = Path(os.environ.get("MOGS_SHARED_DATA") or PROJECT_ROOT.parent / "shared" / "data")
    return root / sub if sub else root
