"""Benchmarks that need more than one stage (``f2l dev …``): they sit above the stages they time."""
