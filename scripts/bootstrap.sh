#!/usr/bin/env bash
# Set up a fresh machine for stepnft: system libraries for offscreen rendering (when root),
# the virtual environment .venv at the repo root (if missing), and stepnft with its extras.
# Re-running is cheap: it reinstalls only when pyproject.toml or constraints.txt changed.
# Options:
#   --libero    adds the LIBERO extra (docs/libero.md; 622 MB of assets), as STEPNFT_EXTRAS=...,libero does.
#   --maniskill adds the ManiSkill3 extra (docs/maniskill.md) and, when root with apt, a Vulkan driver:
#               SAPIEN needs one even without cameras; on Debian 12 Mesa's lavapipe 25 from bookworm-backports.
#   --lerobot   also the optional LeRobot environment .venv-lerobot (SmolVLA, π0, π0.5; docs/lerobot.md):
#               LeRobot 0.6 on Python 3.12 (LeRobot 0.6 needs >= 3.12: python3.12 on PATH, a
#               pyenv 3.12, or LEROBOT_PYTHON=/path/to/python3.12), torch 2.11.0 + torchvision
#               0.26.0 + lerobot[pi,smolvla] 0.6.1, pinned by constraints-lerobot.txt, with stepnft
#               installed editable; about 2 minutes and 5.7 GB (LeRobot's policies import
#               torchvision, which has no wheel for .venv's CPU torch). An environment made for
#               an older LeRobot on an older Python is made anew.
set -euo pipefail
cd "$(dirname "$0")/.."
PYTHON=${PYTHON:-python3}
EXTRAS=${STEPNFT_EXTRAS:-test,video,datasets}
LEROBOT=0
MANISKILL=0
for arg in "$@"; do
  case "$arg" in
    --libero) EXTRAS="$EXTRAS,libero" ;;
    --lerobot) LEROBOT=1 ;;
    --maniskill) EXTRAS="$EXTRAS,maniskill"; MANISKILL=1 ;;
    *) echo "bootstrap.sh: unknown option $arg (known: --libero, --lerobot, --maniskill)" >&2; exit 2 ;;
  esac
done
case ",$EXTRAS," in *,maniskill,*) MANISKILL=1 ;; esac  # STEPNFT_EXTRAS=...,maniskill: its driver too

