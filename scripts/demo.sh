#!/usr/bin/env bash
# Set up everything (scripts/setup.sh: venv, ROS 2 Jazzy wheels, stellar_cal_msgs, this
# package) and run the built-in demonstration of the model-discovery loop:
#   simulate a bag with a hidden effect -> calibrate -> diagnose -> add the effect -> RMS falls.
# Arguments go to `stellar-cal demo` (e.g. --duration 300 -o my_demo).
set -euo pipefail
ROOT="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
cd "$ROOT"
VENV="${VENV:-$ROOT/.venv}"
export VENV
bash "$ROOT/scripts/setup.sh" --quiet
exec "$VENV/bin/stellar-cal" demo "$@"
