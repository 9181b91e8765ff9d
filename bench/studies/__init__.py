"""Studies: each builds RunSpecs, runs what the cache lacks, and writes CSVs into OUT/data."""
