"""Benchmarks: measurements of run time against error. Never imported by tests; nothing here asserts a time."""
