"""Benchmarks that print figures (``llrs bench ...``); see docs/benchmarks.md."""
