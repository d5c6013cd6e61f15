"""Tiny LeRobot VLAs (SmolVLA, π0, π0.5) fine-tuned on MetaWorld camera observations from the
CLI: demonstrations with cameras, SFT of a new tiny VLA of each model (`stepnft sft --init`), then
π-StepNFT (`stepnft train --init RUN/policy`), beside the MLP flow policy (state only) on the same
tasks, the same demonstrations and the same RL budget. A pipeline check: random, tiny VLMs, not
what a pretrained model reaches.

Run in the LeRobot environment (docs/lerobot.md):

    MUJOCO_GL=egl .venv-lerobot/bin/python benchmarks/vla_learning.py --out benchmarks/results/vla

Every step is a CLI command (printed before it runs, so the docs can quote them); the script
only chains them and gathers the run summaries into ``OUT/report.json``. Steps whose output
already exists are skipped, so a run into the same OUT resumes where it stopped.
"""

from __future__ import annotations

import argparse
import json
import os
import shlex
import subprocess
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
import provenance  # noqa: E402

os.environ.setdefault("MUJOCO_GL", "egl")


def run(argv: list, module: str = "stepnft.cli") -> float:
    """``python -m module argv`` in its own process (one at a time); returns its CPU seconds."""
    argv = [str(a) for a in argv]
    print("$", "python -m", module, shlex.join(argv), flush=True)
    start = os.times()
    subprocess.run([sys.executable, "-m", module, *argv], check=True)
    end = os.times()
    return (end.children_user - start.children_user) + (end.children_system - start.children_system)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--out", default="benchmarks/results/vla")
    parser.add_argument("--tasks", nargs="+", default=["reach-v3", "drawer-open-v3", "door-open-v3"])
    parser.add_argument("--models", nargs="+", default=["smolvla", "pi0", "pi05"], choices=["smolvla", "pi0", "pi05"],
                        help="LeRobot models to build tiny and fine-tune (π0 / π0.5 need LeRobot 0.6)")
    parser.add_argument("--camera", default="corner", help="MetaWorld camera (upright view)")
    parser.add_argument("--image-size", type=int, default=64)
    parser.add_argument("--demos", type=int, default=5, help="demonstrations per task")
    parser.add_argument("--sft-steps", type=int, default=1000, help="VLA SFT steps (the MLP takes 3000)")
    parser.add_argument("--sft-train", default="expert+state", choices=["expert", "expert+state", "vlm"],
                        help="trained parameters of each VLA, in SFT and RL (LeRobot's fine-tuning default: "
                             "expert+state; a new tiny model's state projection is random, so SFT should train it)")
    parser.add_argument("--iterations", type=int, default=8)
    parser.add_argument("--episodes", type=int, default=12, help="episodes per RL iteration")
    parser.add_argument("--eval-episodes", type=int, default=20, help="test episodes per task")
    parser.add_argument("--max-episode-steps", type=int, default=100)
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()

    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    cameras = ["--env.cameras", args.camera, "--env.image-size", args.image_size]
    env = ["--env.tasks", *args.tasks, "--env.max-episode-steps", args.max_episode_steps,
           "--env.envs-per-task", max(1, args.episodes // len(args.tasks))]
    demos = ["--demos.path", out / "demos", "--demos.episodes", args.demos]
    common = ["--seed", args.seed, "--num-threads", 1]
    rl = ["--iterations", args.iterations, "--episodes-per-iteration", args.episodes,
          "--eval.episodes", args.eval_episodes, "--eval.every", max(1, args.iterations // 2),
          "--eval.during-episodes", 10, "--algo.minibatch-size", 128]
    cpu: dict[str, float] = {}

    def step(name: str, done: Path, argv: list, module: str = "stepnft.cli") -> None:
        if not done.exists():
            t0 = time.perf_counter()
            cpu[f"{name}_cpu_s"] = run(argv, module)
            cpu[f"{name}_wall_s"] = time.perf_counter() - t0

    # Demonstrations with the camera's views (the MLP reads only their states).
    step("demos", out / "demos" / "manifest.json", ["demos", *env, *cameras, *demos])
    # A new tiny VLA of each model on an offline configuration, then SFT on the camera
    # demonstrations (the `train` run evaluates it, as its starting point).
    runs = {}
    for model in args.models:
        folder = out / f"tiny_{model}"
        step(f"{model}_new", folder / "config.json",
             ["new", "--out", folder, "--model", model, "--size", "tiny", "--state-dim", 39, "--action-dim", 4,
              "--chunk-size", 4, "--n-exec", 4, "--num-steps", 4, "--cameras", args.camera,
              "--image-size", args.image_size, "--train", args.sft_train, "--seed", args.seed],
             module="stepnft.policies.lerobot")
        step(f"{model}_sft", out / f"{model}_sft" / "summary.json",
             ["sft", "--init", folder, "--run-dir", out / f"{model}_sft", *env, *cameras, *demos, *common,
              "--sft.steps", args.sft_steps, "--sft.batch-size", 64, "--sft.lr", 1e-3, "--sft.time-law", "beta",
              "--eval.episodes", 0])
        runs[f"{model}_it{args.iterations}"] = ["--init", out / f"{model}_sft" / "policy", *cameras]
    runs[f"mlp_it{args.iterations}"] = ["--sft.steps", 3000]
    for name, flags in runs.items():
        step(name, out / name / "summary.json", ["train", "--run-dir", out / name, *flags, *env, *demos, *common, *rl])

    report_path = out / "report.json"
    report = json.loads(report_path.read_text()) if report_path.is_file() else {}
    report.setdefault("cpu_s", {}).update(cpu)
    report |= {"args": vars(args), "commit": provenance.commit(), "command": provenance.command(),
               "packages": provenance.packages((*provenance.NUMERIC_PACKAGES, "lerobot", "transformers"))}
    for name in runs:
        summary = json.loads((out / name / "summary.json").read_text())
        report[name] = {t: {k: {key: summary["tasks"][t][k][key] for key in ("success", "ci95")}
                            for k in ("before", "after", "best")} for t in args.tasks}
        report[name] |= {"average": summary["average"], "env_steps": summary["env_steps"]}
    report_path.write_text(json.dumps(report, indent=2))
    print(json.dumps(report, indent=2))


if __name__ == "__main__":
    main()
