"""Few-shot learning benchmark: SFT vs π-StepNFT on five MetaWorld tasks, several seeds.

One multi-task policy per seed: scripted-expert demonstrations (seeded by the run seed) ->
few-shot SFT -> π-StepNFT under a fixed env-step budget -> ODE evaluation on the fixed
initial states. Prints and writes a table (task x {SFT, π-StepNFT} success with 95 % CIs,
env steps, wall-clock) to ``--out``/learning.md and .json. A seed whose run folder already
holds ``summary.json`` is reused, so seeds can run in parallel invocations and be tabled at the end.

    .venv/bin/python benchmarks/learning.py --seeds 0 1 2
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import statistics
import time
from pathlib import Path

from stepnft.config import DEFAULT_TASKS, load_config
from stepnft.train import train


def parse_args(argv=None) -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--config", default="configs/quickstart.yaml", help="base run config (YAML); flags below override it")
    p.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2], help="one full run per seed")
    p.add_argument("--tasks", nargs="+", default=DEFAULT_TASKS, help="MetaWorld v3 tasks (one multi-task policy)")
    p.add_argument("--demos", type=int, default=None, help="demonstrations per task (default: the config's)")
    p.add_argument("--task-demos", nargs="*", default=None, metavar="TASK=N",
                   help="per-task demonstration counts, e.g. door-open-v3=1 (default: the config's)")
    p.add_argument("--env-steps", type=int, default=None, help="RL env-step budget per run (default: the config's)")
    p.add_argument("--eval-episodes", type=int, default=100, help="evaluation episodes per task (>= 100 for reported figures)")
    p.add_argument("--out", default="benchmarks/results/learning", help="folder for runs and the result table")
    return p.parse_args(argv)


def fmt(rates: list[float]) -> str:
    if len(rates) == 1:
        return f"{rates[0]:.2f}"
    return f"{statistics.mean(rates):.2f} ± {statistics.stdev(rates):.2f}"


def main(argv=None) -> dict:
    args = parse_args(argv)
    base = load_config(args.config)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    demos = base.demos
    if args.demos is not None:
        demos = dataclasses.replace(demos, episodes=args.demos)
    if args.task_demos is not None:
        demos = dataclasses.replace(demos, task_episodes={k: int(v) for k, v in (s.split("=") for s in args.task_demos)})
    runs = []
    for seed in args.seeds:
        cfg = dataclasses.replace(
            base, seed=seed, run_dir=str(out / f"seed{seed}"),
            env=dataclasses.replace(base.env, tasks=list(args.tasks)),
            demos=dataclasses.replace(demos, seed=seed, path=str(out / f"demos_seed{seed}")),
            eval=dataclasses.replace(base.eval, episodes=args.eval_episodes),
            env_step_budget=args.env_steps if args.env_steps is not None else base.env_step_budget,
        )
        done = Path(cfg.run_dir) / "summary.json"
        if done.is_file():  # finished earlier (or in a parallel invocation): reuse it
            summary = json.loads(done.read_text())
            runs.append({"seed": seed, "wall_clock_s": summary.get("wall_clock_s", float("nan")), **summary})
            continue
        start = time.perf_counter()
        summary = train(cfg)
        summary["wall_clock_s"] = time.perf_counter() - start
        done.write_text(json.dumps(summary, indent=2))
        runs.append({"seed": seed, **summary})

    lines = ["| task | SFT | π-StepNFT | per seed (SFT → π-StepNFT, 95 % CI) |", "|---|---|---|---|"]
    for task in args.tasks:
        before = [r["tasks"][task]["before"]["success"] for r in runs]
        after = [r["tasks"][task]["after"]["success"] for r in runs]
        seeds = "; ".join(
            f"s{r['seed']}: {r['tasks'][task]['before']['success']:.2f} → {r['tasks'][task]['after']['success']:.2f} "
            f"[{r['tasks'][task]['after']['ci95'][0]:.2f}, {r['tasks'][task]['after']['ci95'][1]:.2f}]" for r in runs)
        lines.append(f"| {task} | {fmt(before)} | {fmt(after)} | {seeds} |")
    avg_b = [r["average"]["before"] for r in runs]
    avg_a = [r["average"]["after"] for r in runs]
    lines.append(f"| **average** | {fmt(avg_b)} | {fmt(avg_a)} | " + "; ".join(
        f"s{r['seed']}: {r['average']['before']:.2f} → {r['average']['after']:.2f}" for r in runs) + " |")
    steps = [r["env_steps"] for r in runs]
    wall = [r["wall_clock_s"] for r in runs]
    footer = (f"\nRL env steps per run: {fmt([float(s) for s in steps])}; wall-clock per run (incl. demos, SFT, "
              f"2 evaluations of {args.eval_episodes} episodes/task): {statistics.mean(wall) / 60:.1f} min; "
              f"seeds {args.seeds}; demos/task {demos.episodes} {demos.task_episodes or ''}; config {args.config}.")
    table = "\n".join(lines) + "\n" + footer
    print(table)
    (out / "learning.md").write_text(table + "\n")
    result = {"args": vars(args), "runs": runs, "average": {"sft": avg_b, "stepnft": avg_a}}
    (out / "learning.json").write_text(json.dumps(result, indent=2))
    return result


if __name__ == "__main__":
    main()
