#!/usr/bin/env bash
# Set up (if needed) and run the main job on the embedded default: MetaWorld demonstrations ->
# few-shot SFT -> online π-StepNFT -> evaluation, printing success before -> after per task.
# Extra arguments go to `stepnft train` (e.g. --seed 1, --run-dir runs/mine).
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/bootstrap.sh
export MUJOCO_GL=${MUJOCO_GL:-egl}
exec .venv/bin/stepnft train --config configs/quickstart.yaml "$@"
