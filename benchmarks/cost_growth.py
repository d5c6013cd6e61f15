"""How the cost grows with the work: one policy on 5, 10 and 50 MetaWorld tasks.

Two parts, one table each:

* **Memory, measured live.** A short ``stepnft train`` of each config (``--configs``; its own
  demonstrations and SFT, then ``--iterations`` RL iterations and small evaluations) runs in a
  subprocess while its process tree's proportional set size (PSS, from
  ``/proc/PID/smaps_rollup``: pages shared between processes are split among them, so the sum
  is the tree's real footprint) is sampled every ``--interval`` seconds: the peak of the learner
  (the main process: policy, EMA copy, optimizer, the iteration's batch and update), of the
  simulator workers together, and of the whole tree. Its ``summary.json`` adds the rollout rate
  and the updates' share of the RL wall-clock of that short run.
* **From finished learning benchmarks** (``--learning LABEL=FOLDER``: their committed
  ``learning.json``): per seed, RL env steps, wall-clock, the share of each phase (rollouts,
  updates, validation, test evaluations), the rollout rate, and the env steps until validation
  success first reached SFT + 0.10 and SFT + 0.20 (with the hours it took, in proportion to the
  run's env steps: a run folder's per-iteration clock is not committed).

Prints both tables and writes ``OUT/cost_growth.{json,md}`` with the command and commit:

    MUJOCO_GL=egl .venv/bin/python benchmarks/cost_growth.py --out benchmarks/results/cost_growth
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import yaml
from provenance import ROOT, command, commit, cpu, packages, write_results

CONFIGS = ["configs/quickstart.yaml", "configs/mt10.yaml", "configs/mt50.yaml"]
LEARNING = ["5 tasks=benchmarks/results/learning_progress", "10 tasks=benchmarks/results/mt10_stepnft",
            "50 tasks=benchmarks/results/mt50_stepnft", "5 tasks, PPO=benchmarks/results/learning_ppo",
            "10 tasks, PPO=benchmarks/results/mt10_ppo"]
GAINS = (0.10, 0.20)


def children(pid: int) -> list[int]:
    """Every descendant of ``pid`` (the simulator workers, a forkserver and its children)."""
    found = []
    try:
        tasks = os.listdir(f"/proc/{pid}/task")
    except FileNotFoundError:
        return found
    for tid in tasks:
        try:
            kids = Path(f"/proc/{pid}/task/{tid}/children").read_text().split()
        except (FileNotFoundError, ProcessLookupError):
            continue
        for kid in map(int, kids):
            found += [kid, *children(kid)]
    return found


def pss_mb(pid: int) -> float:
    """The process's proportional set size in MiB (0 once it has gone)."""
    try:
        for line in Path(f"/proc/{pid}/smaps_rollup").read_text().splitlines():
            if line.startswith("Pss:"):
                return int(line.split()[1]) / 1024
    except (FileNotFoundError, ProcessLookupError, PermissionError):
        pass
    return 0.0


