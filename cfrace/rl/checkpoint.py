"""Training checkpoints on disk: the file name, the format tag and the one reader.

Read by the trainer (resume), warm starts and export; written by cfrace.rl.train. A checkpoint is
a torch file of the trainer's own making, read with ``weights_only=True``: tensors, plain Python
values and numpy arrays (the RNG states) only, so a crafted file cannot run code when it is
loaded; it gets one line instead. torch is imported only to read one, so that the names here cost
nothing to import (the sweep planner uses them).
"""

from __future__ import annotations

from pathlib import Path

from cfrace.errors import ConfigError

CHECKPOINT = "checkpoint.pt"
FORMAT = "cfrace-ippo-1"


def _numpy_globals() -> list:
    """What a checkpoint's numpy arrays (np.random.get_state()) need besides tensors: the array
    rebuild function, the array and dtype types (they construct arrays of plain numbers only)."""
    import numpy as np

    try:
        from numpy._core.multiarray import _reconstruct
    except ImportError:   # numpy 1.x
        from numpy.core.multiarray import _reconstruct
    dtypes = [getattr(np.dtypes, n) for n in dir(np.dtypes) if n.endswith("DType")] if hasattr(np, "dtypes") else []
    return [_reconstruct, np.ndarray, np.dtype, *dtypes]


def load_checkpoint(path: str | Path) -> dict:
    """A checkpoint file or a run directory (its checkpoint.pt) -> the saved dict; one-line ConfigError
    when it is missing, unreadable or not a cfrace checkpoint."""
    path = Path(path)
    if path.is_dir():
        path = path / CHECKPOINT
    if not path.exists():
        raise ConfigError(f"{path}: no such checkpoint")
    import pickle
    import zipfile

    if not zipfile.is_zipfile(path):    # torch.save writes a zip archive: anything else is no checkpoint of ours
        what = "an empty file" if path.stat().st_size == 0 else "not a torch zip archive"
        raise ConfigError(f"{path}: not a cfrace training checkpoint ({what}; `cfrace train` writes checkpoint.pt)")

    import torch

    try:
        with torch.serialization.safe_globals(_numpy_globals()):
            ckpt = torch.load(path, map_location="cpu", weights_only=True)
    except pickle.UnpicklingError as exc:
        unsafe = next((line.strip() for line in str(exc).splitlines() if "GLOBAL" in line or "global" in line), "")
        raise ConfigError(f"{path}: refused, not a plain-data checkpoint: loading it would run code or build "
                          f"objects ({unsafe[:120] or 'unsupported pickle content'})") from None
    except Exception as exc:  # torch raises many types for damaged files
        first = (str(exc).strip().splitlines() or [type(exc).__name__])[0]
        raise ConfigError(f"{path}: not a readable checkpoint ({first[:120]})") from None
    if not isinstance(ckpt, dict) or ckpt.get("format") != FORMAT:
        raise ConfigError(f"{path}: not a cfrace training checkpoint")
    return ckpt
