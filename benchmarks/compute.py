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
- Policy calls: observations/s of the rollout's policy call alone (processed on the CPU, sampled
  with per-env CPU generators on the device, the chunk back on the CPU), for batches of
  ``--sample-sizes`` envs.

``--device cpu,cuda`` runs everything once per device (the policy, EMA copy, critic and optimizer
on it; docs/gpu.md) and, with several, draws ``compute_devices.png``.

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
    p.add_argument("--device", default="cpu", help="devices of the policy, comma-separated (e.g. cpu,cuda)")
    p.add_argument("--sample-sizes", default="1,8,64,512", help="envs per policy call of the policy-call timing ('': skip)")
    p.add_argument("--sample-repeats", type=int, default=20, help="timed policy calls per size (after 3 warm-ups)")
    p.add_argument("--lang-cache", default=None, help="folder of cached instruction embeddings (default: a temporary one)")
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

    from stepnft.envs import simulator_for
    from stepnft.policies.base import make_policy as build

    torch.manual_seed(0)
    policy = build(cfg.policy)
    sim = simulator_for(cfg.env)
    policy.processor.bind_instructions([sim.instruction(t) for t in cfg.env.tasks], lang_cache)
    return policy


def make_batch(cfg, policy, spec, calls: int, episodes: int):
    """A synthetic iteration (fixed seed) sampled by ``policy`` and recorded as ``spec`` says:
    calls interleaved over episodes as waves write them, groups of 4 episodes sharing a task and
    an initial-state seed, every other episode a success."""
    import torch

    from stepnft.batch import Batch
    from stepnft.devices import to_device

    g = torch.Generator().manual_seed(0)
    episode = torch.arange(calls) % episodes
    episode_task = (torch.arange(episodes) // 4) % len(cfg.env.tasks)
    obs = {"state": torch.randn(calls, cfg.policy.state_dim, generator=g), "task": episode_task[episode]}
    sample = to_device(policy.sample(policy.prepare(obs), noise_level=spec.noise_level, generator=g,
                                     stochastic_steps=spec.stochastic_steps, keep_path=spec.record_steps == "all"), "cpu")
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


def synchronize(device: str) -> None:
    """Wait for the device's queued work (a timer must not stop before the GPU does)."""
    import torch

    if device.startswith("cuda"):
        torch.cuda.synchronize()


def time_learner(name: str, args: argparse.Namespace, lang_cache: str, device: str, queue) -> None:
    """In a fresh process: time ``repeats`` updates of variant ``name`` on ``device``; puts a result dict."""
    import torch

    from stepnft.algos.base import make_algorithm
    from stepnft.algos.variants import variant_config
    from stepnft.config import load_config

    torch.set_num_threads(args.threads)
    cfg = load_config(args.config)
    algo_cfg = variant_config(name, cfg.algo)
    policy = make_policy(cfg, lang_cache).to(device)
    algo = make_algorithm(algo_cfg, policy, cfg.iterations, torch.Generator().manual_seed(0))
    batch = make_batch(cfg, algo.acting_policy(), algo.rollout, args.calls, args.episodes)
    rss_before = current_rss_mb()
    algo.update(batch)  # warm-up (and PPO builds its critic)
    times = []
    with PeakRss() as memory:
        for _ in range(args.repeats):
            synchronize(device)
            start = time.perf_counter()
            metrics = algo.update(batch)
            synchronize(device)
            times.append(time.perf_counter() - start)
    seconds = statistics.median(times)
    queue.put({"algo": name, "device": device, "update_s": seconds, "calls": batch.num_calls, "transitions": batch.num_steps,
               "calls_per_s": batch.num_calls / seconds, "transitions_per_s": batch.num_steps / seconds,
               "epochs": algo_cfg.update_epochs, "minibatch_size": algo_cfg.minibatch_size,
               "optimizer_steps": metrics["losses/update_steps"],
               "ms_per_step": 1000 * seconds / max(metrics["losses/update_steps"], 1),
               "rss_before_mb": rss_before, "update_peak_rss_mb": memory.peak_mb, "process_peak_rss_mb": rss_mb()})


def time_rollout(args: argparse.Namespace, lang_cache: str, device: str, queue) -> None:
    """In a fresh process: collector env steps/s (the policy on ``device``) against random-action env steps/s."""
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
    algo = make_algorithm(cfg.algo, make_policy(cfg, lang_cache).to(device), 1, torch.Generator())
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
    queue.put({"device": device, "rollout_env_steps": batch.env_steps, "rollout_policy_calls": batch.num_calls,
               "rollout_calls_per_s": batch.num_calls / policy_s, "rollout_steps_per_s": batch.env_steps / policy_s,
               "random_env_steps": steps, "random_steps_per_s": steps / random_s,
               "rollout_frac_of_random": (batch.env_steps / policy_s) / (steps / random_s),
               "envs": venv.num_envs, "peak_rss_mb": rss_mb()})


def time_sampling(args: argparse.Namespace, lang_cache: str, device: str, queue) -> None:
    """In a fresh process: the rollout's policy call alone (π-StepNFT's acting policy and rollout
    spec, per-env CPU generators), as the collector makes it, for each of ``--sample-sizes`` envs."""
    import torch

    from stepnft.algos.base import make_algorithm
    from stepnft.config import load_config
    from stepnft.devices import to_device

    torch.set_num_threads(args.threads)
    cfg = load_config(args.config)
    algo = make_algorithm(cfg.algo, make_policy(cfg, lang_cache).to(device), 1, torch.Generator())
    policy, spec = algo.acting_policy(), algo.rollout
    rows = []
    for size in [int(n) for n in args.sample_sizes.split(",") if n.strip()]:
        g = torch.Generator().manual_seed(size)
        raw = {"state": torch.randn(size, cfg.policy.state_dim, generator=g),
               "task": torch.randint(0, len(cfg.env.tasks), (size,), generator=g)}
        generators = [torch.Generator().manual_seed(i) for i in range(size)]

        def call():
            return to_device(policy.sample(policy.prepare(raw), noise_level=spec.noise_level, generator=generators,
                                           stochastic_steps=spec.stochastic_steps,
                                           keep_path=spec.record_steps == "all"), "cpu")

        for _ in range(3):
            call()
        synchronize(device)
        start = time.perf_counter()
        for _ in range(args.sample_repeats):
            call()
        seconds = (time.perf_counter() - start) / args.sample_repeats
        rows.append({"device": device, "envs": size, "ms_per_call": 1000 * seconds, "obs_per_s": size / seconds})
    queue.put(rows)


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
    from stepnft.devices import resolve_device
    from stepnft.envs import simulator_for
    from stepnft.policies.language import LanguageEncoder

    algos = [a.strip() for a in args.algos.split(",") if a.strip()]
    devices = [d.strip() for d in args.device.split(",") if d.strip()]
    unknown = [a for a in algos if a not in VARIANTS]
    if unknown or args.episodes % 4 or args.calls < args.episodes:
        raise SystemExit(f"--algos from {', '.join(VARIANTS)}; --episodes a multiple of 4 and <= --calls (got {unknown})")
    for device in devices:
        resolve_device(device)
    cfg = load_config(args.config)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    learners, sampling, rollouts = [], [], []
    with tempfile.TemporaryDirectory() as tmp:
        lang_cache = args.lang_cache or tmp
        if cfg.policy.lang_dim:  # embed once here: the timed processes read the table from disk
            sim = simulator_for(cfg.env)
            LanguageEncoder(cfg.policy.language_encoder, lang_cache).embed([sim.instruction(t) for t in cfg.env.tasks])
        for device in devices:
            learners += [in_fresh_process(time_learner, a, args, lang_cache, device) for a in algos]
            if args.sample_sizes.strip():
                sampling += in_fresh_process(time_sampling, args, lang_cache, device)
            if args.rollout_episodes:
                rollouts.append(in_fresh_process(time_rollout, args, lang_cache, device))

    lines = [f"Learner: one update on {args.calls} policy calls of {args.episodes} episodes ({args.config}: "
             f"{cfg.policy.hidden_dim}-wide policy, {len(cfg.env.tasks)} tasks), median of {args.repeats}, "
             f"{args.threads} torch thread(s).", "",
             "| device | algorithm | transitions | epochs × minibatch | optimizer steps | ms / step | update (s) | "
             "calls/s | transitions/s | stepnft calls/s ÷ this | RSS before → peak in updates (MiB) | "
             "process peak RSS (MiB) |", "|---" * 12 + "|"]
    for r in learners:
        ref = next((x for x in learners if x["algo"] == "stepnft" and x["device"] == r["device"]), r)
        lines.append(f"| {r['device']} | {r['algo']} | {r['transitions']} | {r['epochs']} × {r['minibatch_size']} | "
                     f"{r['optimizer_steps']:.0f} | {r['ms_per_step']:.1f} | {r['update_s']:.3f} | "
                     f"{r['calls_per_s']:,.0f} | {r['transitions_per_s']:,.0f} | "
                     f"{ref['calls_per_s'] / r['calls_per_s']:.2f} | {r['rss_before_mb']:.0f} → {r['update_peak_rss_mb']:.0f} | "
                     f"{r['process_peak_rss_mb']:.0f} |")
    if sampling:
        lines += ["", f"Policy calls (π-StepNFT's rollout call: processed on the CPU, Flow-SDE with per-env CPU "
                  f"generators, chunk back on the CPU), mean of {args.sample_repeats}:", "",
                  "| device | envs per call | ms / call | observations/s |", "|---" * 4 + "|"]
        lines += [f"| {r['device']} | {r['envs']} | {r['ms_per_call']:.2f} | {r['obs_per_s']:,.0f} |" for r in sampling]
    for rollout in rollouts:
        lines += ["", f"Rollout on {rollout['device']} ({rollout['envs']} envs, π-StepNFT's Flow-SDE rollouts of an "
                  f"untrained policy): {rollout['rollout_steps_per_s']:,.0f} env steps/s "
                  f"({rollout['rollout_calls_per_s']:,.0f} policy calls/s) over {rollout['rollout_env_steps']:,} steps; "
                  f"random actions: {rollout['random_steps_per_s']:,.0f} env steps/s over "
                  f"{rollout['random_env_steps']:,} steps; ratio **{rollout['rollout_frac_of_random']:.2f}**. "
                  f"Peak RSS {rollout['peak_rss_mb']:.0f} MiB."]
    lines += ["", f"Command: `python benchmarks/compute.py {' '.join(argv if argv is not None else sys.argv[1:])}`"]
    table = "\n".join(lines)
    print(table)
    (out / "compute.md").write_text(table + "\n")
    result = {"args": vars(args), "learners": learners, "sampling": sampling, "rollout": rollouts}
    (out / "compute.json").write_text(json.dumps(result, indent=2))
    if len(devices) > 1:
        plot_devices(result, out / "compute_devices.png")
    return result


def plot_devices(result: dict, path: Path) -> None:
    """Learner transitions/s per algorithm and policy-call observations/s per batch size, one
    bar or line per device."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    devices = list(dict.fromkeys(r["device"] for r in result["learners"]))
    algos = list(dict.fromkeys(r["algo"] for r in result["learners"]))
    fig, (left, right) = plt.subplots(1, 2, figsize=(11, 4))
    width = 0.8 / len(devices)
    for i, device in enumerate(devices):
        rate = {r["algo"]: r["transitions_per_s"] for r in result["learners"] if r["device"] == device}
        left.bar([k + i * width for k in range(len(algos))], [rate[a] for a in algos], width, label=device)
        rows = [r for r in result["sampling"] if r["device"] == device]
        if rows:
            right.plot([r["envs"] for r in rows], [r["obs_per_s"] for r in rows], "o-", label=device)
    left.set_xticks([k + 0.4 - width / 2 for k in range(len(algos))], algos)
    left.set_ylabel("update: recorded transitions / s")
    left.set_title("learner")
    right.set_xscale("log")
    right.set_yscale("log")
    right.set_xlabel("envs per policy call")
    right.set_ylabel("observations sampled / s")
    right.set_title("rollout policy call")
    for ax in (left, right):
        ax.legend()
        ax.grid(alpha=0.3)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)

if __name__ == "__main__":
    main()
