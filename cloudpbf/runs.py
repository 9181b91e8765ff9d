"""The run cache, as the studies and the CLI use it: describe a run (RunSpec), execute it (or find it
stored), read its result.  The parts: cloudpbf.store (identity and key, atomic files, lock, manifest and
quarantine, results), cloudpbf.execution (the step loop, checkpoints, resume), cloudpbf.solvers (one adapter
per solver).  save_frame (write_csv) and atomic_write_json / _text are the writers a study's outputs go
through.
"""
from cloudpbf.execution import cached_result, execute, execute_summary
from cloudpbf.solvers import SOLVERS
from cloudpbf.store.files import save_frame
from cloudpbf.store.identity import RunSpec, code_version, default_root
from cloudpbf.store.manifest import QUARANTINE, verify_run
from cloudpbf.store.result import RunResult
from cloudpbf_io.files import atomic_write_json, atomic_write_text

__all__ = ["RunSpec", "RunResult", "execute", "execute_summary", "cached_result", "verify_run", "default_root",
           "code_version", "SOLVERS", "QUARANTINE", "save_frame", "write_csv", "atomic_write_json", "atomic_write_text"]

write_csv = save_frame     # the name the studies use for their CSV outputs
