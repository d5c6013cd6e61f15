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
