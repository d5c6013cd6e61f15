"""Can the execution suite be solved? MetaWorld's scripted experts under each held-out
execution perturbation, against the training distribution.

The experts read the full state (true object and goal positions), so they show what the
perturbations leave solvable, not what a learned policy manages. Episode e of a task starts
from seed ``--seed + e`` as in evaluation; a perturbation's episodes are those its suite would
give it (seed % 4). Prints a table and writes ``--out``/ood_experts.md and .json.

    .venv/bin/python benchmarks/ood_experts.py --episodes 40
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

from stepnft.envs import DEFAULT_TASKS
from stepnft.envs.metaworld import MetaWorld
from stepnft.envs.perturbations import Perturbations, SUITES
from stepnft.evaluate import wilson_interval


def parse_args(argv=None) -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--tasks", nargs="+", default=DEFAULT_TASKS, help="MetaWorld v3 tasks")
    p.add_argument("--episodes", type=int, default=40, help="episodes per task and setting")
    p.add_argument("--seed", type=int, default=0, help="first initial-state seed")
    p.add_argument("--max-episode-steps", type=int, default=200, help="episode cap")
    p.add_argument("--out", default="benchmarks/results/ood_experts", help="folder for the result table")
    return p.parse_args(argv)


def expert_success(sim, task: str, perturbation: str | None, seeds: list[int], max_steps: int) -> int:
    """Successes of the scripted expert from ``seeds`` under one held-out perturbation (None: none)."""
    options = {"perturbations": Perturbations((perturbation,), heldout=True)} if perturbation else {}
    env = sim.make_env(task, n_exec=1, max_episode_steps=max_steps, **options)
    expert = sim.expert(task, 0)
    wins = 0
    for seed in seeds:
        obs, _ = env.reset(seed=seed)
        done, info = False, {"success": False}
        while not done:
            action = np.clip(expert.act(obs), -1, 1).astype(np.float32)
            obs, _, terminated, truncated, info = env.step(action[None])
            done = terminated or truncated
        wins += bool(info["success"])
    env.close()
    return wins


def main(argv=None) -> dict:
    args = parse_args(argv)
    sim = MetaWorld()
    names = SUITES["execution"]
    settings = [None, *names]
    results: dict[str, dict[str, float]] = {}
    for task in args.tasks:
        results[task] = {}
        for name in settings:
            # The seeds the execution suite gives this perturbation (all seeds for the training distribution).
            seeds = [s for s in range(args.seed, args.seed + len(names) * args.episodes)
                     if name is None or names[s % len(names)] == name][: args.episodes]
            results[task][name or "ind"] = expert_success(sim, task, name, seeds, args.max_episode_steps) / len(seeds)
            print(f"{task:<16} {name or 'ind':<16} {results[task][name or 'ind']:.2f}", flush=True)
    columns = ["ind", *names]
    width = lambda p: float(np.subtract(*wilson_interval(round(p * args.episodes), args.episodes)[::-1]))  # noqa: E731
    lines = ["# Scripted experts under the execution perturbations", "",
             f"{args.episodes} episodes per task and setting (seeds from {args.seed}), episodes capped at "
             f"{args.max_episode_steps} steps; success rate (95 % CIs up to "
             f"{max(width(p) for r in results.values() for p in r.values()):.2f} wide).", "",
             "| task | " + " | ".join(columns) + " |", "|---" * (len(columns) + 1) + "|"]
    lines += [f"| {task} | " + " | ".join(f"{results[task][c]:.2f}" for c in columns) + " |" for task in args.tasks]
    lines.append("| **average** | " + " | ".join(f"{np.mean([results[t][c] for t in args.tasks]):.2f}"
                                                 for c in columns) + " |")
    text = "\n".join(lines) + "\n"
    print("\n" + text)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    (out / "ood_experts.md").write_text(text)
    (out / "ood_experts.json").write_text(json.dumps({"args": vars(args), "success": results}, indent=2))
    return results


if __name__ == "__main__":
    main()
