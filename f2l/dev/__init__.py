"""Benchmarks and developer tools (``f2l dev …``): they sit above the stages they time, so no
library module holds a benchmark."""
