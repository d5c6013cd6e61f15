"""What an update costs at a VLA's real size (SmolVLA, π0, π0.5): seconds per update sample and peak memory for
π-StepNFT, PPO (Flow-SDE, its value head on the VLA's pooled prefix) and GRPO at an equal batch,
for each precision (with gradient checkpointing, and with LoRA on the VLM), plus policy calls/s with and without the
prefix cache.

The model (``--model``) is the full-size architecture built offline from a local configuration
with random weights (``stepnft.policies.lerobot.tiny``): SmolVLA (SmolVLM2-500M backbone, 16
language layers, ~450 M parameters), π0 / π0.5 (PaliGemma with gemma_2b and a gemma_300m
action expert, ~3.5 B; LeRobot 0.6); ``--size tiny`` is a quick check. Every algorithm gets the
same batch of policy calls (one episode per call; GRPO's groups of 2 share a reset seed) and does
one optimizer step over all of it (``minibatch_size`` = every recorded step): π-StepNFT records
one denoising step per call, PPO and GRPO all K (their likelihood sums over the chain), so an
"update sample" is a policy call for all three. ``train: expert`` (the action expert trains, the
VLM is frozen), the prefix cache on, the prefix shared by a call's recorded steps.

Each configuration runs in its own process, so its peak memory is its own: on a CPU the peak
resident set size (VmHWM) during the timed updates, less the resident size before them (the
model, its EMA copy and the batch), and in total; on a GPU ``torch.cuda.max_memory_allocated``.
Times are wall-clock and CPU seconds (CPU time is steadier where other jobs share the machine).
With ``--out`` the table is written after every row, and rerunning the command keeps the rows it
has (delete the folder to measure again).

    .venv-lerobot/bin/python benchmarks/vla_compute.py --out benchmarks/results/vla_compute
    .venv-lerobot/bin/python benchmarks/vla_compute.py --model pi0 --out benchmarks/results/vla_compute_pi0
    .venv-lerobot/bin/python benchmarks/vla_compute.py --size tiny --reps 1        # a quick check
    python benchmarks/vla_compute.py --device cuda --calls 16 --out OUT            # on a GPU
"""

from __future__ import annotations

import argparse
import contextlib
import json
import os
import platform
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import torch

import provenance

ALGOS = ("stepnft", "ppo", "grpo")
LORA_RANK = 16
CASES = [(algo, "bf16", False, 0) for algo in ALGOS] + [(algo, "bf16", True, LORA_RANK) for algo in ALGOS] + \
        [(algo, "bf16", True, 0) for algo in ALGOS] + [(algo, "fp32", False, 0) for algo in ALGOS]
"""(algorithm, precision, gradient checkpointing, LoRA rank) of the cost table, in its row order:
rank 0 trains the action expert (``train: expert``), a rank trains LoRA adapters on the VLM's
attention and the expert (``train: vlm``). fp32 last: at π0's size it may not fit what is free."""
CHUNK = {"tiny": (4, 4), "full": (50, 10)}
"""Chunk size and denoising steps K per size (SmolVLA's and π0's defaults at full size)."""
MODELS = ("smolvla", "pi0", "pi05")


def raw_obs(calls: int, side: int, seed: int = 0) -> dict:
    g = torch.Generator().manual_seed(seed)
    return {"state": torch.randn(calls, 39, generator=g), "task": torch.zeros(calls, dtype=torch.int64),
            "image": torch.randint(0, 256, (calls, 1, 3, side, side), dtype=torch.uint8, generator=g)}


def available_gb() -> float:
    """``MemAvailable`` of the machine, in GB."""
    line = next(l for l in Path("/proc/meminfo").read_text().splitlines() if l.startswith("MemAvailable:"))
    return int(line.split()[1]) / 2**20


def cap_memory(gb: float) -> None:
    """Cap this process's data segment (heap and anonymous mappings: where tensors live) at
    ``gb``: past it an allocation fails with an error instead of the kernel killing a process."""
    import resource

    limit = int(gb * 2**30)
    resource.setrlimit(resource.RLIMIT_DATA, (limit, limit))


def rss_mb(key: str = "VmRSS") -> float:
    """This process's resident set size (``VmRSS``) or its peak since the last reset (``VmHWM``), in MB."""
    for line in Path("/proc/self/status").read_text().splitlines():
        if line.startswith(key + ":"):
            return int(line.split()[1]) / 1024
    return float("nan")


def reset_peak() -> None:
    """Reset VmHWM to the current resident size (Linux: ``clear_refs`` 5)."""
    Path("/proc/self/clear_refs").write_text("5")


