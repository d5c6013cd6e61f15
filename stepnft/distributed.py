"""Data-parallel learning over several processes (``torchrun``), the same update as one process.

Every process holds the policy and the iteration's whole batch (sample weights such as label
balancing are statistics of the whole batch). Each minibatch is split between the processes:
each runs the policy forward and backward on its share (:func:`shard_forward`), receives the
others' outputs without their autograd graphs, and computes the one-process loss on the whole
minibatch; :class:`~torch.nn.parallel.DistributedDataParallel` all-reduces the gradients, so
after an ordinary ``loss.backward()`` every process holds the one-process gradient (up to
float rounding) and takes the same optimizer step. Anything else an algorithm trains without
:func:`shard_forward` (PPO's critic) is computed whole, identically, on every process.

Rank 0 runs the training loop (rollouts, in process or on Ray workers; evaluation; logs;
checkpoints) and :func:`broadcast` sends the start state and each batch to the others, which
only update (``stepnft.train``). Launch::

    torchrun --nproc-per-node 2 -m stepnft.cli train ...

gloo carries CPU tensors, nccl CUDA ones. Outside ``torchrun`` every function here is a no-op.
"""

from __future__ import annotations

import gc
import os
import weakref
from datetime import timedelta
from typing import Any, Callable

import torch
import torch.distributed as dist
from torch import Tensor, nn

_wrappers: weakref.WeakKeyDictionary = weakref.WeakKeyDictionary()

TIMEOUT = timedelta(hours=2)
"""How long a process waits for the others (rank 0's SFT and evaluations run while the others wait)."""


def launched() -> bool:
    """Whether ``torchrun`` started this process as one of several."""
    return int(os.environ.get("WORLD_SIZE", "1")) > 1


def init() -> bool:
    """Join the process group ``torchrun`` describes, once; True in a multi-process run."""
    if dist.is_initialized():
        return True
    if not launched():
        return False
    if torch.cuda.is_available():
        torch.cuda.set_device(int(os.environ.get("LOCAL_RANK", "0")))
    dist.init_process_group("cpu:gloo,cuda:nccl" if torch.cuda.is_available() else "gloo", timeout=TIMEOUT)
    return True


def close(wait: bool = False) -> None:
    """Leave the process group (if any). ``wait``: first wait until every process gets here (the
    end of a run that went well; after an error the others may never come)."""
    if not dist.is_initialized():
        return
    if wait:
        dist.barrier()
    # The DDP wrappers hold the group (its gloo threads): dropped first, so that nothing is left
    # to destroy it during the interpreter's exit, where a follower has aborted ("terminate
    # called without an active exception"). The dictionary alone never frees them: each value
    # refers to its own key.
    _wrappers.clear()
    gc.collect()
    dist.destroy_process_group()


def world_size() -> int:
    return dist.get_world_size() if dist.is_initialized() else 1


def rank() -> int:
    return dist.get_rank() if dist.is_initialized() else 0


def broadcast(obj: Any = None) -> Any:
    """Rank 0's ``obj`` on every process (pickled, through the CPU); ``obj`` itself in one process."""
    if world_size() == 1:
        return obj
    box = [obj]
    dist.broadcast_object_list(box, src=0, device=torch.device("cpu"))
    return box[0]


def data_parallel(module: nn.Module) -> nn.Module:
    """``module`` in DistributedDataParallel (made once per module, which broadcasts rank 0's
    parameters) in a multi-process run; ``module`` itself in one process."""
    if world_size() == 1:
        return module
    if module not in _wrappers:
        device = next(module.parameters()).device
        # Every trained parameter must get a gradient from each loss (freeze the others), as DDP expects.
        _wrappers[module] = nn.parallel.DistributedDataParallel(
            module, device_ids=[device.index] if device.type == "cuda" else None)
    return _wrappers[module]


class _ScaleGrad(torch.autograd.Function):
    """The identity, with the gradient multiplied by ``scale`` on the way back."""

    @staticmethod
    def forward(ctx, x: Tensor, scale: float) -> Tensor:
        ctx.scale = scale
        return x.view_as(x)

    @staticmethod
    def backward(ctx, grad: Tensor):
        return grad * ctx.scale, None


def shard_forward(forward: Callable[[Tensor], Tensor], idx: Tensor) -> Tensor:
    """``forward(idx)``: outputs ``[len(idx), ...]`` for samples ``idx``. In a multi-process
    run each process computes its contiguous share of ``idx`` (through a
    :func:`data_parallel` module) and gathers the others' shares without their graphs: a loss
    on the result is the one-process loss, and its backward gives this process's part of the
    gradient, scaled by the number of processes so that DDP's average of the parts is their
    sum: the whole minibatch's gradient."""
    world = world_size()
    if world == 1:
        return forward(idx)
    parts = idx.tensor_split(world)
    mine = _ScaleGrad.apply(forward(parts[rank()]), float(world))
    padded = mine.new_zeros((max(len(p) for p in parts), *mine.shape[1:]))  # all_gather needs equal sizes
    padded[: len(mine)] = mine.detach()
    gathered = [torch.empty_like(padded) for _ in range(world)]
    dist.all_gather(gathered, padded)
    gathered[rank()] = mine
    return torch.cat([g[: len(p)] for g, p in zip(gathered, parts)])

