"""Scaling benchmark: rollout env-steps/s on 1 vs 2 Ray workers (and in process), learner
samples/s on 1 vs 2 DDP processes, the weight-push time; then a projection of a 64-environment
run on N machines (docs/scaling.md explains the model).

Settings are the README main command's (configs/quickstart.yaml: 5 MetaWorld tasks x 4 envs,
200-step episodes, the state + language flow policy, π-StepNFT with every denoising step
recorded), with a freshly initialised policy (its episodes run to the step cap, so every
measurement costs the same). The learner is idle while rollouts are timed. Prints a table and
writes scaling.json, scaling.md and scaling.png to --out.

    .venv/bin/python benchmarks/scaling.py            # the measurement: a quiet machine with >= 3 cores, a few minutes
    .venv/bin/python benchmarks/scaling.py --quick    # checks that it runs (tiny sizes: numbers mean nothing)
    .venv/bin/python benchmarks/scaling.py --project-from benchmarks/results/scaling --config configs/mt50.yaml \
        --project-envs 400 --episode-steps 144.3 --project-iterations 160 --out benchmarks/results/scaling_mt50
                                                      # the projection alone, for another run, from measured figures
"""

from __future__ import annotations

import argparse
import copy
import dataclasses
import json
import math
import os
import platform
import statistics
import sys
import tempfile
import time
import types
from pathlib import Path

import torch
import torch.distributed as dist
import torch.multiprocessing as mp
from provenance import commit, write_results

from stepnft.algos.base import make_algorithm, make_optimizer
from stepnft.algos.stepnft import stepnft_update
from stepnft.config import RayConfig, load_config
from stepnft.envs import get_simulator, make_vec_env
from stepnft.envs.sharded import shard_ranges
from stepnft.policies.base import make_policy
from stepnft.rollout.collector import Collector


def parse_args(argv=None) -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--config", default="configs/quickstart.yaml", help="run config giving the env, policy and algorithm")
    p.add_argument("--waves", type=int, default=12,
                   help="timed rollout waves per setting, taken in turns (after one warm-up wave each); the median counts")
    p.add_argument("--updates", type=int, default=5, help="timed π-StepNFT updates per learner setting (after a warm-up)")
    p.add_argument("--learner-rounds", type=int, default=3, help="learner timings per setting, taken in turns")
    p.add_argument("--learner-hidden-dim", type=int, default=1024,
                   help="also time the learner with a wider policy (compute-bound, where DDP pays); 0: skip")
    p.add_argument("--pushes", type=int, default=10, help="timed weight pushes per kind")
    p.add_argument("--push-hidden-dim", type=int, default=2048,
                   help="also time pushes of a wider policy (6 layers this wide) to measure bandwidth; 0: skip")
    p.add_argument("--cores-per-machine", type=int, default=16, help="for the projection: rollout cores per machine")
    p.add_argument("--project-envs", type=int, default=64, help="for the projection: parallel environments")
    p.add_argument("--project-iterations", type=int, default=300, help="for the projection: iterations of the run")
    p.add_argument("--episode-steps", type=float, default=None,
                   help="for the projection: mean env steps per episode (default: the measured rollouts', which run "
                        "a fresh policy to the step cap; a trained policy's episodes end earlier on success)")
    p.add_argument("--project-from", default=None, metavar="FOLDER",
                   help="measure nothing: project from FOLDER/scaling.json's figures with this --config and the "
                        "--project-* flags, and write projection.{json,md} to --out")
    p.add_argument("--quick", action="store_true", help="tiny sizes, to check the script runs")
    p.add_argument("--out", default="benchmarks/results/scaling", help="output folder")
    return p.parse_args(argv)


def setup(args):
    cfg = load_config(args.config)
    # One core per rollout worker: each Ray worker (and the in-process baseline) steps its envs itself
    # rather than in env.num_workers processes of its own, so 2 workers fit on 2 cores.
    cfg = dataclasses.replace(cfg, env=dataclasses.replace(cfg.env, num_workers=0))
    if args.quick:
        cfg = dataclasses.replace(cfg, env=dataclasses.replace(cfg.env, tasks=cfg.env.tasks[:2], envs_per_task=2,
                                                               max_episode_steps=20),
                                  policy=dataclasses.replace(cfg.policy, lang_dim=0, hidden_dim=64))
        args.waves, args.updates, args.learner_rounds, args.pushes, args.push_hidden_dim = 1, 1, 1, 2, 0
        args.learner_hidden_dim = 0
    torch.set_num_threads(cfg.num_threads)  # as `stepnft train` (and each Ray worker) does
    torch.manual_seed(0)
    policy = make_policy(cfg.policy)
    policy.processor.bind_instructions(get_simulator(cfg.env.name).vec_env_layout(cfg.env.tasks)["instructions"])
    return cfg, policy.eval()