RANDOM_INITS = ("uniform_", "normal_", "trunc_normal_", "kaiming_uniform_", "kaiming_normal_", "xavier_uniform_",
                "xavier_normal_")
"""``torch.nn.init``'s random initialisers, which :func:`tiled_init` replaces (constant ones stay)."""
TILE = 1 << 22
"""Draws in the block :func:`tiled_init` tiles (4 M: 16 MB in float32)."""


@contextlib.contextmanager
def tiled_init(std: float = 0.02):
    """Inside this context every random initialiser of ``torch.nn.init`` (and transformers' guarded
    copies of them, which call the originals through ``TORCH_INIT_FUNCTIONS``) fills its tensor by
    tiling one block of N(0, ``std``²) draws instead of drawing each value: a full-size π0's 4 B
    parameters take ~250 s to draw on one core here (``normal_`` in bfloat16 runs at ~30 M values/s)
    and a few seconds to tile. A cost benchmark's weights only need to be finite and of a
    realistic scale (the time of a matrix product does not depend on its values); constant
    initialisers (norms' ones and zeros, zeroed biases) are kept."""
    block = torch.randn(TILE, generator=torch.Generator().manual_seed(0)) * std

    def fill(tensor, *args, **kwargs):
        with torch.no_grad():
            flat = tensor.view(-1) if tensor.is_contiguous() else torch.empty(tensor.numel(), dtype=tensor.dtype)
            for i in range(0, flat.numel(), TILE):
                part = flat[i:i + TILE]
                part.copy_(block[:part.numel()])
            if not tensor.is_contiguous():
                tensor.copy_(flat.view(tensor.shape))
        return tensor

    targets = [sys.modules[name] for name in ("torch.nn.init", "torch.nn.modules.linear", "torch.nn.modules.conv",
                                              "torch.nn.modules.sparse", "torch.nn.modules.activation")
               if name in sys.modules]
    originals = [(module, name, getattr(module, name)) for module in targets for name in RANDOM_INITS
                 if hasattr(module, name)]
    table = None
    try:
        from transformers import initialization

        table = initialization.TORCH_INIT_FUNCTIONS
    except ImportError:  # LeRobot 0.4.4's transformers initialises through torch.nn.init itself
        pass
    saved = {name: table[name] for name in RANDOM_INITS if name in table} if table is not None else {}
    try:
        for module, name, _ in originals:
            setattr(module, name, fill)
        for name in saved:
            table[name] = fill
        yield
    finally:
        for module, name, original in originals:
            setattr(module, name, original)
        for name, original in saved.items():
            table[name] = original


def build(model: str, size: str, device: str, tmp: Path, lora_rank: int = 0, precision: str = "fp32",
          init: str = "tiled"):
    from stepnft.policies.lerobot.tiny import PI_SIZES, SIZES, NewVLA, build_vla

    chunk, steps = CHUNK[size]
    side = SIZES["smolvla" if size == "full" else size]["vision"]["image_size"] if model == "smolvla" else PI_SIZES[size][2]
    # A bf16 row builds its model in bfloat16 from the start (π0: LeRobot's dtype too): π0's 3.5 B
    # parameters are 14 GB in float32, a peak that building in float32 and casting would add; the
    # trained parameters then go back to float32, as set_precision keeps them.
    default = torch.get_default_dtype()
    torch.set_default_dtype(torch.bfloat16 if precision == "bf16" else torch.float32)
    try:
        with tiled_init() if init == "tiled" else contextlib.nullcontext():
            policy = build_vla(NewVLA(out="", model=model, size=size, chunk_size=chunk, n_exec=chunk, num_steps=steps,
                                      image_size=side, train="vlm" if lora_rank else "expert", lora_rank=lora_rank),
                               tmp / size, dtype="bfloat16" if precision == "bf16" else "float32")
    finally:
        torch.set_default_dtype(default)
    for param in policy.parameters():
        if param.requires_grad:
            param.data = param.data.float()
    policy.processor.bind_instructions(["open the drawer"])
    return policy.to(device), side


