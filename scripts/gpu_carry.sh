#!/usr/bin/env bash
# Build what scripts/gpu_check.sh carries to a lent GPU machine (<= 64 MiB; the machine has
# Python 3.12, torch with CUDA and transformers, and reaches no registry):
#
#     bash scripts/gpu_carry.sh [CARRY [PART]]   # default .gpucarry core
#
# PART core: what the MetaWorld checks need; PART vla: what the LeRobot checks need (the two carries
# go in two device calls: gpu_check.sh's PARTS). The limit counts the working tree too, and the
# tracked tree is now ~39 MB (26.7 MB of it saved policies in benchmarks/results): the vla carry
# (~17 MiB) fits beside it, the core carry (~43 MiB: MetaWorld's wheel is 36 MB) no longer does.
#
# CARRY/whl: wheels, for CPython 3.12 on x86-64 Linux, of stepnft's dependencies the machine
# lacks, at the versions installed in .venv (gymnasium, metaworld, mujoco, tyro, ...), and of
# LeRobot 0.6 with what it needs beyond the machine's packages, at .venv-lerobot's versions (for
# the full-size SmolVLA / π0 checks; a package still missing there shows in gpu_check's
# vla_*.log); gpu_check.sh installs them with --no-deps. CARRY/lang_cache:
# the quickstart tasks' instruction embeddings (from a quickstart run's lang_cache, if one is
# here), so no sentence encoder is needed. Prints the carry's size.
set -euo pipefail
CARRY=${1:-.gpucarry}
PART=${2:-core}
mkdir -p "$CARRY/whl" "$CARRY/lang_cache"
# The machine's image already holds torch, torchvision, numpy, matplotlib, tensorboard, pillow, peft,
# accelerate, einops, rich, pyyaml, tqdm, safetensors (the device library's KINDS.md): not carried.
MAIN="gymnasium farama-notifications metaworld mujoco glfw tyro docstring-parser typeguard shtab"
# LeRobot 0.6.1 as tested here: its transformers (5.5; the image's is newer, and transformers checks
# its tokenizers' version at import) with its tokenizers and hub client; draccus for its configs.
LEROBOT="lerobot draccus mergedeep pyyaml-include toml transformers tokenizers huggingface-hub termcolor"
pins() {  # the versions installed in a venv, as NAME==VERSION, for the names given
    local venv=$1
    shift
    "$venv/bin/python" -m pip list --format=freeze 2>/dev/null | awk -F'==' -v want=" $* " \
        'BEGIN { IGNORECASE = 1 } { n = tolower($1); gsub("_", "-", n); if (index(want, " " n " ")) print $0 }'
}
download() {
    python3 -m pip download -q --no-deps --only-binary=:all: --python-version 3.12 --implementation cp \
        --platform manylinux_2_28_x86_64 --platform manylinux_2_17_x86_64 --platform manylinux2014_x86_64 \
        --platform any -d "$CARRY/whl" "$@"
}
TYRO="tyro docstring-parser typeguard shtab"  # stepnft's command line: both parts
case $PART in
    core) download $(pins .venv $MAIN) ;;
    vla) download $(pins .venv $TYRO) $(pins .venv-lerobot $(echo $LEROBOT | tr '\n' ' ') gymnasium farama-notifications) ;;
    *) echo "gpu_carry.sh: PART is core or vla" >&2; exit 2 ;;
esac
cache=$(ls -d runs/*/lang_cache 2>/dev/null | head -n 1 || true)
[ -n "$cache" ] && cp -r "$cache"/. "$CARRY/lang_cache/"
du -sh "$CARRY"
ls "$CARRY/whl" | wc -l
