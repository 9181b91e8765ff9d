"""Atomic writers of the run store (tables, arrays) on pbf_cuda.files.atomic_path, and file checksums."""
from __future__ import annotations

import hashlib
from pathlib import Path

import numpy as np

from pbf_cuda.files import atomic_path

__all__ = ["write_csv", "write_parquet", "save_npz", "sha256_file"]


def write_csv(frame, path: str | Path) -> Path:
    """Write a pandas DataFrame as CSV atomically (no index)."""
    with atomic_path(path) as tmp:
        frame.to_csv(tmp, index=False)
    return Path(path)


def write_parquet(frame, path: str | Path) -> Path:
    with atomic_path(path) as tmp:
        frame.to_parquet(tmp, index=False)
    return Path(path)


def save_npz(path: Path, arrays: dict) -> None:
    with atomic_path(path) as tmp:
        with open(tmp, "wb") as fh:
            np.savez(fh, **arrays)


def sha256_file(path: str | Path) -> str:
    digest = hashlib.sha256()
    with open(path, "rb") as fh:
        for block in iter(lambda: fh.read(1 << 20), b""):
            digest.update(block)
    return digest.hexdigest()
