"""Compute benchmark: what each algorithm's learner costs, and what the rollout costs against the
simulator alone.

- Learner: every algorithm updates the same policy (the base config's model, same
  initialisation) on the same synthetic iteration (``--calls`` policy calls of ``--episodes``
  episodes over the base config's tasks, half of them successful, groups of 4 episodes per
  initial state), each recording its denoising steps as its own rollout spec says. Reported:
  seconds per update (median of ``--repeats``), policy calls/s and recorded transitions/s, and
  resident memory (one fresh process per algorithm): before the updates, the peak during them
  (sampled every 2 ms) and the process's peak (``getrusage``).
- Rollout: env steps/s of the collector playing ``--rollout-episodes`` Flow-SDE episodes with
  the policy (π-StepNFT's rollout spec), against the same vector env stepped with uniform
  random action chunks (the simulator-only rate).

    .venv/bin/python benchmarks/compute.py        # writes benchmarks/results/compute/compute.md, .json

Run it alone on the machine: the figures are timings.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import multiprocessing as mp
import resource
import statistics
import sys
import tempfile
import time
from pathlib import Path

DEFAULT_ALGOS = "stepnft,paper,ppo,ppo-one,grpo,grpo-one"


def parse_args(argv=None) -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--config", default="configs/quickstart.yaml", help="base run config: model, tasks, envs, algo settings")
    p.add_argument("--algos", default=DEFAULT_ALGOS, help="variants of `stepnft compare` to time (comma-separated)")
    p.add_argument("--calls", type=int, default=1000, help="policy calls in the synthetic iteration (~20 MetaWorld episodes)")
    p.add_argument("--episodes", type=int, default=20, help="episodes the calls belong to (a multiple of 4)")
    p.add_argument("--repeats", type=int, default=3, help="timed updates per algorithm (after one warm-up)")
    p.add_argument("--rollout-episodes", type=int, default=20, help="episodes of the rollout timing (0: skip it)")
    p.add_argument("--max-episode-steps", type=int, default=None, help="episode cap of the rollout timing (default: the config's)")
    p.add_argument("--threads", type=int, default=1, help="torch threads (the runs use 1)")
    p.add_argument("--out", default="benchmarks/results/compute", help="folder for compute.md and compute.json")
    return p.parse_args(argv)


def rss_mb() -> float:
    """Peak resident memory of this process so far, MiB (Linux reports KiB)."""
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    return peak / 1024 if sys.platform != "darwin" else peak / 2**20


def current_rss_mb() -> float:
    try:
        pages = int(Path("/proc/self/statm").read_text().split()[1])
        return pages * resource.getpagesize() / 2**20
    except OSError:
        return float("nan")


class PeakRss:
    """Within the block, a thread samples the resident memory every 2 ms; ``peak_mb`` is its maximum."""

    def __enter__(self):
        import threading

        self.peak_mb, self._stop = current_rss_mb(), threading.Event()
        self._thread = threading.Thread(target=self._poll, daemon=True)
        self._thread.start()
        return self

    def _poll(self):
        while not self._stop.wait(0.002):
            self.peak_mb = max(self.peak_mb, current_rss_mb())

    def __exit__(self, *exc):
        self._stop.set()
        self._thread.join()
        self.peak_mb = max(self.peak_mb, current_rss_mb())


def make_policy(cfg, lang_cache: str):
    """The base config's policy, initialised from seed 0, its instructions bound."""
    import torch

    from stepnft.envs import get_simulator
    from stepnft.policies.base import make_policy as build

    torch.manual_seed(0)
    policy = build(cfg.policy)
    sim = get_simulator(cfg.env.name)
    policy.processor.bind_instructions([sim.instruction(t) for t in cfg.env.tasks], lang_cache)
    return policy


