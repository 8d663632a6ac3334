"""Experiments run by make targets: sweeps over seeds and grids, benchmarks and the truth-start
tables."""
