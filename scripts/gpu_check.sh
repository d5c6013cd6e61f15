#!/usr/bin/env bash
# GPU checks for --device (docs/gpu.md), for a lent CUDA machine with python3, torch and pytest
# but none of stepnft's other dependencies: one script, each part its own step and log, none
# stopping the next. Run from the repository root:
#
#     bash scripts/gpu_check.sh CARRY
#
# CARRY holds whl/ (wheels of the missing packages: tyro, gymnasium, metaworld, mujoco, ...;
# installed with --no-deps into $SITE, default /tmp/site) and lang_cache/ (the quickstart tasks' instruction
# embeddings, so no sentence encoder is needed). Logs and results go to $OUT (default
# /tmp/gpu_check): setup.log, core_tests.log, cuda_tests.log, compute.log, compute/ and steps.txt.
# Parts, in priority order: (a) the core unit tests on the machine's CPU (GPU hidden: a check of
# its python and torch), (b) the CUDA tests of tests/test_devices.py and tests/policies/test_memory.py
# (bf16 on CUDA), (c) benchmarks/compute.py on cpu and cuda, (d) the cost table of a full-size
# SmolVLA on cuda (benchmarks/vla_compute.py; needs LeRobot 0.6: its wheel and the ones it needs
# beyond the machine's torch in CARRY/whl, else the step says what is missing), (d2) π0 at full
# size (3.5 B) in bf16 on cuda: π-StepNFT and PPO updates, expert-only, checkpointed and LoRA,
# two timed updates of 8 policy calls each after a warm-up, (e) MetaWorld camera rollouts on 16
# worker processes rendering through EGL (benchmarks/render_throughput.py). About 12 minutes in
# all; each step has its own limit.
set +e
CARRY=${1:-.gpucarry}
OUT=${OUT:-/tmp/gpu_check}
PY=${PY:-python3}
SITE=${SITE:-/tmp/site}
XDIST=${XDIST--n 8}
mkdir -p "$OUT"
export PYTHONUNBUFFERED=1 HF_HUB_OFFLINE=1 PYTHONPATH=$SITE:$PWD
: > "$OUT/steps.txt"

PARTS=${PARTS:-setup core_tests cuda_tests compute vla_compute vla_pi0 render}
# Two device calls where one carry would pass 64 MiB (scripts/gpu_carry.sh): PARTS="setup core_tests
# cuda_tests compute render" with the core carry, then PARTS="setup vla_compute vla_pi0" with the vla one.

step() {  # step NAME SECONDS COMMAND...: run with a time limit into $OUT/NAME.log, note rc and time
    local name=$1 limit=$2 start=$SECONDS
    shift 2
    case " $PARTS " in *" $name "*) ;; *) return 0 ;; esac
    echo "=== $name (at most ${limit}s)"
    timeout "$limit" "$@" > "$OUT/$name.log" 2>&1
    local rc=$?
    echo "$name rc=$rc $((SECONDS - start))s" | tee -a "$OUT/steps.txt"
    tail -n 12 "$OUT/$name.log"
}

setup() {
    nvidia-smi --query-gpu=name,memory.total,driver_version --format=csv
    $PY -c "import sys, torch; print(sys.version); print('torch', torch.__version__, 'cuda', torch.version.cuda, torch.cuda.is_available(), torch.cuda.get_device_name(0) if torch.cuda.is_available() else '')"
    $PY -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade --target "$SITE" "$CARRY"/whl/*.whl
    $PY -c "import stepnft, tyro; print('stepnft from', stepnft.__file__)"
    $PY -c "import gymnasium, metaworld, mujoco" || echo "no MetaWorld here (the vla carry)"
}

CORE_TESTS=${CORE_TESTS:-"tests/test_sampling.py tests/test_losses.py tests/test_batch.py tests/test_ema.py tests/algos
tests/envs/test_bandit.py tests/test_demo_bandit.py tests/test_baselines_bandit.py tests/test_distributed.py
tests/rollout/test_collector.py tests/test_devices.py"}

export -f setup
export CARRY PY SITE PARTS
step setup 60 bash -c setup
# (a) on the machine's CPU: the GPU hidden, so the CUDA tests skip and --device cuda is refused.
step core_tests 120 env CUDA_VISIBLE_DEVICES= $PY -m pytest -q -p no:cacheprovider $XDIST $CORE_TESTS
# (b) on the GPU: SFT, rollout, updates and checkpoints against the CPU, a bandit run, bf16 under autocast.
step cuda_tests 100 $PY -m pytest -q -p no:cacheprovider -rs tests/test_devices.py tests/policies/test_memory.py
# (c) throughput of the quickstart policy (MetaWorld tasks, instructions from the cache) on cpu and cuda.
step compute 150 $PY benchmarks/compute.py --device cpu,cuda --algos stepnft,ppo,grpo --calls 1000 --episodes 20 \
    --repeats 3 --rollout-episodes 40 --sample-sizes 1,8,64,512,4096 --lang-cache "$CARRY/lang_cache" --out "$OUT/compute"
rm -f "$OUT/compute/compute.md"  # the table is in compute.log (8 files come back)
# (d) a full-size SmolVLA (random weights, offline configuration): update cost per algorithm and precision.
step vla_compute 200 $PY benchmarks/vla_compute.py --device cuda --calls 8 --reps 2 --sample-calls 8 --threads 4 \
    --out "$OUT/vla_compute"
# (d2) π0 at full size in bf16 (random weights, offline configuration): π-StepNFT and PPO updates.
step vla_pi0 300 $PY benchmarks/vla_compute.py --model pi0 --device cuda --precisions bf16 --algos stepnft ppo \
    --calls 8 --reps 2 --sample-calls 8 --threads 8 --out "$OUT/vla_compute_pi0"
# (e) the camera loop's simulator side on 16 processes, rendering through the GPU's EGL.
step render 120 env MUJOCO_GL=egl $PY benchmarks/render_throughput.py --workers 16 --envs-per-task 8 --seconds 20 \
    --out "$OUT/render"
cat "$OUT/steps.txt"
