#!/usr/bin/env bash
# Install zplatform with its test extras into .venv and run the whole check:
# ruff, mypy and the default pytest suite (slow soaks are opt-in: -m slow).
set -euo pipefail
cd "$(dirname "$0")/.."
PY=${PYTHON:-python3}
if [ ! -x .venv/bin/python ]; then
  "$PY" -m venv .venv
fi
.venv/bin/python -m pip install --quiet --upgrade pip
.venv/bin/python -m pip install --quiet -e '.[test]'
# The console's browser test opens it in Debian's headless Chromium; install
# it where we may (root with apt), else that one test skips and says why.
if ! command -v chromium >/dev/null 2>&1 && [ "$(id -u)" = 0 ] && command -v apt-get >/dev/null; then
  (apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq chromium) \
    >/dev/null 2>&1 || echo "test.sh: could not install chromium; the browser test will skip"
fi
.venv/bin/ruff check .
.venv/bin/mypy
.venv/bin/python -m pytest -n "${ZP_TEST_WORKERS:-2}" --dist loadgroup "$@"
