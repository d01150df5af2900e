"""Command-line tools of dax-algos that are not the runner (benchmarks, sweeps)."""