def make_batch(cfg, policy, spec, calls: int, episodes: int):
    """A synthetic iteration (fixed seed) sampled by ``policy`` and recorded as ``spec`` says:
    calls interleaved over episodes as waves write them, groups of 4 episodes sharing a task and
    an initial-state seed, every other episode a success."""
    import torch

    from stepnft.batch import Batch

    g = torch.Generator().manual_seed(0)
    episode = torch.arange(calls) % episodes
    episode_task = (torch.arange(episodes) // 4) % len(cfg.env.tasks)
    obs = {"state": torch.randn(calls, cfg.policy.state_dim, generator=g), "task": episode_task[episode]}
    sample = policy.sample(policy.processor(obs), noise_level=spec.noise_level, generator=g,
                           stochastic_steps=spec.stochastic_steps, keep_path=spec.record_steps == "all")
    if spec.record_steps == "all":
        steps = sample.all_steps()
        steps["call"] = steps.pop("sample")
    else:
        steps = {"x_t": sample.x_t, "x_next": sample.x_next, "v_old": sample.v_old, "t": sample.t, "dt": sample.dt,
                 "call": torch.arange(calls)}
    last = {int(e): i for i, e in enumerate(episode.tolist())}
    return Batch(
        episode_success=torch.arange(episodes) % 2 == 0, episode_task=episode_task,
        episode_length=torch.bincount(episode, minlength=episodes) * cfg.policy.n_exec,
        episode_seed=1000 + torch.arange(episodes) // 4, obs=obs, actions=sample.actions,
        mask=torch.ones(calls, cfg.policy.horizon, dtype=torch.bool), reward=torch.zeros(calls),
        done=torch.tensor([last[int(e)] == i for i, e in enumerate(episode.tolist())]), episode=episode, **steps)


def time_learner(name: str, args: argparse.Namespace, lang_cache: str, queue) -> None:
    """In a fresh process: time ``repeats`` updates of variant ``name``; puts a result dict."""
    import torch

    from stepnft.algos.base import make_algorithm
    from stepnft.algos.variants import variant_config
    from stepnft.config import load_config

    torch.set_num_threads(args.threads)
    cfg = load_config(args.config)
    algo_cfg = variant_config(name, cfg.algo)
    policy = make_policy(cfg, lang_cache)
    algo = make_algorithm(algo_cfg, policy, cfg.iterations, torch.Generator().manual_seed(0))
    batch = make_batch(cfg, algo.acting_policy(), algo.rollout, args.calls, args.episodes)
    rss_before = current_rss_mb()
    algo.update(batch)  # warm-up (and PPO builds its critic)
    times = []
    with PeakRss() as memory:
        for _ in range(args.repeats):
            start = time.perf_counter()
            metrics = algo.update(batch)
            times.append(time.perf_counter() - start)
    seconds = statistics.median(times)
    queue.put({"algo": name, "update_s": seconds, "calls": batch.num_calls, "transitions": batch.num_steps,
               "calls_per_s": batch.num_calls / seconds, "transitions_per_s": batch.num_steps / seconds,
               "epochs": algo_cfg.update_epochs, "minibatch_size": algo_cfg.minibatch_size,
               "optimizer_steps": metrics["losses/update_steps"],
               "ms_per_step": 1000 * seconds / max(metrics["losses/update_steps"], 1),
               "rss_before_mb": rss_before, "update_peak_rss_mb": memory.peak_mb, "process_peak_rss_mb": rss_mb()})


def time_rollout(args: argparse.Namespace, lang_cache: str, queue) -> None:
    """In a fresh process: collector env steps/s against random-action env steps/s."""
    import numpy as np
    import torch

    from stepnft.algos.base import make_algorithm
    from stepnft.config import load_config
    from stepnft.envs import make_vec_env
    from stepnft.rollout.collector import Collector

    torch.set_num_threads(args.threads)
    cfg = load_config(args.config)
    if args.max_episode_steps:
        cfg = dataclasses.replace(cfg, env=dataclasses.replace(cfg.env, max_episode_steps=args.max_episode_steps))
    algo = make_algorithm(cfg.algo, make_policy(cfg, lang_cache), 1, torch.Generator())
    venv = make_vec_env(cfg.env, cfg.policy.n_exec, seed=0)
    try:
        collector = Collector(venv, seed=0)
        collector.collect(algo.acting_policy(), venv.num_envs, algo.rollout)  # warm-up
        start = time.perf_counter()
        batch = collector.collect(algo.acting_policy(), args.rollout_episodes, algo.rollout)
        policy_s = time.perf_counter() - start
        rng = np.random.default_rng(0)
        steps, start = 0, time.perf_counter()
        while steps < batch.env_steps:  # whole waves of random chunks, at least as many env steps
            venv.reset(seed=[int(s) for s in rng.integers(2**24, 2**31, venv.num_envs)])
            done = np.zeros(venv.num_envs, dtype=bool)
            while not done.all():
                chunk = rng.uniform(-1, 1, (venv.num_envs, cfg.policy.n_exec, cfg.policy.action_dim)).astype(np.float32)
                _, _, terminated, truncated, info = venv.step(chunk)
                steps += int(np.asarray(info["steps"]).sum())
                done |= np.asarray(terminated) | np.asarray(truncated)
        random_s = time.perf_counter() - start
    finally:
        venv.close()
    queue.put({"rollout_env_steps": batch.env_steps, "rollout_steps_per_s": batch.env_steps / policy_s,
               "random_env_steps": steps, "random_steps_per_s": steps / random_s,
               "rollout_frac_of_random": (batch.env_steps / policy_s) / (steps / random_s),
               "envs": venv.num_envs, "peak_rss_mb": rss_mb()})


def in_fresh_process(target, *args) -> dict:
    ctx = mp.get_context("spawn")
    queue = ctx.Queue()
    proc = ctx.Process(target=target, args=(*args, queue))
    proc.start()
    result = queue.get()
    proc.join()
    return result


def main(argv=None) -> dict:
    args = parse_args(argv)
    from stepnft.algos.variants import VARIANTS
    from stepnft.config import load_config
    from stepnft.envs import get_simulator
    from stepnft.policies.language import LanguageEncoder

    algos = [a.strip() for a in args.algos.split(",") if a.strip()]
    unknown = [a for a in algos if a not in VARIANTS]
    if unknown or args.episodes % 4 or args.calls < args.episodes:
        raise SystemExit(f"--algos from {', '.join(VARIANTS)}; --episodes a multiple of 4 and <= --calls (got {unknown})")
    cfg = load_config(args.config)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    with tempfile.TemporaryDirectory() as lang_cache:
        if cfg.policy.lang_dim:  # embed once here: the timed processes read the table from disk
            sim = get_simulator(cfg.env.name)
            LanguageEncoder(cfg.policy.language_encoder, lang_cache).embed([sim.instruction(t) for t in cfg.env.tasks])
        learners = [in_fresh_process(time_learner, a, args, lang_cache) for a in algos]
        rollout = in_fresh_process(time_rollout, args, lang_cache) if args.rollout_episodes else None

    ref = next((r for r in learners if r["algo"] == "stepnft"), learners[0])
    lines = [f"Learner: one update on {args.calls} policy calls of {args.episodes} episodes ({args.config}: "
             f"{cfg.policy.hidden_dim}-wide policy, {len(cfg.env.tasks)} tasks), median of {args.repeats}, "
             f"{args.threads} torch thread(s).", "",
             f"| algorithm | transitions | epochs × minibatch | optimizer steps | ms / step | update (s) | calls/s | "
             f"transitions/s | {ref['algo']} calls/s ÷ this | RSS before → peak in updates (MiB) | "
             "process peak RSS (MiB) |", "|---" * 11 + "|"]
    for r in learners:
        lines.append(f"| {r['algo']} | {r['transitions']} | {r['epochs']} × {r['minibatch_size']} | "
                     f"{r['optimizer_steps']:.0f} | {r['ms_per_step']:.1f} | {r['update_s']:.3f} | "
                     f"{r['calls_per_s']:,.0f} | {r['transitions_per_s']:,.0f} | "
                     f"{ref['calls_per_s'] / r['calls_per_s']:.2f} | {r['rss_before_mb']:.0f} → {r['update_peak_rss_mb']:.0f} | "
                     f"{r['process_peak_rss_mb']:.0f} |")
    if rollout:
        lines += ["", f"Rollout ({rollout['envs']} envs, π-StepNFT's Flow-SDE rollouts of an untrained policy): "
                  f"{rollout['rollout_steps_per_s']:,.0f} env steps/s over {rollout['rollout_env_steps']:,} steps; "
                  f"random actions: {rollout['random_steps_per_s']:,.0f} env steps/s over "
                  f"{rollout['random_env_steps']:,} steps; ratio **{rollout['rollout_frac_of_random']:.2f}**. "
                  f"Peak RSS {rollout['peak_rss_mb']:.0f} MiB."]
    lines += ["", f"Command: `python benchmarks/compute.py {' '.join(argv if argv is not None else sys.argv[1:])}`"]
    table = "\n".join(lines)
    print(table)
    (out / "compute.md").write_text(table + "\n")
    result = {"args": vars(args), "learners": learners, "rollout": rollout}
    (out / "compute.json").write_text(json.dumps(result, indent=2))
    return result


if __name__ == "__main__":
    main()
