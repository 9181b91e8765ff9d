"""A finished run (stable or not) read back from its directory: RunResult."""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from cloudpbf.store.manifest import read_result

__all__ = ["RunResult"]


@dataclass
class RunResult:
    """A finished run (stable or not), read from its directory."""
    path: Path
    info: dict
    cached: bool = False

    @classmethod
    def load(cls, path: str | Path, cached: bool = False) -> "RunResult":
        """The result in `path` (not verified: see verify_run and cached_result)."""
        path = Path(path)
        info = read_result(path)
        if not isinstance(info, dict):
            raise ValueError(f"{path / 'result.json'}: not a JSON object")
        info.pop("manifest", None)
        info.pop("checksum", None)
        return cls(path, info, cached)

    def __getattr__(self, name):
        info = self.__dict__.get("info", {})
        if name in info:
            return info[name]
        raise AttributeError(name)

    def stats(self):
        import pandas as pd  # harness extra (pandas)
        p = self.path / "stats.parquet"
        return pd.read_parquet(p) if p.exists() else pd.DataFrame()

    def profiles(self):
        import pandas as pd  # harness extra (pandas)
        p = self.path / "profiles.parquet"
        return pd.read_parquet(p) if p.exists() else pd.DataFrame()

    def steps_table(self):
        import pandas as pd  # harness extra (pandas)
        p = self.path / "steps.csv"
        return pd.read_csv(p) if p.exists() else pd.DataFrame()

    def timings(self) -> dict[str, dict]:
        import pandas as pd  # harness extra (pandas)
        p = self.path / "timings.csv"
        if not p.exists():
            return {}
        return {r["phase"]: {"total_ms": r["total_ms"], "count": int(r["count"]), "mean_ms": r["mean_ms"]}
                for r in pd.read_csv(p).to_dict("records")}

    def snapshot_paths(self) -> list[Path]:
        return sorted((self.path / "snapshots").glob("step_*.npz"))

    def snapshot(self, step: int | None = None) -> dict[str, np.ndarray]:
        """A stored state (the last one when step is None), as a dict of numpy arrays."""
        paths = self.snapshot_paths()
        if step is not None:
            paths = [p for p in paths if p.name == f"step_{step:06d}.npz"]
        if not paths:
            raise FileNotFoundError(f"{self.path}: no snapshot{'' if step is None else f' at step {step}'}")
        with np.load(paths[-1]) as z:
            return {k: z[k] for k in z.files}

    def summary(self) -> dict:
        """Small JSON-able dict (what a dask task returns)."""
        return {**self.info, "path": str(self.path), "cached": self.cached}
