"""Benchmarks of zplatform: ``python -m bench.<name> [--quick] [--json PATH]``.

The result files are described in docs/architecture.md#files.

A benchmark uses the platform's public API only. To time a step inside the
nodes it installs a tracer (:func:`zplatform.trace.install`) that receives the
platform's named trace points (``sync.issued``, ``dn.serve``, ``tm.put``, ...;
the list is :mod:`zplatform.trace`'s doc), never a stand-in patched into a
private attribute: ``tests/unit/test_bench_private.py`` fails on any private
zplatform name read, imported or patched here.
"""
