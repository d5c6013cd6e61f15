#!/usr/bin/env bash
# Set up (if needed) and run the test suite, with the ray extra so the Ray tests run (without
# it they skip). The LIBERO tests need the libero extra (622 MB of assets), which CI installs:
#   STEPNFT_EXTRAS=test,video,ray,libero bash scripts/run-tests.sh
# The ManiSkill tests need the maniskill extra and a Vulkan driver (bootstrap.sh installs Mesa's
# as root with apt): STEPNFT_EXTRAS=test,video,ray,maniskill bash scripts/run-tests.sh
# Extra arguments go to pytest. Without arguments it then also runs the LeRobot adapter's tests
# in the optional LeRobot environment (.venv-lerobot, LeRobot 0.6 on Python 3.12: about 2 minutes and 5.7 GB the first
# time, docs/lerobot.md); STEPNFT_LEROBOT_TESTS=0 skips that part.
set -euo pipefail
cd "$(dirname "$0")/.."
STEPNFT_EXTRAS=${STEPNFT_EXTRAS:-test,video,ray} bash scripts/bootstrap.sh
export MUJOCO_GL=${MUJOCO_GL:-egl}
if [ $# -gt 0 ] || [ "${STEPNFT_LEROBOT_TESTS:-1}" = 0 ]; then
  exec .venv/bin/python -m pytest -q "$@"
fi
.venv/bin/python -m pytest -q
bash scripts/bootstrap.sh --lerobot
exec .venv-lerobot/bin/python -m pytest -q tests/policies/test_lerobot.py tests/policies/test_lerobot_memory.py
