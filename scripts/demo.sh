#!/usr/bin/env bash
# Install zplatform into .venv and run the demo mission.
set -euo pipefail
cd "$(dirname "$0")/.."
PY=${PYTHON:-python3}
if [ ! -x .venv/bin/python ]; then
  "$PY" -m venv .venv
fi
.venv/bin/python -m pip install --quiet --upgrade pip
.venv/bin/python -m pip install --quiet -e .
.venv/bin/zplatform check configs/led_test.yaml >/dev/null
# The thesis' LED platform test: A -LAUNCH-> B -3 s-> C -LED4-> D -ABORT-> E,
# commands played by the ground node, telemetry logged to led_test.csv.
exec .venv/bin/zplatform up configs/led_test.yaml --duration 20 \
  --commands configs/led_test.commands --log led_test.csv --summary - "$@"