if [ "$(id -u)" = 0 ] && command -v apt-get >/dev/null 2>&1; then
  # Mesa's CPU EGL, for MuJoCo rendering (videos, image observations) with MUJOCO_GL=egl.
  if ! dpkg -s libegl1 libegl-mesa0 >/dev/null 2>&1; then
    apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq libegl1 libegl-mesa0
  fi
  if [ "$MANISKILL" = 1 ]; then
    # SAPIEN's Vulkan device on a CPU machine: Mesa's lavapipe. Debian 12's (Mesa 22) lacks a
    # feature SAPIEN needs; bookworm-backports has Mesa 25. Only the Vulkan drivers (and the
    # libdrm they need) come from backports: the EGL Mesa that renders MuJoCo stays as it was.
    codename=$(. /etc/os-release && echo "${VERSION_CODENAME:-}")
    have=$(dpkg-query -W -f='${Version}' mesa-vulkan-drivers 2>/dev/null || true)
    major=${have%%.*}
    if [ "$codename" = bookworm ] && [ "${major:-0}" -lt 25 ]; then
      if ! grep -rqs bookworm-backports /etc/apt/sources.list /etc/apt/sources.list.d/; then
        # The Debian mirror this machine already uses (deb822 .sources, else a sources.list line).
        mirror=$(sed -nE 's/^URIs: *([^ ]+).*/\1/p' /etc/apt/sources.list.d/*.sources 2>/dev/null | grep -v security | head -n 1 || true)
        [ -n "$mirror" ] || mirror=$(awk '$1 == "deb" && $2 !~ /^\[/ && $2 !~ /security/ { print $2; exit }' /etc/apt/sources.list 2>/dev/null || true)
        if [ -z "$mirror" ]; then
          echo "bootstrap.sh: --maniskill: no Debian mirror found in /etc/apt to add bookworm-backports from; add it by hand and install mesa-vulkan-drivers/bookworm-backports" >&2
          exit 2
        fi
        echo "deb $mirror bookworm-backports main" > /etc/apt/sources.list.d/bookworm-backports.list
      fi
      apt-get update -qq
      DEBIAN_FRONTEND=noninteractive apt-get install -y -qq libvulkan1 mesa-vulkan-drivers/bookworm-backports
    elif [ -z "$have" ]; then
      apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq libvulkan1 mesa-vulkan-drivers
    fi
  fi
fi

[ -x .venv/bin/python ] || "$PYTHON" -m venv .venv
# Extras to install, comma-separated (scripts/run-tests.sh adds ray and libero, for their tests).
stamp=.venv/.stepnft-installed  # "<hash of pyproject + constraints> <extras installed>"
want=$(cat pyproject.toml constraints.txt | sha1sum | cut -d' ' -f1)
have=$(cat "$stamp" 2>/dev/null || true)
installed=$([ "${have%% *}" = "$want" ] && echo "${have#* }" || true)
extras=$installed
for extra in ${EXTRAS//,/ }; do
  case ",$installed," in *",$extra,"*) ;; *) extras=${extras:+$extras,}$extra ;; esac
done
if [ "$extras" != "$installed" ]; then
  .venv/bin/python -m pip install -q --upgrade pip
  # torch first, pinned: the CPU wheel. Anything resolving torch later must not pull a CUDA build.
  .venv/bin/python -m pip install -q "torch==2.13.0"
  .venv/bin/python -m pip install -q -c constraints.txt -e ".[$extras]"
  echo "$want $extras" > "$stamp"
fi

if [ "$LEROBOT" = 1 ]; then
  # LeRobot 0.6 needs Python >= 3.12: LEROBOT_PYTHON, else python3.12 / python3.13 on PATH, else pyenv's newest 3.12.
  is_312() { "$1" -c 'import sys; raise SystemExit(sys.version_info < (3, 12))' 2>/dev/null; }
  LEROBOT_PY=${LEROBOT_PYTHON:-}
  if [ -z "$LEROBOT_PY" ]; then
    for candidate in python3.12 python3.13 "$PYTHON"; do
      if command -v "$candidate" >/dev/null 2>&1 && is_312 "$(command -v "$candidate")"; then
        LEROBOT_PY=$(command -v "$candidate"); break
      fi
    done
  fi
  if [ -z "$LEROBOT_PY" ] && command -v pyenv >/dev/null 2>&1; then
    version=$(pyenv versions --bare 2>/dev/null | grep -E '^3\.12\.[0-9]+$' | sort -V | tail -n 1 || true)
    [ -n "$version" ] && LEROBOT_PY="$(pyenv root)/versions/$version/bin/python"
  fi
  if [ -z "$LEROBOT_PY" ] || ! is_312 "$LEROBOT_PY"; then
    echo "bootstrap.sh: the LeRobot environment (LeRobot 0.6) needs Python >= 3.12 and none was found${LEROBOT_PY:+ ($LEROBOT_PY is older)}: install one (pyenv install 3.12, or your system's python3.12) or name it with LEROBOT_PYTHON=/path/to/python3.12" >&2
    exit 2
  fi
  if [ -x .venv-lerobot/bin/python ] && ! is_312 .venv-lerobot/bin/python; then
    rm -rf .venv-lerobot  # made for LeRobot 0.4 on an older Python
  fi
  [ -x .venv-lerobot/bin/python ] || "$LEROBOT_PY" -m venv .venv-lerobot
  stamp=.venv-lerobot/.stepnft-installed
  want=$(cat pyproject.toml constraints-lerobot.txt | sha1sum | cut -d' ' -f1)
  if [ ! -f "$stamp" ] || [ "$(cat "$stamp")" != "$want" ]; then
    # LeRobot's torch is PyPI's CUDA build (its nvidia libraries are most of the 5.7 GB): say so
    # before pip fills the disk halfway through.
    free_gb=$(df -Pk . | awk 'NR == 2 { print int($4 / 1048576) }')
    if [ ! -f "$stamp" ] && [ "$free_gb" -lt 8 ]; then
      echo "bootstrap.sh: the LeRobot environment needs about 8 GB free (5.7 GB installed plus downloads), $free_gb GB are free here; free some disk (scripts/run-tests.sh skips this part with STEPNFT_LEROBOT_TESTS=0)" >&2
      exit 2
    fi
    .venv-lerobot/bin/python -m pip install -q --upgrade pip
    .venv-lerobot/bin/python -m pip install -q -c constraints-lerobot.txt "torch" "torchvision"
    .venv-lerobot/bin/python -m pip install -q -c constraints-lerobot.txt "lerobot[pi,smolvla]" "peft" -e ".[test]"
    echo "$want" > "$stamp"
  fi
fi