def live(config: str, iterations: int, interval: float, tmp: Path) -> dict:
    """A short run of ``config`` with its process tree's memory sampled until it exits."""
    run = tmp / Path(config).stem
    cmd = [sys.executable, "-m", "stepnft.cli", "train", "--config", config, "--run-dir", str(run),
           "--demos.path", str(tmp / f"demos_{Path(config).stem}"), "--iterations", str(iterations),
           "--eval.episodes", "2", "--eval.during-episodes", "2", "--checkpoint-every", str(iterations)]
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    peaks = {"learner_MB": 0.0, "workers_MB": 0.0, "total_MB": 0.0, "workers": 0}
    start = time.perf_counter()
    proc = subprocess.Popen(cmd, cwd=ROOT, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    while proc.poll() is None:
        learner = pss_mb(proc.pid)
        kids = children(proc.pid)
        workers = sum(pss_mb(k) for k in kids)
        peaks["learner_MB"] = max(peaks["learner_MB"], learner)
        peaks["workers_MB"] = max(peaks["workers_MB"], workers)
        peaks["total_MB"] = max(peaks["total_MB"], learner + workers)
        peaks["workers"] = max(peaks["workers"], len(kids))
        time.sleep(interval)
    err = proc.stderr.read()
    if proc.returncode:
        sys.exit(f"cost_growth.py: {' '.join(cmd)} failed ({proc.returncode}): {err.strip().splitlines()[-1:]}")
    summary = json.loads((run / "summary.json").read_text())
    cfg = yaml.safe_load((run / "config.yaml").read_text())
    t = summary["time_s"]
    return {"config": config, "tasks": len(cfg["env"]["tasks"]), "envs": len(cfg["env"]["tasks"]) * cfg["env"]["envs_per_task"],
            "episodes_per_iteration": cfg["episodes_per_iteration"], "iterations": iterations,
            "rl_env_steps": summary["env_steps"], "rollout_steps_per_s": summary["env_steps"] / t["rollouts"],
            "updates_share_of_rl": t["updates"] / (t["rollouts"] + t["updates"]), "wall_s": time.perf_counter() - start,
            "command": " ".join(cmd), **peaks}


def first_reaching(curve: list, level: float) -> float | None:
    """Env steps at the first validation at or above ``level`` (None: never)."""
    return next((float(steps) for steps, value in curve if value >= level - 1e-9), None)


def from_learning(label: str, folder: Path) -> dict:
    data = json.loads((folder / "learning.json").read_text())
    seeds = []
    for run in data["runs"]:
        t, steps = run["time_s"], float(run["env_steps"])
        wall = run.get("wall_clock_s") or sum(t.values())
        curve = run["curves"]["charts/validation_success_rate"]
        row = {"seed": run["seed"], "commit": run.get("commit", data["commit"]), "env_steps": steps, "wall_s": wall,
               "shares": {k: v / wall for k, v in t.items()}, "rollout_steps_per_s": steps / t["rollouts"],
               "sft_validation": curve[0][1], "final_validation": curve[-1][1]}
        for gain in GAINS:
            at = first_reaching(curve, curve[0][1] + gain)
            row[f"steps_to_plus_{gain:.2f}"] = at
            row[f"hours_to_plus_{gain:.2f}"] = None if at is None else wall * at / steps / 3600
        seeds.append(row)
    return {"label": label, "folder": str(folder), "tasks": len(data["tasks"]), "algorithm": data["runs"][0]["algorithm"],
            "command": data["command"], "seeds": seeds}


def fmt_mean(values: list, spec: str) -> str:
    values = [v for v in values if v is not None]
    if not values:
        return "never"
    mean = statistics.mean(values)
    return format(mean, spec) + (f" ± {format(statistics.stdev(values), spec)}" if len(values) > 1 else "")


def tables(live_rows: list[dict], learned: list[dict]) -> str:
    lines = ["Memory of a short run (peak PSS; the learner holds the policy, its EMA copy, the optimizer and the "
             "iteration's batch):", "",
             "| config | tasks | envs | episodes / iteration | learner peak (MB) | workers' peak, together (MB) | "
             "tree peak (MB) | rollout env steps/s | updates' share of RL |", "|---|---|---|---|---|---|---|---|---|"]
    lines += [f"| {r['config']} | {r['tasks']} | {r['envs']} | {r['episodes_per_iteration']} | {r['learner_MB']:,.0f} | "
              f"{r['workers_MB']:,.0f} ({r['workers']} processes) | {r['total_MB']:,.0f} | "
              f"{r['rollout_steps_per_s']:,.0f} | {r['updates_share_of_rl']:.0%} |" for r in live_rows]
    lines += ["", "Finished learning benchmarks (mean ± sd over seeds; hours to a gain: in proportion to env steps):", "",
              "| run | tasks | algorithm | seeds | RL env steps (M) | wall-clock (h) | rollouts | updates | validation | "
              "test evaluations | rollout env steps/s | env steps (M) to SFT + 0.10 | h | to SFT + 0.20 | h |",
              "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for r in learned:
        s = r["seeds"]
        share = lambda k: fmt_mean([x["shares"].get(k, 0.0) * 100 for x in s], ".0f") + " %"
        steps_to = lambda g: [x[f"steps_to_plus_{g:.2f}"] for x in s]
        hours_to = lambda g: fmt_mean([x[f"hours_to_plus_{g:.2f}"] for x in s], ".2f")
        millions_to = lambda g: fmt_mean([None if n is None else n / 1e6 for n in steps_to(g)], ".2f")
        reached = lambda g: sum(n is not None for n in steps_to(g))
        lines.append(f"| {r['label']} | {r['tasks']} | {r['algorithm']} | {len(s)} | {fmt_mean([x['env_steps'] / 1e6 for x in s], '.2f')} | "
                     f"{fmt_mean([x['wall_s'] / 3600 for x in s], '.2f')} | {share('rollouts')} | {share('updates')} | "
                     f"{share('validation')} | {share('test_eval')} | {fmt_mean([x['rollout_steps_per_s'] for x in s], ',.0f')} | "
                     + " | ".join(f"{millions_to(g)} ({reached(g)}/{len(s)}) | {hours_to(g)}" for g in GAINS) + " |")
    return "\n".join(lines)


def main(argv=None) -> dict:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--configs", nargs="*", default=CONFIGS, help="configs to run briefly for the memory table")
    p.add_argument("--iterations", type=int, default=2, help="RL iterations of each short run")
    p.add_argument("--interval", type=float, default=0.2, help="seconds between memory samples")
    p.add_argument("--learning", nargs="*", default=LEARNING, metavar="LABEL=FOLDER",
                   help="finished learning benchmarks (their learning.json) for the second table")
    p.add_argument("--out", default="benchmarks/results/cost_growth")
    args = p.parse_args(argv)
    for spec in args.learning:
        if "=" not in spec or not (Path(spec.split("=", 1)[1]) / "learning.json").is_file():
            p.error(f"--learning {spec!r}: expected LABEL=FOLDER with FOLDER/learning.json")
    for config in args.configs:
        if not Path(config).is_file():
            p.error(f"--configs: {config} does not exist")
    with tempfile.TemporaryDirectory(prefix="cost_growth_") as tmp:
        live_rows = []
        for config in args.configs:
            live_rows.append(live(config, args.iterations, args.interval, Path(tmp)))
            print(json.dumps(live_rows[-1]), flush=True)
    learned = [from_learning(label, Path(folder)) for label, folder in (spec.split("=", 1) for spec in args.learning)]
    text = tables(live_rows, learned)
    record = {"command": command(), "commit": commit(), "packages": packages(), "cpu": cpu(),
              "load_average_1min": os.getloadavg()[0], "args": vars(args), "live": live_rows, "learning": learned}
    write_results(Path(args.out), "cost_growth", record, text, f"Command: `{record['command']}` (commit "
                  f"{record['commit']}; load average {record['load_average_1min']:.1f} at the end)")
    print(text)
    return record


if __name__ == "__main__":
    main()
