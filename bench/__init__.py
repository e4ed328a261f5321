"""Benchmarks of zplatform: ``python -m bench.<name> [--quick] [--json PATH]``.

The result files are described in docs/architecture.md#files.
"""
