"""The real loop's speed against the simulator alone, on a finished run's own settings.

For each policy of the run (its SFT start ``sft_policy/`` and its trained ``policy/``) and each
worker count, this plays what the run plays: training iterations (the run's task allocation,
episodes per iteration, Flow-SDE noise and recorded denoising steps; early termination on) and
an evaluation (ODE, fixed initial states), through the collector and the run's vector env. Every
episode's reset seed and the chunks of actions it stepped are taken from the recorded batch;
then exactly that simulator work is replayed in as many plain processes as there were workers,
each stepping its share of the episodes (split evenly by env steps) with no policy and no
pipes. The ratio of the two wall-clocks is the loop's efficiency: 1.0 means the loop costs
nothing beyond the simulator.

For an ``env.name: gym`` run the same work is replayed a third time on the user's Gymnasium env
itself (reset with the same seeds, stepped with the same actions in its own units): the loop
against the raw env's stepping rate, the chunk env's own cost included.

Each setting is measured in ``--repeats`` turns (the loop, then its replay), and the median ratio
counts: the machine's slow spells fall on both sides of a turn alike. Prints a table and writes
``OUT/loop_throughput.{json,md,png}`` with the command and commit.
The run's ``summary.json`` phase times (demonstrations, SFT, rollouts, updates, validation, test
evaluation) are copied into the table when the run recorded them.

    MUJOCO_GL=egl .venv/bin/python benchmarks/loop_throughput.py --run runs/quickstart-X
    MUJOCO_GL=egl .venv/bin/python benchmarks/loop_throughput.py --run runs/image-X --out benchmarks/results/loop_throughput_image
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import multiprocessing
import os
import sys
import time
from pathlib import Path

import numpy as np
import torch
from provenance import command, commit, cpu, packages

from stepnft.algos.base import make_algorithm
from stepnft.config import load_config
from stepnft.envs import env_options, make_vec_env, simulator_for
from stepnft.policies.base import load_policy
from stepnft.rollout.allocation import TaskAllocator
from stepnft.rollout.collector import Collector
from stepnft.rollout.plan import EpisodePlan, RolloutSpec


def episode_ops(batch, policy, num_tasks: int) -> list[tuple[int, int, list[np.ndarray], list[int]]]:
    """What the simulator did for each episode of a recorded batch: its task, reset seed, the
    action chunks it stepped (the policy's executed positions, as the collector sent them) and
    how many steps of each chunk ran (fewer in the chunk the episode ended inside)."""
    n_exec = policy.config.n_exec
    chunks = policy.env_actions(batch.actions[:, :n_exec]).clamp(-1.0, 1.0).numpy()
    executed = batch.mask[:, :n_exec].sum(dim=1).tolist()
    calls, steps = [[] for _ in range(batch.num_episodes)], [[] for _ in range(batch.num_episodes)]
    for c, e in enumerate(batch.episode.tolist()):
        calls[e].append(chunks[c])
        steps[e].append(int(executed[c]))
    return [(int(batch.episode_task[e]), int(batch.episode_seed[e]), calls[e], steps[e])
            for e in range(batch.num_episodes)]


def play(cfg, run: Path, which: str, workers: int, iterations: int, eval_episodes: int) -> dict:
    """The loop's wall-clock for ``iterations`` training collections and one evaluation of
    ``which`` policy with ``workers`` simulator processes; and each episode's simulator work.
    The evaluation plays the fixed plan of ``evaluate_policy`` with its one recorded step per
    call (the replay needs the actions; recording costs the loop a little)."""
    policy = load_policy(run / which)
    env_cfg = dataclasses.replace(cfg.env, num_workers=workers)
    venv = make_vec_env(env_cfg, policy.config.n_exec, cfg.seed)
    policy.processor.bind_instructions(venv.instruction_variants, run / "lang_cache")
    collector = Collector(venv, seed=cfg.seed)
    allocator = TaskAllocator(len(venv.tasks), cfg.task_allocation, cfg.allocation_floor)
    summary = json.loads((run / "summary.json").read_text())
    start = summary["tasks"]
    allocator.success[:] = [start[t]["before" if which == "sft_policy" else "after"]["success"] for t in venv.tasks]
    spec = make_algorithm(cfg.algo, policy, cfg.iterations, torch.Generator()).rollout
    tasks = len(venv.tasks)
    try:
        collector.play(policy, collector.plan(tasks, spec), spec.noise_level)  # warm-up: first resets
        t0 = time.perf_counter()
        train = []
        for _ in range(iterations):
            batch = collector.collect(policy, cfg.episodes_per_iteration, spec,
                                      allocator.allocate(cfg.episodes_per_iteration, spec.group_size))
            allocator.update(batch)
            train.append(batch)
        t1 = time.perf_counter()
        evaluation = collector.play(policy, EpisodePlan.fixed(tasks, eval_episodes, cfg.eval.seed), 0.0,
                                    record=RolloutSpec(0.0))
        t2 = time.perf_counter()
    finally:
        collector.close()
    return {"train": {"seconds": t1 - t0, "env_steps": sum(b.env_steps for b in train),
                      "episodes": [op for b in train for op in episode_ops(b, policy, tasks)]},
            "eval": {"seconds": t2 - t1, "env_steps": evaluation.env_steps,
                     "episodes": episode_ops(evaluation, policy, tasks)}}


def _replay_part(args) -> tuple[float, int]:
    env_cfg, n_exec, part, barrier, raw = args
    tasks = {task for task, *_ in part}
    if raw:  # the user's Gymnasium env itself (gymnasium.make as the chunk env calls it) and its action map
        from stepnft.envs.gym import ActionMap, GymSpec, make_gym_env

        spec = GymSpec.from_config(env_cfg)
        ids = {task: spec.env_id(env_cfg.tasks[task]) for task in tasks}
        envs = {task: make_gym_env(ids[task], dict(spec.make_kwargs), env_cfg.max_episode_steps) for task in tasks}
        actions = {task: ActionMap(env.action_space) for task, env in envs.items()}
    else:
        sim = simulator_for(env_cfg)
        envs = {task: sim.make_env(env_cfg.tasks[task], n_exec=n_exec, max_episode_steps=env_cfg.max_episode_steps,
                                   terminate_on_success=env_cfg.terminate_on_success, **env_options(env_cfg))
                for task in tasks}
    barrier.wait()
    start, steps = time.perf_counter(), 0
    for task, seed, chunks, executed in part:
        env = envs[task]
        if raw:  # stepped with the same actions in its own units
            env.reset(seed=seed)
            for chunk, n in zip(chunks, executed):
                for action in chunk[:n]:
                    env.step(actions[task].to_env(action))
                steps += n
            continue
        env.reset(seed=seed)
        for chunk in chunks:
            steps += env.step(chunk)[4]["steps"]
    seconds = time.perf_counter() - start
    for env in envs.values():
        env.close()
    return seconds, steps


def replay(cfg, n_exec: int, episodes: list, processes: int, raw: bool = False) -> dict:
    """The same simulator work in ``processes`` plain processes (episodes split evenly by steps);
    ``raw``: through the Gymnasium env an ``env.name: gym`` chunk env wraps, not the chunk env."""
    parts, loads = [[] for _ in range(processes)], [0] * processes
    for episode in sorted(episodes, key=lambda e: -len(e[2])):
        w = int(np.argmin(loads))
        parts[w].append(episode)
        loads[w] += len(episode[2])
    context = multiprocessing.get_context("forkserver")
    with context.Manager() as manager:
        barrier = manager.Barrier(processes)
        with context.Pool(processes) as pool:
            results = pool.map(_replay_part, [(cfg.env, n_exec, part, barrier, raw) for part in parts])
    return {"seconds": max(s for s, _ in results), "env_steps": sum(n for _, n in results)}


def measure(cfg, run: Path, which: str, workers: int, args) -> list[dict]:
    """``args.repeats`` turns of (the loop, then the same simulator work alone) for one policy
    and worker count; the median ratio of each part (training, evaluation) over the turns, so
    that a slow spell of a shared machine falls on both sides of a turn alike. An ``env.name:
    gym`` run is replayed a second time on the raw Gymnasium env (``raw_`` keys)."""
    n_exec = load_policy(run / which).config.n_exec
    modes = {"": False, "raw_": True} if cfg.env.name == "gym" else {"": False}
    turns: dict[str, list[dict]] = {"train": [], "eval": []}
    for _ in range(args.repeats):
        loop = play(cfg, run, which, workers, args.iterations, args.eval_episodes)
        for part in turns:
            turn = {"env_steps": loop[part]["env_steps"], "loop_s": loop[part]["seconds"]}
            for prefix, raw in modes.items():
                sim = replay(cfg, n_exec, loop[part]["episodes"], max(1, workers), raw=raw)
                assert sim["env_steps"] == loop[part]["env_steps"], (prefix, sim["env_steps"], loop[part]["env_steps"])
                turn |= {f"{prefix or 'simulator_'}s": sim["seconds"], f"{prefix}ratio": sim["seconds"] / loop[part]["seconds"]}
            turns[part].append(turn)
    rows = []
    for part, measured in turns.items():
        ratios = [m["ratio"] for m in measured]
        middle = measured[int(np.argsort(ratios)[len(ratios) // 2])]
        row = {"policy": which, "workers": workers, "part": part, "env_steps": middle["env_steps"],
               "loop_steps_per_s": middle["env_steps"] / middle["loop_s"]}
        for prefix in modes:  # "": the chunk env's simulator alone; "raw_": the user's Gymnasium env alone
            name = prefix or "simulator_"
            row |= {f"{name}steps_per_s": middle["env_steps"] / middle[f"{name}s"],
                    f"{prefix}ratio": float(np.median([m[f"{prefix}ratio"] for m in measured])),
                    f"{prefix}ratios": [m[f"{prefix}ratio"] for m in measured]}
        rows.append(row)
        print(f"{which:<11} workers={workers} {part:<5}: loop {row['loop_steps_per_s']:7,.0f} env steps/s, "
              f"simulator alone {row['simulator_steps_per_s']:7,.0f}: ratio {row['ratio']:.2f} "
              f"(turns: {', '.join(f'{r:.2f}' for r in ratios)})"
              + (f"; the Gymnasium env alone {row['raw_steps_per_s']:7,.0f}: ratio {row['raw_ratio']:.2f}"
                 if "raw_ratio" in row else ""), flush=True)
    return rows


def main(argv=None) -> dict:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--run", required=True, help="a finished `stepnft train` run folder (its config and policies)")
    p.add_argument("--policies", nargs="+", default=["sft_policy", "policy"], help="policy folders of the run")
    p.add_argument("--workers", type=int, nargs="+", default=[1, 2], help="simulator worker processes (env.num_workers)")
    p.add_argument("--iterations", type=int, default=2, help="training collections per setting")
    p.add_argument("--eval-episodes", type=int, default=20, help="evaluation episodes per task per setting")
    p.add_argument("--repeats", type=int, default=3, help="turns of (loop, simulator alone) per setting; the median counts")
    p.add_argument("--lanes", type=int, default=None,
                   help="measure with this many lanes instead of the package's (1: no overlap of inference and "
                        "simulation); patches stepnft.envs.base.LANES for the measurement")
    p.add_argument("--envs-per-task", type=int, default=None, help="sub-envs per task instead of the run's")
    p.add_argument("--out", default="benchmarks/results/loop_throughput")
    args = p.parse_args(argv)
    if args.lanes is not None:
        import stepnft.envs.base

        stepnft.envs.base.LANES = args.lanes
    torch.set_num_threads(1)
    run = Path(args.run)
    cfg = load_config(run / "config.yaml")
    if args.envs_per_task is not None:
        cfg = dataclasses.replace(cfg, env=dataclasses.replace(cfg.env, envs_per_task=args.envs_per_task))
    rows = []
    for which in args.policies:
        for workers in args.workers:
            rows += measure(cfg, run, which, workers, args)
    summary = json.loads((run / "summary.json").read_text())
    from stepnft.envs import base

    record = {"command": command(), "commit": commit(), "packages": packages(), "cpu": cpu(), "args": vars(args),
              "lanes": base.LANES, "envs_per_task": cfg.env.envs_per_task,
              "cameras": list(cfg.env.cameras), "rows": rows, "run_time_s": summary.get("time_s"),
              "run_env_steps": summary.get("env_steps"), "load_average_1min": os.getloadavg()[0],
              "cores": len(os.sched_getaffinity(0))}
    write_report(record, Path(args.out))
    return record


def write_report(record: dict, out: Path) -> None:
    out.mkdir(parents=True, exist_ok=True)
    (out / "loop_throughput.json").write_text(json.dumps(record, indent=2))
    lines = ["# Loop throughput against the simulator alone", "",
             f"Command: `{record['command']}` (commit {record['commit']}); cameras: {record['cameras'] or 'none'}; "
             f"{record['lanes']} lanes, {record['envs_per_task']} sub-envs per task; "
             f"{record['cores']} cores, load average {record['load_average_1min']:.2f} when it ended.", "",
             "| policy | workers | part | env steps | loop env steps/s | simulator alone env steps/s | ratio (median) | turns |",
             "|---|---|---|---|---|---|---|---|"]
    lines += [f"| {r['policy']} | {r['workers']} | {r['part']} | {r['env_steps']:,} | {r['loop_steps_per_s']:,.0f} | "
              f"{r['simulator_steps_per_s']:,.0f} | {r['ratio']:.2f} | {', '.join(f'{x:.2f}' for x in r['ratios'])} |"
              for r in record["rows"]]
    if record.get("run_time_s"):
        total = sum(record["run_time_s"].values())
        lines += ["", f"The run's own wall-clock by phase ({total / 60:.1f} min, {record['run_env_steps']:,} RL env steps):",
                  "", "| phase | seconds | share |", "|---|---|---|"]
        lines += [f"| {k} | {v:.0f} | {v / total:.0%} |" for k, v in record["run_time_s"].items()]
    if any("raw_ratio" in r for r in record["rows"]):
        lines += ["", "`env.name: gym`: the same work on the user's Gymnasium env itself (its own actions, no chunk "
                  "env: the raw env's stepping rate):", "",
                  "| policy | workers | part | Gymnasium env alone env steps/s | loop / raw env (median) | turns |",
                  "|---|---|---|---|---|---|"]
        lines += [f"| {r['policy']} | {r['workers']} | {r['part']} | {r['raw_steps_per_s']:,.0f} | "
                  f"{r['raw_ratio']:.2f} | {', '.join(f'{x:.2f}' for x in r['raw_ratios'])} |"
                  for r in record["rows"] if "raw_ratio" in r]
    (out / "loop_throughput.md").write_text("\n".join(lines) + "\n")
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(7, 3.5))
    labels = [f"{r['policy']}\n{r['part']}, {r['workers']}w" for r in record["rows"]]
    ax.bar(range(len(labels)), [r["ratio"] for r in record["rows"]], color="tab:blue")
    ax.axhline(0.8, color="gray", ls="--", lw=1, label="target 0.8")
    ax.set_xticks(range(len(labels)), labels, fontsize=7)
    ax.set_ylabel("loop / simulator alone")
    ax.set_ylim(0, 1.1)
    ax.legend(fontsize=8)
    ax.set_title(f"loop efficiency ({'cameras' if record['cameras'] else 'state'})", fontsize=9)
    fig.tight_layout()
    fig.savefig(out / "loop_throughput.png", dpi=120)
    print(f"wrote {out / 'loop_throughput.md'}")


if __name__ == "__main__":
    main()
