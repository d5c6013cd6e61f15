"""The EMA rollout policy ``v_old`` and its cosine decay schedule (docs/algorithm.md §5)."""

from __future__ import annotations

import copy
import itertools
import math

import torch
from torch import Tensor, nn


def ema_decay(iteration: int, horizon: int, base: float = 0.1, target: float = 0.995) -> float:
    """Decay after ``iteration``: ``base`` at 0, rising on a half cosine to ``target`` at ``horizon``.

    A low decay early lets the rollout policy follow the learner quickly; a high one late
    keeps exploration data stable.
    """
    progress = min(iteration / max(horizon, 1), 1.0)
    return target - (target - base) * 0.5 * (1.0 + math.cos(math.pi * progress))


def _frozen_children(model: nn.Module) -> list[nn.Module]:
    """Outermost sub-modules whose parameters are all frozen (e.g. a VLM backbone)."""
    found: list[nn.Module] = []

    def visit(module: nn.Module) -> None:
        for child in module.children():
            params = list(child.parameters())
            if params and not any(p.requires_grad for p in params):
                found.append(child)
            else:
                visit(child)

    visit(model)
    return found


def make_ema_copy(model: nn.Module) -> nn.Module:
    """A copy of ``model`` for rollouts; frozen sub-modules (and a policy's input processor)
    are shared, not copied."""
    memo = {id(m): m for m in _frozen_children(model)}
    processor = getattr(model, "processor", None)
    if processor is not None:
        memo[id(processor)] = processor
    ema = copy.deepcopy(model, memo)
    for p in ema.parameters():
        p.requires_grad_(False)
    return ema


@torch.no_grad()
def ema_update(ema: nn.Module, model: nn.Module, decay: float) -> None:
    """``θ_old ← decay θ_old + (1 - decay) θ`` for trained parameters; buffers are copied."""
    for p_ema, p in zip(ema.parameters(), model.parameters()):
        if p_ema is p:  # shared frozen module
            continue
        p_ema.lerp_(p, 1.0 - decay)
    for b_ema, b in zip(ema.buffers(), model.buffers()):
        if b_ema is not b:
            b_ema.copy_(b)


def shared_state_names(ema: nn.Module, model: nn.Module) -> set[str]:
    """The state-dict entries of ``ema`` that are ``model``'s own tensors (its frozen modules,
    shared by :func:`make_ema_copy`)."""
    own = {id(t) for t in itertools.chain(model.parameters(), model.buffers())}
    tensors = itertools.chain(ema.named_parameters(remove_duplicate=False), ema.named_buffers(remove_duplicate=False))
    return {name for name, t in tensors if id(t) in own} & ema.state_dict().keys()


def ema_state_dict(ema: nn.Module, model: nn.Module) -> dict[str, Tensor]:
    """What a checkpoint keeps of the EMA copy: its state dict without the entries shared with
    ``model`` (saved with the policy; a frozen VLM would otherwise be stored twice)."""
    shared = shared_state_names(ema, model)
    return {k: v for k, v in ema.state_dict().items() if k not in shared}


def load_ema_state_dict(ema: nn.Module, model: nn.Module, state: dict[str, Tensor]) -> None:
    """Restore :func:`ema_state_dict` into an EMA copy of ``model``; a whole state dict (as
    checkpoints held before) loads too. Every entry must be either in ``state`` or shared."""
    shared = shared_state_names(ema, model)
    missing, unexpected = ema.load_state_dict({k: v for k, v in state.items() if k not in shared}, strict=False)
    missing = set(missing) - shared
    if missing or unexpected:
        raise ValueError(f"the EMA state does not fit the policy: {len(missing)} entries missing "
                         f"({', '.join(sorted(missing)[:3])}), {len(unexpected)} unexpected "
                         f"({', '.join(unexpected[:3])})")