def make_batch(policy, algo: str, calls: int, side: int):
    """``calls`` Flow-SDE policy calls of ``policy`` as one iteration's batch: one episode per
    call, half successful, groups of 2 sharing a reset seed; every denoising step recorded for
    PPO and GRPO, one per call for π-StepNFT."""
    from stepnft.batch import Batch
    from stepnft.devices import to_device

    raw = raw_obs(calls, side)
    with torch.no_grad():
        sample = to_device(policy.sample(policy.prepare(raw), noise_level=0.5, generator=torch.Generator().manual_seed(1),
                                         keep_path=True), "cpu")
    h = policy.chunk_shape[0]
    return Batch(episode_success=torch.arange(calls) % 2 == 0, episode_task=torch.zeros(calls, dtype=torch.int64),
                 episode_length=torch.full((calls,), h), episode_seed=torch.arange(calls) // 2, obs=raw,
                 actions=sample.actions, mask=torch.ones(calls, h, dtype=torch.bool),
                 reward=(torch.arange(calls) % 2 == 0).float(), done=torch.ones(calls, dtype=torch.bool),
                 episode=torch.arange(calls), **sample.recorded_steps(every_step=algo != "stepnft"))


def algo_config(algo: str, steps: int):
    from stepnft.algos.grpo import GRPOConfig
    from stepnft.algos.ppo import PPOConfig
    from stepnft.algos.stepnft import StepNFTConfig

    common = dict(minibatch_size=steps, update_epochs=1)
    if algo == "stepnft":
        return StepNFTConfig(**common)
    if algo == "ppo":
        return PPOConfig(noise_level=0.5, target_kl=None, **common)
    return GRPOConfig(noise_level=0.5, group_size=2, target_kl=None, **common)


def sync(device: str) -> None:
    if device.startswith("cuda"):
        torch.cuda.synchronize()


def one(args) -> dict:
    """One row of the table (run in its own process)."""
    from stepnft.algos.base import make_algorithm

    torch.set_num_threads(args.threads)
    cuda = args.device.startswith("cuda")
    with tempfile.TemporaryDirectory() as tmp:
        start = time.perf_counter()
        policy, side = build(args.model, args.size, args.device, Path(tmp), args.lora_rank, args.precision, args.init)
        build_s = time.perf_counter() - start
    policy.set_precision(args.precision).set_gradient_checkpointing(args.checkpointing)
    out = {"algo": args.algo, "precision": args.precision, "gradient_checkpointing": args.checkpointing,
           "lora_rank": args.lora_rank, "calls": args.calls, "warmups": args.warmups, "init": args.init,
           "build_s": build_s, "onednn_max_cpu_isa": os.environ.get("ONEDNN_MAX_CPU_ISA"), "parameters_M": sum(p.numel() for p in policy.parameters()) / 1e6,
           "trained_M": sum(p.numel() for p in policy.parameters() if p.requires_grad) / 1e6,
           "weights_MB": sum(p.nbytes for p in policy.parameters()) / 2**20}
    batch = make_batch(policy, args.algo, args.calls, side)
    algo = make_algorithm(algo_config(args.algo, batch.num_steps), policy, 1, torch.Generator().manual_seed(0))
    out["recorded_steps"] = batch.num_steps
    if cuda:
        torch.cuda.reset_peak_memory_stats()
        base = torch.cuda.memory_allocated() / 2**20
    else:
        base = rss_mb()
        reset_peak()
    wall = cpu = 0.0
    for rep in range(args.warmups + args.reps):  # warm-ups first (PPO builds its value head in its first update)
        sync(args.device)
        start, start_cpu = time.perf_counter(), time.process_time()
        metrics = algo.update(batch)
        sync(args.device)
        if rep >= args.warmups:
            wall += time.perf_counter() - start
            cpu += time.process_time() - start_cpu
    peak = torch.cuda.max_memory_allocated() / 2**20 if cuda else rss_mb("VmHWM")
    out |= {"update_s_per_sample": wall / args.reps / args.calls, "update_cpu_s_per_sample": cpu / args.reps / args.calls,
            "peak_MB": peak, "before_update_MB": base, "update_peak_MB": peak - base,
            "memory": "cuda max_memory_allocated" if cuda else "VmHWM (peak resident set)",
            "update_steps": metrics.get("losses/update_steps"), "skipped_nonfinite": metrics.get("losses/skipped_nonfinite")}
    if args.algo == "stepnft" and not args.checkpointing:  # sampling does not depend on the algorithm
        policy.eval()
        for cache in (True, False) if args.model == "smolvla" else (True,):  # π0 / π0.5 always cache their prefix
            policy.config.prefix_cache = cache
            raw = raw_obs(args.sample_calls, side, seed=2)
            obs = policy.prepare(raw)
            policy.sample(obs, noise_level=0.5, generator=torch.Generator().manual_seed(0))
            sync(args.device)
            start = time.perf_counter()
            policy.sample(obs, noise_level=0.5, generator=torch.Generator().manual_seed(0))
            sync(args.device)
            out[f"calls_per_s_{'cache' if cache else 'no_cache'}"] = args.sample_calls / (time.perf_counter() - start)
        policy.config.prefix_cache = True
    return out


