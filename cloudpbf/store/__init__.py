"""The run store: one simulation run is one directory, named by a hash of what decides its result.

identity (RunSpec, its key, the code version, where runs live), files (atomic table and array writers,
sha256), lock (one writer per run directory), manifest (verify a finished run, quarantine a damaged one),
result (RunResult: a finished run read back).  The step loop that fills a directory is cloudpbf.execution;
cloudpbf.runs is the face the studies and the CLI use.
"""