def wider_policy(cfg, policy, **sizes):
    """A fresh policy of other ``sizes`` (hidden_dim, num_layers) with ``policy``'s processor, so it
    reads the same observations and normalisation."""
    wide = make_policy(dataclasses.replace(cfg.policy, **sizes))
    wide.processor = policy.processor
    return wide


# --- rollouts ---------------------------------------------------------------------------------
def time_rollouts(collectors: dict, policy, spec, waves: int) -> dict:
    """Env steps/s of each collector, timed wave by wave in turns (one wave of each, ``waves``
    times) so that a shared machine's slow spells fall on every setting alike; the median wave."""
    for collector in collectors.values():  # warm-up: whole-policy push, first resets
        collector.collect(policy, collector.num_envs, spec)
    rates, batches = {key: [] for key in collectors}, {}
    for _ in range(waves):
        for key, collector in collectors.items():
            start = time.perf_counter()
            batches[key] = collector.collect(policy, collector.num_envs, spec)
            rates[key].append(batches[key].env_steps / (time.perf_counter() - start))
    return {key: {"waves": waves, "env_steps_per_wave": batches[key].env_steps,
                  "env_steps_per_s": statistics.median(rates[key]), "per_wave": rates[key],
                  "mean_episode_steps": float(batches[key].episode_length.double().mean()), "last_batch": batches[key]}
            for key in collectors}


def _plain_worker(pipe, env_cfg, n_exec: int, seed: int, sub_envs: list[int], policy, spec, num_threads: int):
    from stepnft.rollout.ray_collector import RolloutWorker

    collector = RolloutWorker(env_cfg, n_exec, seed, sub_envs, num_threads).collector  # a Ray worker's body
    while pipe.recv():
        pipe.send(collector.collect(policy, len(sub_envs), spec).episode_length)
    collector.close()


class PlainProcesses:
    """The machine's own ceiling for 2 workers: the Ray workers' shards played by plain processes
    (no Ray, no driver traffic), a wave ending when both are done."""

    def __init__(self, cfg, policy, spec, num_envs: int, workers: int = 2):
        ctx = mp.get_context("spawn")
        self.num_envs = num_envs
        self.pipes, self.processes = [], []
        for shard in shard_ranges(num_envs, workers, "interleave"):
            parent, child = ctx.Pipe()
            process = ctx.Process(target=_plain_worker, daemon=True,
                                  args=(child, cfg.env, cfg.policy.n_exec, cfg.seed, list(shard), policy, spec,
                                        cfg.num_threads))
            process.start()
            self.pipes.append(parent)
            self.processes.append(process)

    def collect(self, policy, num_episodes, spec):  # the policy and spec are the ones given at start
        for pipe in self.pipes:
            pipe.send(True)
        lengths = torch.cat([pipe.recv() for pipe in self.pipes])
        return types.SimpleNamespace(env_steps=int(lengths.sum()), episode_length=lengths)

    def close(self):
        for pipe, process in zip(self.pipes, self.processes):
            pipe.send(False)
            process.join(timeout=30)


def time_pushes(collector, policy, pushes: int) -> dict:
    """Seconds until every worker holds ``policy``: a policy new to them (whole), one whose
    every tensor changed in place (an update), and an unchanged one (the round trip)."""
    size_mb = sum(t.numel() * t.element_size() for t in policy.state_dict().values()) / 2**20
    whole, changed, unchanged = [], [], []
    for _ in range(pushes):
        whole.append(collector.push(copy.deepcopy(policy)))
    collector.push(policy)
    for _ in range(pushes):
        with torch.no_grad():
            for p in policy.parameters():
                p.mul_(1.0)  # an in-place write, as an optimizer step: every tensor is sent
        changed.append(collector.push(policy))
        unchanged.append(collector.push(policy))
    collector.pop_metrics()
    return {"policy_mb": size_mb, "whole_s": statistics.median(whole), "changed_s": statistics.median(changed),
            "unchanged_s": statistics.median(unchanged)}


