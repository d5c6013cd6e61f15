#!/usr/bin/env bash
# Set up (if needed) and run the test suite, with the ray and libero extras so the Ray and
# LIBERO tests run (without them they skip). Extra arguments go to pytest.
set -euo pipefail
cd "$(dirname "$0")/.."
STEPNFT_EXTRAS=test,video,ray,libero bash scripts/bootstrap.sh
export MUJOCO_GL=${MUJOCO_GL:-egl}
exec .venv/bin/python -m pytest -q "$@"
