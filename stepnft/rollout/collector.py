"""The collector: plays whole episodes of a policy in a vector env and returns a :class:`Batch`.

One *wave* = every sub-env plays exactly one episode from a reset (autoreset disabled, the
finished sub-envs idle). :meth:`Collector.collect` plays waves until it has the episodes an
iteration asks for, sampling as the algorithm's :class:`RolloutSpec` says and recording its
denoising steps; evaluation plays ODE waves from fixed initial-state seeds. The collector
assigns no labels: what an episode's outcome means is the algorithm's business.

``collect`` and ``state_dict`` are the seam a remote (e.g. Ray) collector implements.
"""

from __future__ import annotations

import math

import numpy as np
import torch
from torch import Tensor

from stepnft.algos.base import RolloutSpec
from stepnft.batch import Batch
from stepnft.policies.base import Policy


class Collector:
    """Owns a chunk vector env and the sampler's random generator."""

    def __init__(self, venv, generator: torch.Generator | None = None):
        self.venv = venv
        self.generator = generator if generator is not None else torch.Generator().manual_seed(0)

    @property
    def num_envs(self) -> int:
        return self.venv.num_envs

    def collect(self, policy: Policy, episodes: int, spec: RolloutSpec) -> Batch:
        """At least ``episodes`` episodes (whole waves) sampled and recorded as ``spec`` says."""
        waves = math.ceil(episodes / self.num_envs)
        return Batch.concat([self.play_wave(policy, spec.noise_level, self.generator, record=spec)
                             for _ in range(waves)])

    def play_wave(self, policy: Policy, noise_level: float, generator: torch.Generator,
                  seeds: list[int] | None = None, record: RolloutSpec | None = None) -> Batch:
        """Every sub-env plays one episode from ``reset(seed=seeds)``; with ``record`` the batch
        holds its policy calls and recorded denoising steps, else only the episode table."""
        venv, n = self.venv, self.venv.num_envs
        horizon, action_dim = policy.chunk_shape
        n_exec = policy.config.n_exec
        raw, _ = venv.reset(seed=seeds)
        task_ids = torch.as_tensor(venv.task_ids)
        done = np.zeros(n, dtype=bool)
        success = np.zeros(n, dtype=bool)
        length = np.zeros(n, dtype=np.int64)
        stochastic_steps = record.stochastic_steps if record else "all"
        keep_path = record is not None and record.record_steps == "all"
        calls: list[dict[str, Tensor]] = []
        steps: list[dict[str, Tensor]] = []
        num_calls = 0
        while not done.all():
            active = np.flatnonzero(~done)
            obs = {k: torch.as_tensor(v[active]) for k, v in raw.items()} | {"task": task_ids[active]}
            sample = policy.sample(policy.processor(obs), noise_level=noise_level, generator=generator,
                                   stochastic_steps=stochastic_steps, keep_path=keep_path)
            chunk = np.zeros((n, n_exec, action_dim), dtype=np.float32)
            chunk[active] = sample.actions[:, :n_exec].clamp(-1.0, 1.0).numpy()
            raw, reward, terminated, truncated, info = venv.step(chunk)
            executed = np.asarray(info["steps"])[active]
            length[active] += executed
            success |= np.asarray(info["success"], dtype=bool) & ~done
            ended = (np.asarray(terminated) | np.asarray(truncated))[active]
            done[active] |= ended
            if record is not None:
                calls.append({
                    "obs": obs, "actions": sample.actions,
                    "mask": torch.arange(horizon)[None, :] < torch.as_tensor(executed)[:, None],
                    "reward": torch.as_tensor(np.asarray(reward, dtype=np.float32)[active]),
                    "done": torch.as_tensor(ended), "episode": torch.as_tensor(active, dtype=torch.int64),
                })
                if keep_path:
                    step = sample.all_steps()
                    step["call"] = num_calls + step.pop("sample")
                else:
                    step = {"x_t": sample.x_t, "x_next": sample.x_next, "v_old": sample.v_old, "t": sample.t,
                            "dt": sample.dt, "call": num_calls + torch.arange(len(active))}
                steps.append(step)
                num_calls += len(active)
        episodes = {
            "episode_success": torch.as_tensor(success), "episode_task": task_ids.clone(),
            "episode_length": torch.as_tensor(length),
            "episode_seed": torch.as_tensor(seeds if seeds is not None else [-1] * n, dtype=torch.int64),
        }
        if record is None:
            return Batch(**episodes, **_empty_tables(raw, horizon, action_dim))
        return Batch(
            **episodes,
            obs={k: torch.cat([c["obs"][k] for c in calls]) for k in calls[0]["obs"]},
            **{k: torch.cat([c[k] for c in calls]) for k in ("actions", "mask", "reward", "done", "episode")},
            **{k: torch.cat([s[k] for s in steps]) for k in ("call", "x_t", "x_next", "v_old", "t", "dt")},
        )

    def state_dict(self) -> dict:
        """The sub-envs' RNG states and the sampler's generator: enough to resume exactly."""
        return {"env_rng": self.venv.rng_state(), "generator": self.generator.get_state()}

    def load_state_dict(self, state: dict) -> None:
        self.venv.set_rng_state(state["env_rng"])
        self.generator.set_state(state["generator"])

    def close(self) -> None:
        self.venv.close()


def _empty_tables(raw: dict, horizon: int, action_dim: int) -> dict:
    """Call and step tables with no rows (a wave played without recording)."""
    chunk = torch.zeros(0, horizon, action_dim)
    obs = {k: torch.zeros((0, *np.asarray(v).shape[1:]), dtype=torch.as_tensor(np.asarray(v)).dtype)
           for k, v in raw.items()}
    obs["task"] = torch.zeros(0, dtype=torch.int64)
    return {"obs": obs, "actions": chunk, "mask": torch.zeros(0, horizon, dtype=torch.bool),
            "reward": torch.zeros(0), "done": torch.zeros(0, dtype=torch.bool),
            "episode": torch.zeros(0, dtype=torch.int64), "call": torch.zeros(0, dtype=torch.int64),
            "x_t": chunk, "x_next": chunk, "v_old": chunk, "t": torch.zeros(0), "dt": torch.zeros(0)}
