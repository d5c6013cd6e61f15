"""The vision suite of the no-shift runs against the 4-px-shift recipe's, paired by seed and task.

The no-shift policies' suites (50 episodes per task, eval seed 0: the episodes
benchmarks/results/compare_image_ood's suites used), for each seed S and both policies:

    MUJOCO_GL=egl stepnft eval --policy benchmarks/results/learning_image_noshift/seedS/{policy,sft_policy} \
      --suite vision --eval.episodes 50 --eval.seed 0 \
      --out benchmarks/results/learning_image_noshift/suites/{policy,sft_policy}/seedS/suites.json \
      --env.tasks door-open-v3 button-press-topdown-v3 faucet-open-v3 --env.envs-per-task 8 \
      --env.num-workers 2 --env.cameras corner --env.state-obs proprio

The shift side is compare_image_ood's SFT and π-StepNFT rows (the same recipe and seeds, its own runs:
learning_image's run folders are not kept). Prints markdown; ``> vision.md`` keeps it.

    .venv/bin/python benchmarks/results/learning_image_noshift/vision.py > benchmarks/results/learning_image_noshift/vision.md
"""
import json
import sys
from pathlib import Path

from stepnft.compare import mean_ci
from stepnft.evaluate import format_ci

ROOT = Path(__file__).resolve().parents[3]
sys.path.insert(0, str(ROOT / "benchmarks"))
from provenance import commit  # noqa: E402

TASKS = ["door-open-v3", "button-press-topdown-v3", "faucet-open-v3"]
SHIFT = ROOT / "benchmarks/results/compare_image_ood/suites"
NOSHIFT = ROOT / "benchmarks/results/learning_image_noshift/suites"


def success(path: Path, suite: str | None) -> dict[str, float]:
    data = json.loads(path.read_text())
    tasks = data["suites"][suite]["tasks"] if suite else data["tasks"]
    return {t: tasks[t]["success"] for t in TASKS}


print("| policy | no shift (seeds 0, 1, 2) | 4-px shifts (seeds 0, 1, 2) | no shift minus shifts, over (seed, task) |")
print("|---|---|---|---|")
for label, mine, theirs in [("SFT", "sft_policy", "sft"), ("π-StepNFT", "policy", "stepnft")]:
    a, b, diffs = [], [], []
    for seed in range(3):
        x = success(NOSHIFT / mine / f"seed{seed}" / "suites.json", None)
        y = success(SHIFT / theirs / f"seed{seed}" / "suites.json", "vision")
        a.append(sum(x.values()) / 3)
        b.append(sum(y.values()) / 3)
        diffs += [x[t] - y[t] for t in TASKS]
    print(f"| {label} | {sum(a) / 3:.2f} ({', '.join(f'{v:.2f}' for v in a)}) | {sum(b) / 3:.2f} "
          f"({', '.join(f'{v:.2f}' for v in b)}) | {format_ci(mean_ci(diffs, -1, 1), signed=True)} |")
print(f"\nVision suite, 50 episodes per task; the no-shift suites ran on commit 175e0ec; table written on {commit()}.")
