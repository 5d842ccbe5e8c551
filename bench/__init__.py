"""Benchmarks: each writes its own section of docs/PERFORMANCE.md with the machine and the date."""