# --- the learner ------------------------------------------------------------------------------
def _learner(rank: int, world: int, init_file: str, data_file: str, updates: int, result_file: str) -> None:
    torch.set_num_threads(1)
    if world > 1:
        dist.init_process_group("gloo", init_method=f"file://{init_file}", rank=rank, world_size=world)
    data = torch.load(data_file, weights_only=False)
    policy, batch, algo = data["policy"], data["batch"], data["algo"]
    optimizer, generator = make_optimizer(policy.parameters(), algo), torch.Generator().manual_seed(0)
    policy.train()
    stepnft_update(policy, optimizer, batch, algo, generator)  # warm-up (and the DDP wrapper)
    if world > 1:
        dist.barrier()
    start = time.perf_counter()
    for _ in range(updates):
        stepnft_update(policy, optimizer, batch, algo, generator)
    if world > 1:
        dist.barrier()
        dist.destroy_process_group()
    seconds = time.perf_counter() - start
    if rank == 0:
        samples = updates * algo.update_epochs * batch.num_steps
        Path(result_file).write_text(json.dumps({"samples": samples, "seconds": seconds,
                                                 "samples_per_s": samples / seconds}))


def time_learner(policy, batch, algo, world: int, updates: int) -> dict:
    with tempfile.TemporaryDirectory() as tmp:
        torch.save({"policy": policy, "batch": batch, "algo": algo}, f"{tmp}/data.pt")
        mp.spawn(_learner, args=(world, f"{tmp}/init", f"{tmp}/data.pt", updates, f"{tmp}/result.json"),
                 nprocs=world, join=True)
        return json.loads(Path(f"{tmp}/result.json").read_text())


def measure_learner(policy, batch, algo, args) -> dict:
    """Samples/s of 1 and 2 DDP processes, timed in turns (as the rollouts); the median round."""
    timings = {1: [], 2: []}
    for _ in range(args.learner_rounds):
        for world in timings:
            timings[world].append(time_learner(policy, batch, algo, world, args.updates))
    return {str(world): {"samples_per_update": runs[0]["samples"] // args.updates,
                         "samples_per_s": statistics.median(run["samples_per_s"] for run in runs),
                         "per_round": [run["samples_per_s"] for run in runs]}
            for world, runs in timings.items()}


# --- projection -------------------------------------------------------------------------------
def project(results: dict, cfg, args) -> list[dict]:
    """Seconds per iteration of an ``--project-envs`` run (one episode per env per iteration) on
    N machines of ``--cores-per-machine`` cores: on each machine one core runs a DDP learner
    process (rank 0 also drives), every other core a rollout worker. Rollouts and the learner
    scale at their measured 2-worker / 2-process efficiencies; a wave lasts at least one
    episode (one env per worker)."""
    roll1 = results["rollout"]["1"]["env_steps_per_s"]
    efficiency = min(1.0, results["rollout"]["2"]["env_steps_per_s"] / (2 * roll1))
    learn1 = results["learner"]["1"]["samples_per_s"]
    learn_efficiency = min(1.0, results["learner"]["2"]["samples_per_s"] / (2 * learn1))
    steps = args.episode_steps or results["rollout"]["1"]["mean_episode_steps"]
    k = cfg.policy.num_inference_steps if cfg.algo.record_steps == "all" else 1
    samples = args.project_envs * math.ceil(steps / cfg.policy.n_exec) * k
    rows = []
    for machines in (1, 2, 4, 8, 16):
        workers = machines * (args.cores_per_machine - 1)
        envs_per_worker = math.ceil(args.project_envs / workers)
        rollout = envs_per_worker * steps / (roll1 * (efficiency if workers > 1 else 1.0))
        update = samples * cfg.algo.update_epochs / (learn1 * machines * (learn_efficiency if machines > 1 else 1.0))
        push = results["push"]["default"]["changed_s"]
        total = rollout + update + push
        parts = {"rollout": rollout, "update": update, "weight push": push}
        rows.append({"machines": machines, "rollout_workers": workers, "learner_processes": machines,
                     "rollout_s": rollout, "update_s": update,
                     "push_s": push, "iteration_s": total, "bottleneck": max(parts, key=parts.get),
                     "run_hours": total * args.project_iterations / 3600,
                     "machine_hours": machines * total * args.project_iterations / 3600})
    return rows


# --- report -----------------------------------------------------------------------------------
def learner_settings(results: dict) -> list[tuple[str, str]]:
    """The learner timings present in ``results``: (key, label)."""
    settings = (("learner", "default policy"), ("learner_wide", f"hidden {results['args']['learner_hidden_dim']}"))
    return [(name, label) for name, label in settings if name in results]


