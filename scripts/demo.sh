#!/usr/bin/env bash
# Install zplatform into .venv and run the demo mission.
set -euo pipefail
cd "$(dirname "$0")/.."
PY=${PYTHON:-python3}
if [ ! -x .venv/bin/python ]; then
  "$PY" -m venv .venv
fi
.venv/bin/python -m pip install -qq --upgrade pip
.venv/bin/python -m pip install -qq -e .
.venv/bin/zplatform check configs/led_test.yaml >/dev/null
# The thesis' LED platform test: A -LAUNCH-> B -3 s-> C -LED4-> D -ABORT-> E,
# commands played by the ground node, telemetry logged to led_test.csv (events
# beside it, led_test.events.jsonl), the run's figures to led_test.summary.json.
# `up` ends with its one-line summary; `zplatform ps` lists the run meanwhile.
rc=0
.venv/bin/zplatform up configs/led_test.yaml --duration 20 \
  --commands configs/led_test.commands --log led_test.csv \
  --summary led_test.summary.json "$@" || rc=$?
echo "demo: the run's figures (JSON) are in led_test.summary.json"
echo "demo: plot it with: .venv/bin/pip install -e '.[plot]' &&" \
  ".venv/bin/zplatform plot led_test.csv cn_state led_a_fb --out led_test.png"
# The command is in .venv, not on PATH: say how to reach it.
echo "demo: the zplatform command is in .venv: run 'source .venv/bin/activate'" \
  "(then 'zplatform --help'), or call it as .venv/bin/zplatform"
exit "$rc"
