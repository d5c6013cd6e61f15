"""Rollout throughput of the training collector: env steps/s with the sub-envs in this process
against the same sub-envs in worker processes, in one run.

The collector plays whole Flow-SDE waves (recording every denoising step, as training does)
with a policy the size of the main job's, on the main job's tasks and layout; the policy runs
in this process between env steps, as in training. Prints and writes
``benchmarks/results/rollout_throughput/throughput.json``.

    MUJOCO_GL=egl .venv/bin/python benchmarks/rollout_throughput.py --workers 0 2
"""

from __future__ import annotations

import argparse
import json
import os
import time
from pathlib import Path

import torch

from stepnft.algos.base import RolloutSpec
from stepnft.config import DEFAULT_TASKS, EnvConfig
from stepnft.envs import make_vec_env
from stepnft.policies.flow import FlowPolicy, FlowPolicyConfig
from stepnft.rollout.collector import Collector


def measure(workers: int, tasks: list[str], envs_per_task: int, waves: int, seed: int,
            lang_cache: str | None = None) -> dict:
    torch.manual_seed(seed)
    policy = FlowPolicy(FlowPolicyConfig())
    venv = make_vec_env(EnvConfig(tasks=tasks, envs_per_task=envs_per_task, num_workers=workers), n_exec=4, seed=seed)
    policy.processor.bind_instructions(venv.instructions, lang_cache)
    collector = Collector(venv, seed=seed)
    spec = RolloutSpec(noise_level=0.5, record_steps="all")
    try:
        collector.collect(policy, venv.num_envs, spec)  # warm-up: first resets, thread pools
        start = time.perf_counter()
        steps = sum(collector.collect(policy, venv.num_envs, spec).env_steps for _ in range(waves))
        seconds = time.perf_counter() - start
    finally:
        collector.close()
    return {"workers": workers, "env_steps": steps, "seconds": seconds, "env_steps_per_s": steps / seconds}


def main(argv=None) -> dict:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--workers", type=int, nargs="+", default=[0, 2], help="settings of env.num_workers to compare")
    p.add_argument("--tasks", nargs="+", default=DEFAULT_TASKS)
    p.add_argument("--envs-per-task", type=int, default=8)
    p.add_argument("--waves", type=int, default=4, help="timed waves per setting (after one warm-up wave)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--lang-cache", default=None, help="folder of cached instruction embeddings (default: none, encode them)")
    p.add_argument("--out", default="benchmarks/results/rollout_throughput")
    args = p.parse_args(argv)
    torch.set_num_threads(1)
    results = [measure(w, args.tasks, args.envs_per_task, args.waves, args.seed, args.lang_cache) for w in args.workers]
    base = results[0]["env_steps_per_s"]
    for r in results:
        r["speed_up"] = r["env_steps_per_s"] / base
        print(f"env.num_workers={r['workers']}: {r['env_steps_per_s']:,.0f} env steps/s ({r['speed_up']:.2f}x), "
              f"{r['env_steps']:,} steps in {r['seconds']:.1f} s")
    load = os.getloadavg()
    cores = len(os.sched_getaffinity(0))
    print(f"load average while measuring: {load[0]:.2f} (1 min); cores available: {cores}")
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    record = {"args": vars(args), "results": results, "load_average_1min": load[0], "cores": cores}
    (out / "throughput.json").write_text(json.dumps(record, indent=2))
    return record


if __name__ == "__main__":
    main()
