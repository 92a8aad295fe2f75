"""Training checkpoints on disk: the file name, the format tag and the one reader.

Read by the trainer (resume), warm starts and export; written by cfrace.rl.train. A checkpoint is
a torch file of the trainer's own making (trusted: never load one from elsewhere). torch is imported
only to read one, so that the names here cost nothing to import (the sweep planner uses them).
"""

from __future__ import annotations

from pathlib import Path

from cfrace.errors import ConfigError

CHECKPOINT = "checkpoint.pt"
FORMAT = "cfrace-ippo-1"


def load_checkpoint(path: str | Path) -> dict:
    """A checkpoint file or a run directory (its checkpoint.pt) -> the saved dict; one-line ConfigError
    when it is missing, unreadable or not a cfrace checkpoint."""
    path = Path(path)
    if path.is_dir():
        path = path / CHECKPOINT
    if not path.exists():
        raise ConfigError(f"{path}: no such checkpoint")
    import torch

    try:
        ckpt = torch.load(path, map_location="cpu", weights_only=False)
    except Exception as exc:  # torch raises many types for damaged files
        raise ConfigError(f"{path}: not a readable checkpoint ({str(exc).splitlines()[0][:120]})") from None
    if not isinstance(ckpt, dict) or ckpt.get("format") != FORMAT:
        raise ConfigError(f"{path}: not a cfrace training checkpoint")
    return ckpt
