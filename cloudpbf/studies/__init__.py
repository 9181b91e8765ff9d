"""Studies: each builds RunSpecs, runs what the cache lacks, and writes CSVs into OUT/data.  Each study
is one module here that registers itself (cloudpbf.studies.registry); the demo, the CLI, the scale table
and the report find it there."""
