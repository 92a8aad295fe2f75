"""Where the repo's data folders live (tracks/, calibration/, policies/)."""

from __future__ import annotations

import os
from pathlib import Path

#: The repository root: the parent of the ``cfrace`` package (editable install), or
#: ``$CFRACE_HOME`` when set.
ROOT = Path(os.environ.get("CFRACE_HOME", Path(__file__).resolve().parent.parent))
TRACKS_DIR = ROOT / "tracks"
CALIBRATION_DIR = ROOT / "calibration"
POLICIES_DIR = ROOT / "policies"


def resolve_named(name_or_path: str | Path, folder: Path, suffix: str) -> Path:
    """A path as given when it exists or looks like a path, else ``folder/NAME{suffix}``."""
    text = str(name_or_path)
    path = Path(text)
    if path.exists() or "/" in text or text.endswith(suffix):
        return path
    return folder / f"{text}{suffix}"
