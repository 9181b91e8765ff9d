"""asv benchmarks of cloudpbf (see docs/benchmarks.md)."""
