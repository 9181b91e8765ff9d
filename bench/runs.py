"""The run cache, as the studies and the CLI use it: describe a run (RunSpec), execute it (or find it
stored), read its result.  The parts: bench.store (identity and key, atomic files, lock, manifest and
quarantine, results), bench.execution (the step loop, checkpoints, resume), bench.solvers (one adapter
per solver).  save_frame (write_csv) and atomic_write_json / _text are the writers a study's outputs go
through.
"""
from bench.execution import cached_result, execute, execute_summary
from bench.solvers import SOLVERS
from bench.store.files import save_frame
from bench.store.identity import RunSpec, code_version, default_root
from bench.store.manifest import QUARANTINE, verify_run
from bench.store.result import RunResult
from cloudpbf_io.files import atomic_write_json, atomic_write_text

__all__ = ["RunSpec", "RunResult", "execute", "execute_summary", "cached_result", "verify_run", "default_root",
           "code_version", "SOLVERS", "QUARANTINE", "save_frame", "write_csv", "atomic_write_json", "atomic_write_text"]

write_csv = save_frame     # the name the studies use for their CSV outputs
