"""Success rates of the ManiSkill scripted experts (``stepnft.envs.maniskill.experts``).

Each expert plays one episode from each of ``--seeds`` seeded initial states (seeds 0, 1, ...,
ending at the first success or at ManiSkill's own episode cap for the task), as ``stepnft
demos`` plays them, without action noise. Writes ``--out``/experts.md and .json. Needs the
maniskill extra and a Vulkan device.

    .venv/bin/python benchmarks/maniskill_experts.py --seeds 20
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np

from provenance import NUMERIC_PACKAGES, command, commit, packages
from stepnft.envs import get_simulator


def parse_args(argv=None) -> argparse.Namespace:
    from stepnft.envs.maniskill import EXPERTS

    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--tasks", nargs="+", default=list(EXPERTS), help="tasks with a scripted expert")
    p.add_argument("--seeds", type=int, default=20, help="episodes per task (seeds 0, 1, ...)")
    p.add_argument("--out", default="benchmarks/results/maniskill", help="folder for experts.md and .json")
    return p.parse_args(argv)


def run_expert(sim, task: str, seeds: int) -> dict:
    from stepnft.envs.maniskill import TASKS

    cap = TASKS[task].max_episode_steps
    env = sim.make_env(task, n_exec=1, max_episode_steps=cap)
    expert = sim.expert(task, 0)
    successes, lengths, start = [], [], time.perf_counter()
    try:
        for seed in range(seeds):
            obs, _ = env.reset(seed=seed)
            done = False
            while not done:
                action = np.clip(expert.act(obs), -1.0, 1.0).astype(np.float32)
                obs, _, terminated, truncated, info = env.step(action[None])
                done = terminated or truncated
            successes.append(bool(info["success"]))
            lengths.append(info["episode_steps"])
    finally:
        env.close()
    return {"task": task, "episode_cap": cap, "success_rate": float(np.mean(successes)), "successes": successes,
            "lengths": lengths, "seconds": time.perf_counter() - start}


def main(argv=None) -> dict:
    args = parse_args(argv)
    sim = get_simulator("maniskill")
    rows = []
    for task in args.tasks:
        row = run_expert(sim, task, args.seeds)
        rows.append(row)
        won = [n for n, s in zip(row["lengths"], row["successes"]) if s]
        print(f"{task:<14} {sum(row['successes'])}/{args.seeds} successes, "
              f"{np.mean(won) if won else float('nan'):.1f} steps on average when successful", flush=True)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    summary = {"seeds": args.seeds, "rows": rows,
               "command": command(), "commit": commit(), "packages": packages(NUMERIC_PACKAGES + ("mani-skill", "sapien"))}
    (out / "experts.json").write_text(json.dumps(summary, indent=1))
    lines = ["| task | successes | mean steps of a success | episode cap | failed seeds |", "|---|---|---|---|---|"]
    for row in rows:
        won = [n for n, s in zip(row["lengths"], row["successes"]) if s]
        failed = [str(i) for i, s in enumerate(row["successes"]) if not s]
        lines.append(f"| {row['task']} | {sum(row['successes'])}/{args.seeds} | "
                     f"{np.mean(won) if won else float('nan'):.1f} | {row['episode_cap']} | {', '.join(failed) or '-'} |")
    lines.append(f"\nSeeds 0-{args.seeds - 1}, no action noise; `{summary['command']}`.")
    (out / "experts.md").write_text("\n".join(lines) + "\n")
    return summary


if __name__ == "__main__":
    main()
