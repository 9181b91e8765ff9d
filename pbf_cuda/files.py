"""Atomic file writes shared by the solvers' checkpoints and snapshots."""
from __future__ import annotations

import json
import os
import tempfile
from pathlib import Path

import numpy as np


def atomic_savez(path: str | Path, meta: dict, **arrays) -> Path:
    """Write arrays and a JSON `meta` record (stored as bytes under 'meta') to an npz, atomically:
    a temporary file in the same folder, then os.replace, so readers never see a partial file."""
    path = Path(path)
    arrays["meta"] = np.frombuffer(json.dumps(meta).encode(), dtype=np.uint8)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=path.name, suffix=".tmp")
    try:
        with os.fdopen(fd, "wb") as fh:
            np.savez(fh, **arrays)
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise
    return path


def read_meta(npz) -> dict:
    """The JSON record written by atomic_savez."""
    return json.loads(bytes(npz["meta"]).decode())