def table(rows: list[dict]) -> str:
    lines = ["| algorithm | precision | checkpointing | trained | s / update sample (wall) | CPU s / sample | peak memory of the "
             "update (MB) | peak in all (MB) | weights (MB) | calls/s cache | calls/s no cache |",
             "|---|---|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        trained = f"LoRA {r['lora_rank']} + expert" if r.get("lora_rank") else "expert"
        trained += f" ({r['trained_M']:.3g} M)" if "trained_M" in r else ""
        if "error" in r:
            lines.append(f"| {r['algo']} | {r['precision']} | {'on' if r['gradient_checkpointing'] else 'off'} | "
                         f"{trained} | error: {r['error']} | | | | | | |")
            continue
        calls = [f"{r[k]:.2f}" if k in r else "" for k in ("calls_per_s_cache", "calls_per_s_no_cache")]
        lines.append(f"| {r['algo']} | {r['precision']} | {'on' if r['gradient_checkpointing'] else 'off'} | "
                     f"{trained} | {r['update_s_per_sample']:.3f} | {r['update_cpu_s_per_sample']:.3f} | {r['update_peak_MB']:.0f} | "
                     f"{r['peak_MB']:.0f} | {r['weights_MB']:.0f} | {calls[0]} | {calls[1]} |")
    return "\n".join(lines)


def ratios(rows: list[dict]) -> dict:
    """π-StepNFT against PPO per precision: throughput (PPO's seconds per sample / π-StepNFT's)
    and peak update memory (π-StepNFT's / PPO's); bf16 against fp32: the weights' memory."""
    by = {(r["algo"], r["precision"], r["gradient_checkpointing"]): r for r in rows
          if "error" not in r and not r.get("lora_rank")}
    out = {}
    for precision in ("fp32", "bf16"):
        s, p = by.get(("stepnft", precision, False)), by.get(("ppo", precision, False))
        if s and p:
            out[f"stepnft_vs_ppo_throughput_{precision}"] = p["update_s_per_sample"] / s["update_s_per_sample"]
            out[f"stepnft_vs_ppo_throughput_cpu_{precision}"] = p["update_cpu_s_per_sample"] / s["update_cpu_s_per_sample"]
            out[f"stepnft_vs_ppo_update_memory_{precision}"] = s["update_peak_MB"] / p["update_peak_MB"]
    if ("stepnft", "fp32", False) in by and ("stepnft", "bf16", False) in by:
        out["bf16_vs_fp32_weights"] = by[("stepnft", "bf16", False)]["weights_MB"] / by[("stepnft", "fp32", False)]["weights_MB"]
    for algo in ALGOS:
        if (algo, "bf16", True) in by and (algo, "bf16", False) in by:
            out[f"checkpointing_vs_not_update_memory_{algo}"] = (by[(algo, "bf16", True)]["update_peak_MB"]
                                                                 / by[(algo, "bf16", False)]["update_peak_MB"])
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--model", choices=MODELS, default="smolvla", help="LeRobot model (π0 / π0.5 need LeRobot 0.6)")
    parser.add_argument("--size", choices=[*CHUNK, "smolvla"], default="full",
                        help="full (the model's real architecture) or tiny; smolvla: full, by its old name")
    parser.add_argument("--calls", type=int, default=2, help="policy calls in the update batch (equal for all algorithms)")
    parser.add_argument("--sample-calls", type=int, default=1, help="batch of the timed policy calls")
    parser.add_argument("--reps", type=int, default=1, help="timed updates after the warm-ups")
    parser.add_argument("--warmups", type=int, default=1,
                        help="untimed updates first (0 at π0's size, where one update takes minutes: the first one's "
                             "extra work, PPO's value head and AdamW's state, is then inside the timed one)")
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--onednn-isa", default="ALL",
                        help="oneDNN's instruction-set cap for the rows (ONEDNN_MAX_CPU_ISA): ALL (default) lets bf16 run on "
                             "the CPU's AVX-512 bf16 units; AVX2 is the cap importing stepnft sets for reproducible learning "
                             "figures, under which a bf16 matrix product is ~9x slower on an AVX-512 CPU")
    parser.add_argument("--device", default="cpu")
    parser.add_argument("--init", choices=["tiled", "model"], default="tiled",
                        help="random weights: tiled (one block of N(0, 0.02^2) draws tiled over every tensor, seconds at "
                             "π0's size) or model (the model's own initialisers, ~4.5 min for π0 on one core)")
    parser.add_argument("--algos", nargs="+", choices=ALGOS, default=list(ALGOS), help="rows of these algorithms only")
    parser.add_argument("--precisions", nargs="+", choices=["fp32", "bf16"], default=["fp32", "bf16"],
                        help="rows of these precisions only")
    parser.add_argument("--max-memory-gb", type=float, default=None,
                        help="memory cap (RLIMIT_DATA) of each row's process (default: the memory available at the start "
                             "less 1 GB), so a row that does not fit fails alone instead of the machine's other jobs")
    parser.add_argument("--out", default=None, help="folder for compute.json and compute.md")
    parser.add_argument("--one", nargs=4, metavar=("ALGO", "PRECISION", "CHECKPOINTING", "LORA_RANK"), help=argparse.SUPPRESS)
    args = parser.parse_args()
    # Before importing stepnft (its cap is a default) and before torch runs a kernel (oneDNN reads
    # the cap once); the rows' processes inherit it.
    os.environ["ONEDNN_MAX_CPU_ISA"] = args.onednn_isa
    if args.one:
        args.algo, args.precision, args.checkpointing = args.one[0], args.one[1], args.one[2] == "1"
        args.lora_rank = int(args.one[3])
        print("RESULT " + json.dumps(one(args)), flush=True)
        return
    import stepnft

    if Path(stepnft.__file__).resolve().parents[1] != provenance.ROOT:
        parser.error(f"stepnft is imported from {Path(stepnft.__file__).parent}, not from this checkout: "
                     f"run with PYTHONPATH={provenance.ROOT}")
    args.size = "full" if args.size == "smolvla" else args.size
    out = Path(args.out) if args.out else None
    done_rows = []
    if out is not None and (out / "compute.json").is_file():  # an interrupted table: keep its rows
        done_rows = [r for r in json.loads((out / "compute.json").read_text())["rows"] if "error" not in r]
    results = {"commit": provenance.commit(), "command": provenance.command(), "packages": provenance.packages(), "cpu": provenance.cpu(), "model": args.model, "size": args.size, "calls": args.calls,
               "device": args.device, "torch": torch.__version__, "threads": args.threads,
               "machine": platform.processor() or platform.machine(), "load_average_at_start": list(os.getloadavg()),
               "rows": []}
    limit_gb = args.max_memory_gb or available_gb() - 1
    results["max_memory_gb"] = limit_gb
    for algo, precision, checkpointing, lora_rank in CASES:
        if algo not in args.algos or precision not in args.precisions:
            continue
        kept = [r for r in done_rows if (r["algo"], r["precision"], r["gradient_checkpointing"], r.get("lora_rank", 0)) ==
                (algo, precision, checkpointing, lora_rank)]
        if kept:
            results["rows"].append(kept[0])
            continue
        command = [sys.executable, __file__, "--model", args.model, "--size", args.size, "--calls", str(args.calls), "--reps", str(args.reps),
                   "--warmups", str(args.warmups), "--threads", str(args.threads), "--onednn-isa", args.onednn_isa, "--init", args.init, "--device", args.device, "--sample-calls", str(args.sample_calls),
                   "--one", algo, precision, "1" if checkpointing else "0", str(lora_rank)]
        done = subprocess.run(command, capture_output=True, text=True, preexec_fn=lambda: cap_memory(limit_gb))
        lines = [line for line in done.stdout.splitlines() if line.startswith("RESULT ")]
        row = json.loads(lines[-1][7:]) if lines else {
            "algo": algo, "precision": precision, "gradient_checkpointing": checkpointing, "lora_rank": lora_rank,
            "error": (done.stderr.strip().splitlines() or ["no output"])[-1][:200]}
        row["commit"] = results["commit"]  # a resumed table may mix commits: each row says its own
        results["rows"].append(row)
        print(json.dumps(row), flush=True)
        if out is not None:
            write(out, results, args)
    results["ratios"] = ratios(results["rows"])
    results["load_average_at_end"] = list(os.getloadavg())  # the machine may be shared with other jobs
    print(table(results["rows"]))
    print(json.dumps(results["ratios"], indent=1))
    if out is not None:
        write(out, results, args)


def write(out: Path, results: dict, args) -> None:
    """``compute.json`` and ``compute.md`` (the rows so far: a rerun of the command keeps them)."""
    out.mkdir(parents=True, exist_ok=True)
    (out / "compute.json").write_text(json.dumps(results, indent=2))
    (out / "compute.md").write_text(f"`{results['command']}` (commit {results['commit']}, {args.device}, "
                                    f"{args.threads} threads, {args.calls} policy calls per update)\n\n"
                                    + table(results["rows"]) + "\n")

if __name__ == "__main__":
    main()
