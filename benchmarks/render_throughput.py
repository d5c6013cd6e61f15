"""Simulator throughput with camera observations against state only, in one run.

Plays random-action episodes of MetaWorld chunk envs (the tasks' vector env, as training
does) for ``--seconds`` per setting and counts env steps per second of wall-clock:

- ``state``: state observations only;
- ``image, render every step``: one render per env step (chunks of 1: the per-step rate);
- ``image, chunks of N``: one render per policy call, i.e. per chunk of ``--n-exec`` steps (what
  camera policies do);
- each of those with ``--workers`` worker processes (rendering in parallel, one per core).

The rendering share is the time the envs spent rendering over the time they spent stepping
(per worker). Prints a table and writes ``--out``/render_throughput.md and .json. Numbers
depend on the machine: run it alone on a quiet one.

    MUJOCO_GL=egl .venv/bin/python benchmarks/render_throughput.py
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import time
from pathlib import Path

import numpy as np

from provenance import command, commit, cpu, packages

from stepnft.envs import DEFAULT_TASKS
from stepnft.envs.metaworld import make_metaworld_vec_env


def parse_args(argv=None) -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--tasks", nargs="+", default=DEFAULT_TASKS, help="MetaWorld v3 tasks")
    p.add_argument("--envs-per-task", type=int, default=2, help="sub-envs per task")
    p.add_argument("--cameras", nargs="+", default=["corner"], help="observation cameras")
    p.add_argument("--image-size", type=int, default=64, help="image side in pixels")
    p.add_argument("--n-exec", type=int, default=4, help="env steps per policy call")
    p.add_argument("--workers", type=int, default=2, help="worker processes of the parallel settings (0: skip them)")
    p.add_argument("--seconds", type=float, default=30.0, help="wall-clock per setting")
    p.add_argument("--max-episode-steps", type=int, default=200, help="episode cap")
    p.add_argument("--out", default="benchmarks/results/render_throughput", help="folder for the result table")
    return p.parse_args(argv)


def measure(args, n_exec: int, cameras: list[str], workers: int) -> dict:
    """Env steps per second of random-action episodes, and the share of env time spent rendering."""
    options = {"cameras": cameras, "image_size": args.image_size} if cameras else {}
    venv = make_metaworld_vec_env(args.tasks, args.envs_per_task, n_exec, args.max_episode_steps, seed=0,
                                  num_workers=workers, **options)
    rng = np.random.default_rng(0)
    try:
        venv.reset(seed=list(range(venv.num_envs)))
        render_before = float(np.sum(venv.get_attr("render_seconds")))  # the first frames set up GL
        steps, start = 0, time.perf_counter()
        done = np.zeros(venv.num_envs, dtype=bool)
        while time.perf_counter() - start < args.seconds:
            if done.all():
                venv.reset()
                done[:] = False
            actions = rng.uniform(-1, 1, (venv.num_envs, n_exec, 4)).astype(np.float32)
            _, _, terminated, truncated, info = venv.step(actions)
            steps += int(np.sum(info["steps"]))
            done |= np.asarray(terminated) | np.asarray(truncated)
        wall = time.perf_counter() - start
        render = float(np.sum(venv.get_attr("render_seconds"))) - render_before
    finally:
        venv.close()
    return {"env_steps_per_s": steps / wall, "env_steps": steps, "seconds": wall,
            "render_share": render / (wall * max(workers, 1)) if cameras else 0.0}


def main(argv=None) -> dict:
    args = parse_args(argv)
    os.environ.setdefault("MUJOCO_GL", "egl")
    settings = [("state", args.n_exec, []), ("image, render every step", 1, args.cameras),
                (f"image, chunks of {args.n_exec}", args.n_exec, args.cameras)]
    rows = []
    for workers in [0] + ([args.workers] if args.workers else []):
        for name, n_exec, cameras in settings:
            result = measure(args, n_exec, cameras, workers)
            rows.append({"setting": name, "workers": workers, **result})
            print(f"{name:<28} workers={workers}  {result['env_steps_per_s']:8.1f} env steps/s  "
                  f"rendering {100 * result['render_share']:4.1f} % of env time", flush=True)
    header = ["| setting | processes | env steps/s | rendering share |", "|---|---|---|---|"]
    table = header + [f"| {r['setting']} | {max(r['workers'], 1)} | {r['env_steps_per_s']:.0f} | "
                      f"{100 * r['render_share']:.0f} % |" for r in rows]
    per_step = {r["workers"]: r["env_steps_per_s"] for r in rows if r["setting"].endswith("every step")}
    chunked = {r["workers"]: r["env_steps_per_s"] for r in rows if r["setting"].startswith("image, chunks")}
    gains = [f"one render per chunk of {args.n_exec}: {chunked[w] / per_step[w]:.1f}x the per-step rate "
             f"({max(w, 1)} process{'es' if w > 1 else ''})" for w in per_step]
    context = (f"{len(args.tasks)} tasks x {args.envs_per_task} envs, cameras {args.cameras} at {args.image_size} px, "
               f"random actions, {args.seconds:.0f} s per setting; {platform.processor() or platform.machine()}, "
               f"{os.cpu_count()} CPUs, MUJOCO_GL={os.environ.get('MUJOCO_GL')}")
    load = os.getloadavg()
    record = {"command": command(), "commit": commit(), "packages": packages(), "cpu": cpu(),
              "load_average_after": load, "args": vars(args), "rows": rows}
    context += (f"; {record['cpu']['model']}, load average {load[0]:.2f} when it ended.\n\n"
                f"Command: `{record['command']}` (commit {record['commit']}).")
    text = "\n".join(["# Render throughput", "", context, "", *table, "", *[f"- {g}" for g in gains], ""])
    print("\n" + text)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    (out / "render_throughput.md").write_text(text)
    (out / "render_throughput.json").write_text(json.dumps(record, indent=2))
    return {"rows": rows}


if __name__ == "__main__":
    main()
