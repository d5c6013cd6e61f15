"""The collector: plays whole episodes of a policy in a vector env and returns a :class:`Batch`.

One *wave* = every active sub-env plays exactly one episode from a reset (autoreset disabled,
the finished sub-envs idle). :meth:`Collector.collect` plays waves until it has the episodes an
iteration asks for, per task if asked (sub-envs a task does not need sit the wave out),
sampling as the algorithm's :class:`RolloutSpec` says and recording its denoising steps; with
``group_size`` G, consecutive groups of G sub-envs of a task start from one shared initial
state. Evaluation plays ODE waves from fixed initial-state seeds. The collector assigns no
labels: what an episode's outcome means is the algorithm's business.

``collect`` and ``state_dict`` are the seam a remote (e.g. Ray) collector implements.
"""

from __future__ import annotations

import math

import numpy as np
import torch
from torch import Tensor

from stepnft.algos.base import RolloutSpec
from stepnft.batch import Batch
from stepnft.devices import to_device
from stepnft.policies.base import Policy


def sub_env_generators(seed: int, num_envs: int) -> tuple[torch.Generator, list[torch.Generator]]:
    """The collector's own generator (group seeds) and one sampler generator per sub-env, all
    derived from ``seed``: sub-env ``i``'s noise depends only on ``(seed, i)``, so any split of
    the sub-envs over workers draws the same episodes."""
    streams = np.random.SeedSequence(seed).spawn(num_envs + 1)
    gens = [torch.Generator().manual_seed(int(s.generate_state(1, np.uint64)[0] >> np.uint64(1))) for s in streams]
    return gens[0], gens[1:]


