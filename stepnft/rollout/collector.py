"""Play episodes in a vectorised env with a flow policy; keep what training needs.

One *wave* = every sub-env plays exactly one episode from a reset (autoreset disabled, the
finished sub-envs idle). Training waves sample with Flow-SDE from the EMA policy and record,
per policy call, the one denoising step of SPEC §3; evaluation waves use the ODE and fixed
initial-state seeds. Labels are terminal-binary: every call of an episode gets ``y = ±1``.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import torch
from torch import Tensor

from stepnft.policies.flow import FlowPolicy


@dataclass
class Wave:
    """Results of one wave over ``N`` sub-envs."""

    success: np.ndarray
    """[N] bool: episode success per sub-env."""
    length: np.ndarray
    """[N] int: env steps per episode."""
    calls: int = 0
    """Policy calls made (batched over the still-running sub-envs)."""
    transitions: dict[str, Tensor] = field(default_factory=dict)
    """Stored step transitions (empty unless recorded); see :func:`run_wave`."""


def run_wave(
    policy: FlowPolicy,
    venv,
    lang_table: Tensor | None,
    noise_level: float,
    generator: torch.Generator,
    seeds: list[int] | None = None,
    record: bool = False,
    stochastic_steps: str = "all",
    record_steps: str = "one",
) -> Wave:
    """Every sub-env of ``venv`` plays one episode with ``policy``.

    ``venv``: a MetaWorld vector env with autoreset disabled (``task_ids`` [N], actions
    ``[N, n_exec, A]``, ``info["steps"]``/``info["success"]``). ``lang_table``: ``[T, L]``
    instruction embeddings per task. With ``record``, ``transitions`` holds per policy call:
    ``state`` [M, S], ``task_id`` [M], ``x_t``, ``x_next``, ``v_old``, ``actions`` [M, H, A],
    ``t``, ``dt`` [M], ``mask`` [M, H] (executed positions), ``y`` [M], ``env_index`` [M].
    ``record_steps``: ``one`` stores the call's one random step (SPEC §3); ``all`` stores
    every one of its K denoising steps (K transitions per call, same simulator cost).
    """
    if record_steps not in ("one", "all"):
        raise ValueError(f"record_steps must be 'one' or 'all', got {record_steps!r}")
    n = venv.num_envs
    n_exec = policy.config.n_exec
    obs, _ = venv.reset(seed=seeds)
    task_ids = torch.as_tensor(venv.task_ids)
    done = np.zeros(n, dtype=bool)
    success = np.zeros(n, dtype=bool)
    length = np.zeros(n, dtype=np.int64)
    parts: list[dict[str, Tensor]] = []
    calls = 0
    while not done.all():
        active = np.flatnonzero(~done)
        state = torch.as_tensor(obs[active], dtype=torch.float32)
        lang = lang_table[task_ids[active]] if lang_table is not None else None
        path = {"keep_path": True} if record and record_steps == "all" else {}
        sample = policy.sample(state, lang, noise_level=noise_level, generator=generator,
                               stochastic_steps=stochastic_steps, **path)
        chunk = np.zeros((n, n_exec, policy.config.action_dim), dtype=np.float32)
        chunk[active] = sample.actions[:, :n_exec].clamp(-1.0, 1.0).numpy()
        obs, _, terminated, truncated, info = venv.step(chunk)
        steps = np.asarray(info["steps"])[active]
        calls += 1
        length[active] += steps
        success |= np.asarray(info["success"], dtype=bool) & ~done
        if record:
            positions = torch.arange(policy.config.horizon)
            part = {
                "state": state, "task_id": task_ids[active], "actions": sample.actions,
                "mask": positions[None, :] < torch.as_tensor(steps)[:, None],
                "env_index": torch.as_tensor(active),
            }
            if record_steps == "all":
                steps_k = sample.all_steps()
                rows = steps_k.pop("sample")
                part = {k: v[rows] for k, v in part.items()} | steps_k
            else:
                part |= {"x_t": sample.x_t, "x_next": sample.x_next, "v_old": sample.v_old, "t": sample.t, "dt": sample.dt}
            parts.append(part)
        done |= np.asarray(terminated) | np.asarray(truncated)
    wave = Wave(success=success, length=length, calls=calls)
    if record:
        transitions = {k: torch.cat([p[k] for p in parts]) for k in parts[0]}
        transitions["y"] = torch.as_tensor(success, dtype=torch.float32)[transitions["env_index"]] * 2 - 1
        wave.transitions = transitions
    return wave


def concat_transitions(waves: list[Wave]) -> dict[str, Tensor]:
    """Stack the recorded transitions of several waves into one batch; ``episode`` [M] numbers
    the episodes of all waves (wave ``i``, sub-env ``e`` -> ``i * N + e``)."""
    batch = {k: torch.cat([w.transitions[k] for w in waves]) for k in waves[0].transitions}
    batch["episode"] = torch.cat([i * len(w.success) + w.transitions["env_index"] for i, w in enumerate(waves)])
    return batch
