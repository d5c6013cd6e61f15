#!/usr/bin/env bash
# Set up (if needed) and run the main job on the embedded default: MetaWorld demonstrations ->
# few-shot SFT -> online π-StepNFT -> evaluation, printing success before -> after per task.
# Each call writes a new run folder runs/quickstart-<time>; extra arguments go to
# `stepnft train` (e.g. --seed 1). Resume an interrupted run with
#   .venv/bin/stepnft train --resume runs/quickstart-<time>
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/bootstrap.sh
export MUJOCO_GL=${MUJOCO_GL:-egl}
exec .venv/bin/stepnft train --config configs/quickstart.yaml --run-dir "runs/quickstart-$(date +%Y%m%d-%H%M%S)" "$@"