def report(results: dict, out: Path) -> str:
    r, a, lines = results, results["args"], []
    lines += ["| rollouts | env steps/s | speed-up vs 1 worker |", "|---|---|---|"]
    for key, label in (("0", "in process (--ray.workers 0)"), ("1", "1 Ray worker"), ("2", "2 Ray workers"),
                       ("plain 2", "2 plain processes, no Ray (the machine's ceiling)")):
        lines.append(f"| {label} | {r['rollout'][key]['env_steps_per_s']:.0f} | "
                     f"{r['rollout'][key]['env_steps_per_s'] / r['rollout']['1']['env_steps_per_s']:.2f}x |")
    turns = [two / one for one, two in zip(r["rollout"]["1"]["per_wave"], r["rollout"]["2"]["per_wave"])]
    lines += ["", f"Medians of {len(turns)} waves each, taken in turns; 2 workers / 1 worker turn by turn: median "
              f"{statistics.median(turns):.2f}x, range {min(turns):.2f}x to {max(turns):.2f}x."]
    lines += ["", "| learner | samples/s | speed-up |", "|---|---|---|"]
    for name, label in learner_settings(r):
        for key in ("1", "2"):
            lines.append(f"| {key} DDP process{'es' if key == '2' else ''}, {label} | {r[name][key]['samples_per_s']:.0f} | "
                         f"{r[name][key]['samples_per_s'] / r[name]['1']['samples_per_s']:.2f}x |")
    lines += ["", "| weight push (2 workers) | MB | new policy | all tensors changed | unchanged |", "|---|---|---|---|---|"]
    for name, p in r["push"].items():
        lines.append(f"| {name} policy | {p['policy_mb']:.1f} | {1e3 * p['whole_s']:.1f} ms | "
                     f"{1e3 * p['changed_s']:.1f} ms | {1e3 * p['unchanged_s']:.1f} ms |")
    lines += ["", projection_table(r["projection"], a)]
    text = "\n".join(lines) + "\n"
    (out / "scaling.md").write_text(f"Command: `{r['command']}` (commit {r.get('commit', '?')}) on {r['machine']}\n\n"
                                    + text)
    return text


def projection_table(projection: list[dict], a: dict) -> str:
    lines = [f"Projection: {a['project_envs']} environments, {a['project_iterations']} iterations, "
             f"{a['cores_per_machine']} cores per machine (docs/scaling.md):", "",
             "| machines | rollout workers | learner processes | rollout s | update s | push s | s / iteration | "
              "bottleneck | run hours | machine-hours |", "|---|---|---|---|---|---|---|---|---|---|"]
    for p in projection:
        lines.append(f"| {p['machines']} | {p['rollout_workers']} | {p['learner_processes']} | {p['rollout_s']:.2f} | "
                     f"{p['update_s']:.2f} | "
                     f"{p['push_s']:.3f} | {p['iteration_s']:.2f} | {p['bottleneck']} | {p['run_hours']:.2f} | "
                     f"{p['machine_hours']:.2f} |")
    return "\n".join(lines)


