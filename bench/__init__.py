"""Benchmarks of zplatform: ``python -m bench.<name> [--quick] [--json PATH]`` (DESIGN.md §7)."""
