"""Atomic writers of the run store (tables, arrays) on cloudpbf_io.files.atomic_path, and file checksums
(sha256_file: cloudpbf.store.safe's, which never follows links and reads regular files only)."""
from __future__ import annotations

from pathlib import Path

import numpy as np

from cloudpbf.store.safe import sha256_file
from cloudpbf_io.files import atomic_path

__all__ = ["save_frame", "save_npz", "sha256_file"]


def save_frame(frame, path: str | Path) -> Path:
    """Write a pandas DataFrame to ``.csv`` or ``.parquet`` (by suffix, no index) atomically; returns the path."""
    path = Path(path)
    suffix = path.suffix.lower()
    if suffix not in (".csv", ".parquet"):
        raise ValueError(f"{path}: expected a .csv or .parquet file name")
    with atomic_path(path) as tmp:
        if suffix == ".csv":
            frame.to_csv(tmp, index=False)
        else:
            frame.to_parquet(tmp, index=False)
    return path


def save_npz(path: Path, arrays: dict) -> None:
    with atomic_path(path) as tmp:
        with open(tmp, "wb") as fh:
            np.savez(fh, **arrays)