def plot(results: dict, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 4, figsize=(18, 4))
    roll = results["rollout"]
    axes[0].bar(["in process", "1 worker", "2 workers", "2 plain\nprocesses"],
                [roll[k]["env_steps_per_s"] for k in ("0", "1", "2", "plain 2")])
    axes[0].set_title("rollouts (learner idle)")
    axes[0].set_ylabel("env steps / s")
    for j, (name, label) in enumerate(learner_settings(results)):
        learn = results[name]
        axes[1].bar([i + 0.4 * j for i in range(2)], [learn[k]["samples_per_s"] / learn["1"]["samples_per_s"]
                                                     for k in ("1", "2")], width=0.4, label=label)
    axes[1].set_xticks([0.2, 1.2], ["1 process", "2 processes"])
    axes[1].set_title("π-StepNFT learner (DDP, gloo)")
    axes[1].set_ylabel("samples / s, relative to 1 process")
    axes[1].legend()
    names = list(results["push"])
    kinds = ("whole_s", "changed_s", "unchanged_s")
    for j, kind in enumerate(kinds):
        axes[2].bar([i + 0.27 * (j - 1) for i in range(len(names))], [1e3 * results["push"][n][kind] for n in names],
                    width=0.27, label=kind.removesuffix("_s"))
    axes[2].set_xticks(range(len(names)), [f"{n}\n{results['push'][n]['policy_mb']:.1f} MB" for n in names])
    axes[2].set_title("weight push to 2 workers")
    axes[2].set_ylabel("ms")
    axes[2].legend()
    proj = results["projection"]
    labels = [str(p["machines"]) for p in proj]
    bottom = [0.0] * len(proj)
    for key, label in (("rollout_s", "rollout"), ("update_s", "update"), ("push_s", "weight push")):
        values = [p[key] for p in proj]
        axes[3].bar(labels, values, bottom=bottom, label=label)
        bottom = [b + v for b, v in zip(bottom, values)]
    axes[3].set_title(f"projected iteration, {results['args']['project_envs']} envs")
    axes[3].set_xlabel("machines")
    axes[3].set_ylabel("s")
    axes[3].legend()
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def main(argv=None) -> dict:
    args = parse_args(argv)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    if args.project_from:
        return project_only(args, out, argv)
    import ray

    from stepnft.rollout.ray_collector import RayCollector

    cfg, policy = setup(args)
    rollout_spec = make_algorithm(cfg.algo, policy, 1, torch.Generator()).rollout
    results = {"rollout": {}, "learner": {}, "push": {}}

    ray.init(num_cpus=3, include_dashboard=False, log_to_driver=False)  # 1 + 2 workers, alive together
    collectors = {"0": Collector(make_vec_env(cfg.env, cfg.policy.n_exec, cfg.seed), seed=cfg.seed)}
    try:
        for workers in (1, 2):
            collectors[str(workers)] = RayCollector(cfg.env, cfg.policy.n_exec, cfg.seed, RayConfig(workers=workers),
                                                    cfg.num_threads)
        collectors["plain 2"] = PlainProcesses(cfg, policy, rollout_spec, collectors["0"].num_envs)
        results["rollout"] = time_rollouts(collectors, policy, rollout_spec, args.waves)
        collectors.pop("plain 2").close()
        collectors.pop("1").close()  # idle from here; the pushes go to the 2 workers
        results["push"]["default"] = time_pushes(collectors["2"], policy, args.pushes)
        if args.push_hidden_dim:
            wide = wider_policy(cfg, policy, hidden_dim=args.push_hidden_dim, num_layers=6)
            results["push"][f"hidden {args.push_hidden_dim}"] = time_pushes(collectors["2"], wide, args.pushes)
    finally:
        for collector in collectors.values():
            collector.close()
        ray.shutdown()
    batch = results["rollout"]["2"].pop("last_batch")
    for key in ("0", "1", "plain 2"):
        results["rollout"][key].pop("last_batch")
    results["learner"] = measure_learner(policy, batch, cfg.algo, args)
    if args.learner_hidden_dim:
        wide = wider_policy(cfg, policy, hidden_dim=args.learner_hidden_dim)
        results["learner_wide"] = measure_learner(wide, batch, cfg.algo, args)
        results["learner_wide"]["policy_params"] = sum(p.numel() for p in wide.parameters())
    results["learner"]["batch_samples"] = batch.num_steps
    results["args"] = vars(args)
    results["projection"] = project(results, cfg, args)
    results["command"] = " ".join(["benchmarks/scaling.py", *(argv if argv is not None else sys.argv[1:])])
    results["commit"] = commit()
    results["machine"] = f"{platform.machine()}, {os.cpu_count()} CPUs, torch {torch.__version__}, ray {ray.__version__}"
    text = report(results, out)
    (out / "scaling.json").write_text(json.dumps(results, indent=2))
    plot(results, out / "scaling.png")
    print(text)
    print(f"wrote {out}/scaling.json, scaling.md and scaling.png")
    return results


def project_only(args, out: Path, argv) -> dict:
    """The projection of ``--config``'s run from the figures a measurement saved."""
    measured = json.loads((Path(args.project_from) / "scaling.json").read_text())
    cfg = load_config(args.config)
    record = {"command": " ".join(["benchmarks/scaling.py", *(argv if argv is not None else sys.argv[1:])]),
              "commit": commit(), "measured": {"folder": args.project_from, "commit": measured.get("commit"),
                                               "command": measured.get("command")},
              "args": vars(args), "projection": project(measured, cfg, args)}
    text = projection_table(record["projection"], record["args"])
    write_results(out, "projection", record, text, f"Command: `{record['command']}` (commit {record['commit']}), "
                  f"from the figures of {args.project_from} (commit {measured.get('commit')})")
    print(text)
    return record


if __name__ == "__main__":
    main()
