"""Benchmarks: each module has run(quick) -> dict of measured figures."""
