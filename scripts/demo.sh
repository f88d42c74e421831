#!/usr/bin/env bash
# Set up what is missing, then render the demo scene into outputs/demo/ (EXR + PNG + JSON).
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/setup.sh test
.venv/bin/torchrefract render configs/demo.yaml --out outputs/demo "$@"
