"""Benchmarks: the figures in ``docs/benchmarks.md``, each behind ``llrs bench <name>`` (``bench.cli``).

Not part of serving: the server never imports this package. Benchmarks use the project's public functions
only, so a change inside a module shows up here as a changed figure, never as a broken import.
"""
