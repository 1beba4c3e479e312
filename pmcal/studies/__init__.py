"""Studies: computations behind the demo and the benchmarks that a user runs from the command line."""
