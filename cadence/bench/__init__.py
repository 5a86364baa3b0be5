"""Benchmarks behind `cadence bench …`: each prints its figures and, where a baseline exists, the ratio
to it measured in the same run (the machines are shared and noisy; absolute times do not compare)."""