class Collector:
    """Owns a chunk vector env and the sampler's random generators (one per sub-env)."""

    def __init__(self, venv, seed: int = 0):
        self.venv = venv
        self.generator, self.env_generators = sub_env_generators(seed, venv.num_envs)

    @property
    def num_envs(self) -> int:
        return self.venv.num_envs

    def collect(self, policy: Policy, episodes: int, spec: RolloutSpec,
                task_episodes: list[int] | None = None) -> Batch:
        """At least ``episodes`` episodes (whole waves of every sub-env) sampled and recorded as
        ``spec`` says; or, with ``task_episodes``, exactly that many of each task."""
        if task_episodes is None:
            waves = [None] * math.ceil(episodes / self.num_envs)
        else:
            waves = self._wave_masks(task_episodes, spec.group_size)
        return Batch.concat([self.play_wave(policy, spec.noise_level, self.env_generators, record=spec, active=active)
                             for active in waves])

    def _wave_masks(self, task_episodes: list[int], group_size: int) -> list[np.ndarray]:
        """Active sub-envs of each wave so that task k plays ``task_episodes[k]`` episodes."""
        task_ids = np.asarray(self.venv.task_ids)
        per_task = [np.flatnonzero(task_ids == k) for k in range(len(self.venv.tasks))]
        if len(task_episodes) != len(per_task) or any(n % group_size for n in task_episodes):
            raise ValueError(f"task_episodes must give one count per task, each a multiple of {group_size}")
        waves = max(math.ceil(n / len(envs)) for n, envs in zip(task_episodes, per_task))
        masks = [np.zeros(self.num_envs, dtype=bool) for _ in range(waves)]
        for n, envs in zip(task_episodes, per_task):
            for w in range(waves):
                masks[w][envs[: max(0, min(len(envs), n - w * len(envs)))]] = True
        return [m for m in masks if m.any()]

    def _group_seeds(self, active: np.ndarray, group_size: int) -> list[int | None]:
        """Reset seeds giving each group of ``group_size`` active sub-envs of a task one initial state."""
        seeds: list[int | None] = [None] * self.num_envs
        task_ids = np.asarray(self.venv.task_ids)
        for k in range(len(self.venv.tasks)):
            envs = np.flatnonzero(active & (task_ids == k))
            if len(envs) % group_size:
                raise ValueError(f"{len(envs)} sub-envs of task {self.venv.tasks[k]!r} in a wave do not split into "
                                 f"groups of {group_size}: make env.envs_per_task a multiple of the group size")
            for group in envs.reshape(-1, group_size):
                # Far above evaluation seeds and below demonstration seeds (stepnft.data.demos).
                seed = int(torch.randint(2**24, 2**31, (1,), generator=self.generator))
                for i in group:
                    seeds[i] = seed
        return seeds

    def _wave_plan(self, seeds: list[int] | None, record: RolloutSpec | None,
                   active: np.ndarray | None) -> tuple[list[int] | None, np.ndarray]:
        """A wave's reset seeds (drawn here for groups when ``record`` asks for them and none
        are given) and its active sub-envs (default: all)."""
        active = np.ones(self.num_envs, dtype=bool) if active is None else np.asarray(active, dtype=bool)
        if record is not None and record.group_size > 1 and seeds is None:
            seeds = self._group_seeds(active, record.group_size)
        return seeds, active

    def play_wave(self, policy: Policy, noise_level: float, generators: list[torch.Generator],
                  seeds: list[int] | None = None, record: RolloutSpec | None = None,
                  active: np.ndarray | None = None) -> Batch:
        """Every sub-env in ``active`` (default: all) plays one episode from
        ``reset(seed=seeds)``, sub-env ``i`` sampling with ``generators[i]``; the others sit the
        wave out. With ``record`` the batch holds the policy calls and recorded denoising
        steps, else only the episode table."""
        venv, n = self.venv, self.venv.num_envs
        horizon, action_dim = policy.chunk_shape
        n_exec = policy.config.n_exec
        seeds, active = self._wave_plan(seeds, record, active)
        if active.all():
            raw, _ = venv.reset(seed=seeds)
        else:
            venv.reset(seed=seeds, options={"reset_mask": active.copy()})
            raw, _ = venv.reset(options={"reset_mask": ~active, "idle": True})
        rows = np.flatnonzero(active)  # sub-envs playing: the rows of the episode table
        task_ids = torch.as_tensor(venv.task_ids)
        done = ~active
        success = np.zeros(n, dtype=bool)
        length = np.zeros(n, dtype=np.int64)
        stochastic_steps = record.stochastic_steps if record else "all"
        keep_path = record is not None and record.record_steps == "all"
        calls: list[dict[str, Tensor]] = []
        steps: list[dict[str, Tensor]] = []
        num_calls = 0
        while not done.all():
            playing = np.flatnonzero(~done)
            obs = {k: torch.as_tensor(v[playing]) for k, v in raw.items()} | {"task": task_ids[playing]}
            # Processed on the CPU, sampled on the policy's device, the chunk back on the CPU.
            sample = to_device(policy.sample(policy.prepare(obs), noise_level=noise_level,
                                             generator=[generators[i] for i in playing],
                                             stochastic_steps=stochastic_steps, keep_path=keep_path), "cpu")
            chunk = np.zeros((n, n_exec, policy.config.action_dim), dtype=np.float32)
            chunk[playing] = policy.env_actions(sample.actions[:, :n_exec]).clamp(-1.0, 1.0).numpy()
            raw, reward, terminated, truncated, info = venv.step(chunk)
            executed = np.asarray(info["steps"])[playing]
            length[playing] += executed
            success |= np.asarray(info["success"], dtype=bool) & ~done
            ended = (np.asarray(terminated) | np.asarray(truncated))[playing]
            done[playing] |= ended
            if record is not None:
                calls.append({
                    "obs": obs, "actions": sample.actions,
                    "mask": torch.arange(horizon)[None, :] < torch.as_tensor(executed)[:, None],
                    "reward": torch.as_tensor(np.asarray(reward, dtype=np.float32)[playing]),
                    "done": torch.as_tensor(ended),
                    "episode": torch.as_tensor(np.searchsorted(rows, playing), dtype=torch.int64),
                })
                step = sample.recorded_steps(every_step=keep_path)
                step["call"] = step["call"] + num_calls
                steps.append(step)
                num_calls += len(playing)
        seed_of = [-1 if seeds is None or seeds[i] is None else seeds[i] for i in rows]
        episodes = {
            "episode_success": torch.as_tensor(success[rows]), "episode_task": task_ids[rows].clone(),
            "episode_length": torch.as_tensor(length[rows]), "episode_seed": torch.as_tensor(seed_of, dtype=torch.int64),
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
        """The sub-envs' RNG states and the generators: enough to resume exactly."""
        return {"env_rng": self.venv.rng_state(), "generator": self.generator.get_state(),
                "env_generators": [g.get_state() for g in self.env_generators]}

    def load_state_dict(self, state: dict) -> None:
        self.venv.set_rng_state(state["env_rng"])
        self.generator.set_state(state["generator"])
        for g, g_state in zip(self.env_generators, state["env_generators"], strict=True):
            g.set_state(g_state)

    def pop_metrics(self) -> dict[str, float]:
        """Metrics of the collector itself since the last call (a remote collector's weight
        pushes and lost episodes); none here."""
        return {}

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
