"""Where the policy runs (``--device``): the setting's check and the one helper that moves data.

The policy, its EMA copy, PPO's critic and the optimizer state live on ``cfg.device``. Everything
else stays on the CPU: the simulators, the observation processors, the rollout :class:`Batch`,
checkpoints, and every random generator. Noise is always drawn from the CPU generators and then
moved, so a CUDA run draws the very same noise as a CPU run (its results differ from the CPU
run's only by floating-point rounding). Data crosses over in :func:`to_device`: processed
observations and minibatches on the way to the policy, sampled chunks on the way back.
"""

from __future__ import annotations

import dataclasses
import re
from typing import TypeVar

import torch

T = TypeVar("T")

DEVICE_PATTERN = r"cpu|cuda(:\d+)?"
"""Accepted ``device`` values: ``cpu``, ``cuda`` (the current GPU; under ``torchrun`` each
process's ``LOCAL_RANK``) or ``cuda:N``."""


def check_device_name(name: str) -> bool:
    return re.fullmatch(DEVICE_PATTERN, name) is not None


def resolve_device(name: str) -> torch.device:
    """``name`` as a device that exists here; a ValueError with one line otherwise."""
    if not check_device_name(name):
        raise ValueError(f"device={name!r} is invalid: use cpu, cuda or cuda:N")
    device = torch.device(name)
    if device.type == "cuda":
        if not torch.cuda.is_available():
            why = "this torch is a CPU-only build" if torch.version.cuda is None else "no GPU is visible"
            raise ValueError(f"--device {name}: CUDA is not available here ({why}, torch {torch.__version__}); "
                             "use --device cpu")
        if device.index is not None and device.index >= torch.cuda.device_count():
            raise ValueError(f"--device {name}: this machine has {torch.cuda.device_count()} GPU(s)")
    return device


def to_device(data: T, device: torch.device | str) -> T:
    """``data`` with every tensor moved to ``device``, through dicts, lists, tuples and dataclasses
    (a :class:`~stepnft.batch.Batch`, a :class:`~stepnft.sampling.ChunkSample`); anything else is
    kept. A tensor already there is returned as it is (no copy)."""
    if torch.is_tensor(data):
        return data.to(device)
    if isinstance(data, dict):
        return {k: to_device(v, device) for k, v in data.items()}
    if isinstance(data, (list, tuple)):
        return type(data)(to_device(v, device) for v in data)
    if dataclasses.is_dataclass(data) and not isinstance(data, type):
        return dataclasses.replace(data, **{f.name: to_device(getattr(data, f.name), device)
                                            for f in dataclasses.fields(data) if f.init})
    return data


def bf16_capped_note(cpu_flags: set[str] | None = None) -> str | None:
    """One line when bfloat16 would run slow on this CPU: it has AVX-512 bf16 (or AMX) units but
    oneDNN is capped at AVX2, the cap importing stepnft sets for reproducible figures
    (``stepnft/__init__.py``), under which a bf16 matrix product falls back to a kernel ~9× slower
    (docs/lerobot.md, "bf16 on a CPU"). ``None`` otherwise. oneDNN reads the cap once, at its first
    kernel, so a process can only be told, not fixed. ``cpu_flags``: the CPU's (default: read from
    ``/proc/cpuinfo``)."""
    import os
    from pathlib import Path

    if os.environ.get("ONEDNN_MAX_CPU_ISA", "").upper() != "AVX2":
        return None
    if cpu_flags is None:
        try:
            line = next((l for l in Path("/proc/cpuinfo").read_text().splitlines() if l.startswith("flags")), "")
        except OSError:  # not Linux: nothing to tell
            return None
        cpu_flags = set(line.split(":", 1)[-1].split())
    if not {"avx512_bf16", "amx_bf16"} & cpu_flags:
        return None
    return ("bf16 on this CPU runs ~9x slower under stepnft's oneDNN cap (ONEDNN_MAX_CPU_ISA=AVX2, set for "
            "reproducible figures): export ONEDNN_MAX_CPU_ISA=ALL before the run to use its bf16 units")
