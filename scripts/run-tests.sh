#!/usr/bin/env bash
# Set up (if needed) and run the test suite, with the ray extra so the Ray tests run (without
# it they skip). The LIBERO tests need the libero extra (622 MB of assets), which CI installs:
#   STEPNFT_EXTRAS=test,video,ray,libero bash scripts/run-tests.sh
# Extra arguments go to pytest.
set -euo pipefail
cd "$(dirname "$0")/.."
STEPNFT_EXTRAS=${STEPNFT_EXTRAS:-test,video,ray} bash scripts/bootstrap.sh
export MUJOCO_GL=${MUJOCO_GL:-egl}
exec .venv/bin/python -m pytest -q "$@"
