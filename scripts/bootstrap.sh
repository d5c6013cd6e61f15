#!/usr/bin/env bash
# Set up a fresh machine for stepnft: system libraries for offscreen rendering (when root),
# the virtual environment .venv at the repo root (if missing), and stepnft with its extras.
# Re-running is cheap: it reinstalls only when pyproject.toml, constraints.txt or the extras changed.
# Optional extras: --libero (LIBERO, docs/libero.md; ~700 MB), or STEPNFT_EXTRAS=libero.
set -euo pipefail
cd "$(dirname "$0")/.."
PYTHON=${PYTHON:-python3}
extras="test,video${STEPNFT_EXTRAS:+,$STEPNFT_EXTRAS}"
for arg in "$@"; do
  case "$arg" in
    --libero) extras="$extras,libero" ;;
    *) echo "bootstrap.sh: unknown option $arg (known: --libero)" >&2; exit 2 ;;
  esac
done

if [ "$(id -u)" = 0 ] && command -v apt-get >/dev/null 2>&1; then
  # Mesa's CPU EGL, for MuJoCo rendering (videos, image observations) with MUJOCO_GL=egl.
  if ! dpkg -s libegl1 libegl-mesa0 >/dev/null 2>&1; then
    apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq libegl1 libegl-mesa0
  fi
fi

[ -x .venv/bin/python ] || "$PYTHON" -m venv .venv
stamp=.venv/.stepnft-installed
want=$( (cat pyproject.toml constraints.txt; echo "$extras") | sha1sum | cut -d' ' -f1)
if [ ! -f "$stamp" ] || [ "$(cat "$stamp")" != "$want" ]; then
  .venv/bin/python -m pip install -q --upgrade pip
  # torch first, pinned: the CPU wheel. Anything resolving torch later must not pull a CUDA build.
  .venv/bin/python -m pip install -q "torch==2.13.0"
  .venv/bin/python -m pip install -q -c constraints.txt -e ".[$extras]"
  echo "$want" > "$stamp"
fi
