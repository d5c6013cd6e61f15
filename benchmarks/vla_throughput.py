"""Throughput of SmolVLA behind stepnft: policy calls/s (Flow-SDE sampling of one chunk per
call) and π-StepNFT update samples/s, for the tiny and the ~450 M configuration, with and
without the prefix cache.

With the cache (the default) a call encodes the vision-language prefix once and each of the K
denoising steps runs the action expert against its keys and values; in the update (action
expert trained, ``train: expert``) the prefix is encoded without gradients. Without it, every
denoising step, and every update sample, runs the whole model, vision encoder included
(SmolVLA's training forward). Models are randomly initialised from offline configurations (no
download). Each figure is timed over ``--reps`` calls after one warm-up call.

``--mode shared`` times the π-StepNFT update with ``record_steps: all`` (every one of a call's K
denoising steps recorded) two ways: the prefix encoded once per policy call and shared among its
recorded steps (the adapter's default, minibatches of whole calls), and encoded once per
recorded step (the path before, ``shares_prefix_in_update = False``). It reports update samples/s
and the prefixes encoded per update of each, and the largest velocity difference between the
two on the same recorded steps.

    .venv-lerobot/bin/python benchmarks/vla_throughput.py --out benchmarks/results/vla_throughput.json
    .venv-lerobot/bin/python benchmarks/vla_throughput.py --sizes tiny --reps 2      # a quick check
    .venv-lerobot/bin/python benchmarks/vla_throughput.py --mode shared --sizes tiny --out OUT.json
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import platform
import tempfile
import time
from pathlib import Path

import torch

import provenance

SETTINGS = {
    # size: (batch of a policy call, denoising steps K, chunk size, update samples, minibatch;
    # --mode shared: policy calls in the batch, all K steps of each recorded, and the minibatch in steps)
    "tiny": dict(batch=8, num_steps=4, chunk_size=4, update_samples=64, minibatch=32, shared_calls=16,
                 shared_minibatch=32),
    "smolvla": dict(batch=1, num_steps=10, chunk_size=50, update_samples=4, minibatch=2, shared_calls=1,
                    shared_minibatch=10),
}


def raw_obs(batch: int, size: int) -> dict:
    g = torch.Generator().manual_seed(0)
    return {"state": torch.randn(batch, 39, generator=g), "task": torch.zeros(batch, dtype=torch.int64),
            "image": torch.randint(0, 256, (batch, 1, 3, size, size), dtype=torch.uint8, generator=g)}


def timed_both(fn, reps: int) -> tuple[float, float]:
    """Wall-clock and this process's CPU seconds per call (one warm-up call first). With one
    thread the CPU time is the compute alone: steadier than the wall clock where other jobs
    share the machine."""
    fn()
    start, cpu = time.perf_counter(), time.process_time()
    for _ in range(reps):
        fn()
    return (time.perf_counter() - start) / reps, (time.process_time() - cpu) / reps


def timed(fn, reps: int) -> float:
    """Seconds per call (one warm-up call first)."""
    return timed_both(fn, reps)[0]


def build(size: str, tmp: Path):
    """The randomly initialised SmolVLA of ``size`` and what to report about it."""
    from stepnft.policies.lerobot.tiny import SIZES, NewSmolVLA, build_smolvla

    s = SETTINGS[size]
    image = SIZES[size]["vision"]["image_size"]
    t0 = time.perf_counter()
    policy = build_smolvla(NewSmolVLA(out="", size=size, chunk_size=s["chunk_size"], n_exec=s["chunk_size"],
                                      num_steps=s["num_steps"], image_size=image), tmp / size)
    built = time.perf_counter() - t0
    policy.processor.bind_instructions(["open the drawer"])
    params = sum(p.numel() for p in policy.parameters())
    trained = sum(p.numel() for p in policy.parameters() if p.requires_grad)
    return policy, image, {"parameters_M": params / 1e6, "trained_M": trained / 1e6, "build_s": built, **s}


def measure(size: str, reps: int, tmp: Path) -> dict:
    from stepnft.algos.base import make_optimizer
    from stepnft.algos.stepnft import StepNFTConfig, stepnft_update
    from stepnft.batch import Batch

    policy, image, out = build(size, tmp)
    s = SETTINGS[size]
    for cache in (True, False):
        policy.config = dataclasses.replace(policy.config, prefix_cache=cache)
        label = "cache" if cache else "no_cache"
        raw = raw_obs(s["batch"], image)
        per_call = timed(lambda: policy.sample(policy.processor(raw), noise_level=0.2,
                                               generator=torch.Generator().manual_seed(0)), reps)
        out[f"calls_per_s_{label}"] = s["batch"] / per_call
        print(size, f"calls_per_s_{label}", out[f"calls_per_s_{label}"], flush=True)
        # One π-StepNFT epoch over `update_samples` recorded steps (one per call).
        n = s["update_samples"]
        raw = raw_obs(n, image)
        sample = policy.sample(policy.processor(raw), noise_level=0.2, generator=torch.Generator().manual_seed(1))
        h = s["chunk_size"]
        batch = Batch(episode_success=torch.arange(n) % 2 == 0, episode_task=torch.zeros(n, dtype=torch.int64),
                      episode_length=torch.full((n,), h), episode_seed=torch.arange(n), obs=raw, actions=sample.actions,
                      mask=torch.ones(n, h, dtype=torch.bool), reward=torch.zeros(n), done=torch.ones(n, dtype=torch.bool),
                      episode=torch.arange(n), call=torch.arange(n), x_t=sample.x_t, x_next=sample.x_next,
                      v_old=sample.v_old, t=sample.t, dt=sample.dt)
        cfg = StepNFTConfig(minibatch_size=s["minibatch"], update_epochs=1)
        optimizer = make_optimizer([p for p in policy.parameters() if p.requires_grad], cfg)
        per_update = timed(lambda: stepnft_update(policy, optimizer, batch, cfg, torch.Generator().manual_seed(0)),
                           max(1, reps // 2))
        out[f"update_samples_per_s_{label}"] = n / per_update
        print(size, f"update_samples_per_s_{label}", out[f"update_samples_per_s_{label}"], flush=True)
    return out


def measure_shared(size: str, reps: int, tmp: Path) -> dict:
    """π-StepNFT updates with ``record_steps: all``: the prefix shared among a call's recorded
    steps vs encoded per step (``train: expert``, the prefix cache on)."""
    from stepnft.algos.base import make_optimizer, step_velocity
    from stepnft.algos.stepnft import StepNFTConfig, stepnft_update
    from stepnft.batch import Batch

    policy, image, out = build(size, tmp)
    s = SETTINGS[size]
    calls, h = s["shared_calls"], s["chunk_size"]
    raw = raw_obs(calls, image)
    sample = policy.sample(policy.processor(raw), noise_level=0.2, generator=torch.Generator().manual_seed(1),
                           keep_path=True)
    batch = Batch(episode_success=torch.arange(calls) % 2 == 0, episode_task=torch.zeros(calls, dtype=torch.int64),
                  episode_length=torch.full((calls,), h), episode_seed=torch.arange(calls), obs=raw,
                  actions=sample.actions, mask=torch.ones(calls, h, dtype=torch.bool), reward=torch.zeros(calls),
                  done=torch.ones(calls, dtype=torch.bool), episode=torch.arange(calls),
                  **sample.recorded_steps(every_step=True))
    encoded = []  # prefixes SmolVLA embeds (vision encoder, VLM layers into the cache), per call of the embedder
    embed = policy._embed_prefix
    policy._embed_prefix = lambda obs: encoded.append(len(obs["observation.state"])) or embed(obs)
    out |= {"recorded_steps": batch.num_steps, "steps_per_call": s["num_steps"]}
    cfg = StepNFTConfig(minibatch_size=s["shared_minibatch"], update_epochs=1)
    optimizer = make_optimizer([p for p in policy.parameters() if p.requires_grad], cfg)
    updates = max(1, reps // 2)
    for share, label in ((True, "shared"), (False, "per_step")):
        policy.shares_prefix_in_update = share
        encoded.clear()
        wall, cpu = timed_both(lambda: stepnft_update(policy, optimizer, batch, cfg, torch.Generator().manual_seed(0)),
                               updates)
        out[f"update_samples_per_s_{label}"] = batch.num_steps / wall
        out[f"update_samples_per_cpu_s_{label}"] = batch.num_steps / cpu
        out[f"prefixes_per_update_{label}"] = sum(encoded) / (updates + 1)
        print(size, label, out[f"update_samples_per_s_{label}"], "samples/s,", out[f"update_samples_per_cpu_s_{label}"],
              "samples/CPU s,", out[f"prefixes_per_update_{label}"], "prefixes per update", flush=True)
    rows = torch.arange(min(batch.num_steps, 2 * s["num_steps"]))  # the first calls' recorded steps
    with torch.no_grad():
        v = [step_velocity(policy, policy, batch, rows, share_prefix=share) for share in (True, False)]
    out["max_abs_velocity_difference"] = float((v[0] - v[1]).abs().max())
    out["speedup_wall"] = out["update_samples_per_s_shared"] / out["update_samples_per_s_per_step"]
    out["speedup_cpu"] = out["update_samples_per_cpu_s_shared"] / out["update_samples_per_cpu_s_per_step"]
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--sizes", nargs="+", default=["tiny", "smolvla"], choices=list(SETTINGS))
    parser.add_argument("--reps", type=int, default=3, help="timed repetitions after one warm-up")
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--mode", choices=["calls", "shared"], default="calls",
                        help="calls: sampling and update throughput, with and without the prefix cache; shared: "
                             "updates with record_steps all, the prefix shared per call vs encoded per step")
    parser.add_argument("--out", default=None, help="also write the figures as JSON here")
    args = parser.parse_args()
    import stepnft

    if Path(stepnft.__file__).resolve().parents[1] != provenance.ROOT:  # the recorded commit would not be what ran
        parser.error(f"stepnft is imported from {Path(stepnft.__file__).parent}, not from this checkout: "
                     f"run with PYTHONPATH={provenance.ROOT}")
    torch.set_num_threads(args.threads)
    results = {"commit": provenance.commit(), "command": provenance.command(), "packages": provenance.packages(), "cpu": provenance.cpu(), "mode": args.mode,
               "torch": torch.__version__, "threads": args.threads,
               "machine": platform.processor() or platform.machine(), "device": "cpu",
               "load_average_at_start": list(os.getloadavg()), "sizes": {}}
    with tempfile.TemporaryDirectory() as tmp:
        for size in args.sizes:
            results["sizes"][size] = (measure_shared if args.mode == "shared" else measure)(size, args.reps, Path(tmp))
            print(size, json.dumps(results["sizes"][size], indent=1), flush=True)
    results["load_average_at_end"] = list(os.getloadavg())  # the machine may be shared with other jobs
    if args.out:
        Path(args.out).parent.mkdir(parents=True, exist_ok=True)
        Path(args.out).write_text(json.dumps(results, indent=2))


if __name__ == "__main__":
    main()
