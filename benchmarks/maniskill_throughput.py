"""ManiSkill3 throughput: env steps per second of one chunk env (CPU PhysX, one process), state
only per task, and with a camera rendered through the Vulkan device (lavapipe on a CPU machine).
Needs the maniskill extra and a Vulkan device.

Each setting builds one env, resets it and steps it with random actions (uniform in [-0.5, 0.5])
for ``--steps`` env steps (``--camera-steps`` with a camera, after one untimed chunk: the first
frame compiles the shaders); the table gives env steps/s of wall-clock and per CPU second of this process (less sensitive
to other load), the reset time and the build time.
The machine's load average is recorded beside the numbers: other processes on the same cores
slow every figure down.

    .venv/bin/python benchmarks/maniskill_throughput.py --steps 400 --camera-steps 60
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import time
from pathlib import Path

import numpy as np

from provenance import NUMERIC_PACKAGES, command, commit, packages
from stepnft.envs import get_simulator


def parse_args(argv=None) -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--tasks", nargs="+", default=["PickCube-v1", "PushCube-v1", "PullCube-v1", "StackCube-v1"],
                   help="tasks timed state only")
    p.add_argument("--camera-task", default="PickCube-v1", help="task timed with a camera")
    p.add_argument("--image-size", type=int, default=128, help="camera image side in pixels")
    p.add_argument("--steps", type=int, default=400, help="env steps timed per state-only setting")
    p.add_argument("--camera-steps", type=int, default=60, help="env steps timed per camera setting")
    p.add_argument("--out", default="benchmarks/results/maniskill", help="folder for throughput.md and .json")
    return p.parse_args(argv)


def time_env(task: str, options: dict, n_exec: int, steps: int) -> dict:
    t0 = time.perf_counter()
    env = get_simulator("maniskill").make_env(task, n_exec=n_exec, max_episode_steps=500, terminate_on_success=False,
                                              **options)
    built = time.perf_counter() - t0
    rng = np.random.default_rng(0)
    try:
        t0 = time.perf_counter()
        env.reset(seed=0)
        reset = time.perf_counter() - t0
        env.step(rng.uniform(-0.5, 0.5, (n_exec, 7)).astype(np.float32))  # untimed: the first frame compiles shaders
        env.reset(seed=1)
        calls = max(1, steps // n_exec)
        t0, cpu0 = time.perf_counter(), time.process_time()
        for _ in range(calls):
            env.step(rng.uniform(-0.5, 0.5, (n_exec, 7)).astype(np.float32))
        rate = calls * n_exec / (time.perf_counter() - t0)
        cpu_rate = calls * n_exec / (time.process_time() - cpu0)
    finally:
        env.close()
    return {"env_steps_per_s": rate, "env_steps_per_cpu_s": cpu_rate, "reset_s": reset, "build_s": built}


def time_raw(task: str, control_mode: str, steps: int) -> dict:
    """ManiSkill's own env without stepnft's wrapper, state only: what the controller costs
    (``pd_ee_delta_pose`` solves inverse kinematics every step, ``pd_joint_delta_pos`` does not)."""
    from stepnft.envs.maniskill.env import make_maniskill_env

    t0 = time.perf_counter()
    env = make_maniskill_env(task, obs_mode="state", control_mode=control_mode, sim_backend="cpu", num_envs=1,
                             render_backend="none")
    built = time.perf_counter() - t0
    rng = np.random.default_rng(0)
    try:
        t0 = time.perf_counter()
        env.reset(seed=0)
        reset = time.perf_counter() - t0
        actions = rng.uniform(-0.5, 0.5, (steps, *env.action_space.shape)).astype(np.float32)
        t0, cpu0 = time.perf_counter(), time.process_time()
        for action in actions:
            env.step(action)
        rate, cpu_rate = steps / (time.perf_counter() - t0), steps / (time.process_time() - cpu0)
    finally:
        env.close()
    return {"env_steps_per_s": rate, "env_steps_per_cpu_s": cpu_rate, "reset_s": reset, "build_s": built}


def main(argv=None) -> dict:
    args = parse_args(argv)
    camera = {"cameras": ["base_camera"], "image_size": args.image_size}
    settings = [(task, "state only, chunks of 4", {}, 4, args.steps) for task in args.tasks]
    settings += [(args.camera_task, f"base_camera {args.image_size} px, rendered every step", camera, 1,
                  args.camera_steps),
                 (args.camera_task, f"base_camera {args.image_size} px, once per chunk of 4", camera, 4,
                  args.camera_steps)]
    load_before = os.getloadavg()
    rows = []
    for task, name, options, n_exec, steps in settings:
        result = time_env(task, options, n_exec, steps)
        rows.append({"task": task, "setting": name, "steps": steps, **result})
        print(f"{task:<14} {name:<44} {result['env_steps_per_s']:7.1f} steps/s  "
              f"{result['env_steps_per_cpu_s']:7.1f} per CPU s  reset {result['reset_s']:.2f} s  "
              f"build {result['build_s']:.1f} s", flush=True)
    for mode in ("pd_ee_delta_pose", "pd_joint_delta_pos"):
        result = time_raw(args.tasks[0], mode, args.steps)
        name = f"ManiSkill alone, {mode}"
        rows.append({"task": args.tasks[0], "setting": name, "steps": args.steps, **result})
        print(f"{args.tasks[0]:<14} {name:<44} {result['env_steps_per_s']:7.1f} steps/s  "
              f"{result['env_steps_per_cpu_s']:7.1f} per CPU s", flush=True)
    summary = {"rows": rows, "load_average_before": load_before, "load_average_after": os.getloadavg(),
               "cpus": os.cpu_count(), "machine": platform.processor() or platform.machine(),
               "lp_num_threads": os.environ.get("LP_NUM_THREADS"),
               "command": command(), "commit": commit(), "packages": packages(NUMERIC_PACKAGES + ("mani-skill", "sapien"))}
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    (out / "throughput.json").write_text(json.dumps(summary, indent=1))
    lines = ["| task | setting | env steps/s | env steps per CPU second | reset (s) | build (s) |",
             "|---|---|---|---|---|---|"]
    lines += [f"| {r['task']} | {r['setting']} | {r['env_steps_per_s']:.1f} | {r['env_steps_per_cpu_s']:.1f} | "
              f"{r['reset_s']:.2f} | {r['build_s']:.1f} |" for r in rows]
    lines.append(f"\nOne process, CPU PhysX, random actions; {args.steps} env steps per state-only setting, "
                 f"{args.camera_steps} with the camera (lavapipe, LP_NUM_THREADS={summary['lp_num_threads']}); "
                 f"{summary['cpus']} CPUs; load average (1, 5, 15 min) before "
                 f"{tuple(round(x, 2) for x in load_before)}, after "
                 f"{tuple(round(x, 2) for x in summary['load_average_after'])}. `{summary['command']}`")
    (out / "throughput.md").write_text("\n".join(lines) + "\n")
    return summary


if __name__ == "__main__":
    main()
