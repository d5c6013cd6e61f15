"""ManiSkill3's GPU-parallel physics behind the chunk vector env interface (``env.sim_backend: gpu``).

On a GPU, ManiSkill simulates many copies of one task as the scenes of one batched env
(``gym.make(task, num_envs=N, sim_backend="gpu")``): every ``step`` advances all N scenes at
once and takes ``[N, 7]`` actions; ``reset(options={"env_idx": idx})`` resets some of them.
:class:`ManiSkillGPUVecEnv` puts one such env per task behind what stepnft's collector expects
of a vector env (``stepnft.envs.base``: ``send_ops`` / ``receive_ops``, the task layout, the
chunk env contract per sub-env), so training, evaluation and ``stepnft compare`` run unchanged.

How the contract maps onto batched physics:

- **One lane.** A batched env cannot step some scenes and leave the others: every op batch the
  collector sends must cover every sub-env in an episode, so all sub-envs form one lane (the
  collector then samples the whole batch in one policy call, on the GPU with ``--device cuda``).
- **Steps, then resets.** A batch of ops runs its chunks first (``n_exec`` batched env steps;
  scenes with no step op, or whose episode ended inside the chunk, get zero actions and their
  results are no longer read), then its resets. So no physics runs between a reset and the
  first chunk of its episode: the policy acts on the state the reset returned.
- **Initial states per seed.** ManiSkill's tasks draw initial states with ``torch.rand`` over
  the scenes being reset, seeded once per reset call: a group reset would make a scene's start
  depend on the group. Each reset op is therefore its own partial reset of one scene, seeded
  with the op's seed, so the initial state depends only on (task, seed), as the CPU backend's
  does (the values differ from the CPU backend's: CUDA's generator is not the CPU's).
- **Chunk bookkeeping** per sub-env is the CPU env's (``ChunkEpisode``): success at any env
  step so far, termination at success, truncation at ``max_episode_steps``, a no-op step on an
  ended episode, ``info`` with ``success``, ``steps`` and ``episode_steps``.

Observations leave the GPU once per chunk (the collector's protocol is per sub-env numpy
arrays); cameras render every scene once per op batch through ManiSkill's sensors.

Not run on a GPU here (no GPU machine could carry ManiSkill's 101 MB wheel): the tests drive
this class with a stand-in for ManiSkill's batched env that follows its API (docs/maniskill.md).
"""

from __future__ import annotations

import collections
from collections.abc import Callable, Sequence
from typing import Any

import gymnasium as gym
import numpy as np
import torch
from gymnasium.utils import seeding

from stepnft.envs.base import ChunkEpisode, checked_chunk
from stepnft.envs.maniskill.tasks import STATE_DIM, TASKS

ACTION_DIM = 7


class _Scene(ChunkEpisode):
    """One sub-env's episode bookkeeping and latest observation."""

    def __init__(self, max_episode_steps: int, terminate_on_success: bool, seed: int):
        self.max_episode_steps = max_episode_steps
        self.terminate_on_success = terminate_on_success
        self.np_random, _ = seeding.np_random(seed)
        self.obs: dict[str, np.ndarray] | None = None


class ManiSkillGPUVecEnv:
    """``len(tasks) * envs_per_task`` sub-envs; sub-env ``i`` runs ``tasks[i // envs_per_task]``
    as scene ``i % envs_per_task`` of that task's batched ManiSkill env (see the module doc).

    ``make(task, **kwargs)`` builds a batched env (default: ``make_maniskill_env``, i.e.
    ``gym.make``); tests pass a stand-in. ``device`` is the simulation's CUDA device.
    """

    num_workers = 0

    def __init__(self, tasks: Sequence[str], instructions: Sequence[str], task_ids: np.ndarray,
                 instruction_variants: list[list[str]] | None = None, *, n_exec: int = 4,
                 max_episode_steps: int = 200, terminate_on_success: bool = True, seed: int = 0,
                 cameras: Sequence[str] = (), image_size: int = 64, device: str = "cuda",
                 make: Callable[..., gym.Env] | None = None):
        from stepnft.envs.maniskill.env import CONTROL_MODE, MAX_EPISODE_STEPS, make_maniskill_env

        self.tasks = list(tasks)
        self.instructions = list(instructions)
        self.instruction_variants = instruction_variants or [[i] for i in self.instructions]
        self.task_ids = np.asarray(task_ids, dtype=np.int64)
        self.task_names = [self.tasks[i] for i in self.task_ids]
        self.num_envs = len(self.task_ids)
        self.lanes = np.zeros(self.num_envs, dtype=np.int64)  # one lane: see the module doc
        if not 1 <= max_episode_steps <= MAX_EPISODE_STEPS:
            raise ValueError(f"max_episode_steps must be in [1, {MAX_EPISODE_STEPS}], got {max_episode_steps}")
        self.n_exec = n_exec
        self.cameras = list(cameras)
        self.action_space = gym.spaces.Box(-1.0, 1.0, (n_exec, ACTION_DIM), np.float32)
        # Sub-env i is scene `scene[i]` of the batched env of its task.
        self.scene = np.zeros(self.num_envs, dtype=np.int64)
        for k in range(len(self.tasks)):
            mine = np.flatnonzero(self.task_ids == k)
            self.scene[mine] = np.arange(len(mine))
        env_seeds = np.random.SeedSequence(seed).generate_state(self.num_envs)
        self._scenes = [_Scene(max_episode_steps, terminate_on_success, int(s)) for s in env_seeds]
        make = make or make_maniskill_env
        kwargs: dict[str, Any] = dict(
            obs_mode="state", control_mode=CONTROL_MODE, reward_mode="normalized_dense",
            sim_backend=device if device.startswith("cuda") else "gpu",
            render_backend=device if (cameras and device.startswith("cuda")) else ("gpu" if cameras else "none"),
            max_episode_steps=10**9)  # stepnft counts episode steps itself
        if cameras:
            kwargs["sensor_configs"] = dict(width=image_size, height=image_size)
        self._envs: list[gym.Env] = []
        try:
            for k, task in enumerate(self.tasks):
                if task not in TASKS:
                    raise ValueError(f"unknown ManiSkill task {task!r}; valid names: {', '.join(TASKS)}")
                self._envs.append(make(task, num_envs=int((self.task_ids == k).sum()), **kwargs))
            for env in self._envs:
                unknown = [c for c in self.cameras if c not in env.unwrapped._sensors]
                if unknown:
                    raise ValueError(f"unknown ManiSkill camera {unknown[0]!r}; its cameras: "
                                     f"{', '.join(env.unwrapped._sensors)}")
                # A first full reset: the batched env must be reset before any partial reset or step.
                env.reset(seed=[int(s) for s in np.random.SeedSequence([seed, 1]).generate_state(env.unwrapped.num_envs)])
        except BaseException:
            self.close()
            raise
        self._replies: collections.deque[list] = collections.deque()

    # --- the collector's protocol ----------------------------------------------------------------
    def send_ops(self, ops: Sequence[tuple[int, str, Any]]) -> None:
        """``(i, "reset", seed)`` / ``(i, "step", chunk)``: run here, now, steps before resets
        (module doc); the results come back in op order from :meth:`receive_ops`."""
        self._replies.append(self._run(ops))

    def receive_ops(self) -> list:
        return self._replies.popleft()

    def _run(self, ops: Sequence[tuple[int, str, Any]]) -> list:
        results: list[Any] = [None] * len(ops)
        stepping = [(n, int(i), arg) for n, (i, op, arg) in enumerate(ops) if op == "step"]
        if len(set(int(i) for i, _, _ in ops)) != len(ops):
            raise ValueError("one op per sub-env per batch: a batched env steps every scene at once")
        if stepping:
            for n, i, result in self._step_chunks(stepping):
                results[n] = result
        for n, (i, op, arg) in enumerate(ops):
            if op == "reset":
                results[n] = self._reset_one(int(i), arg)
            elif op != "step":
                raise ValueError(f"unknown op {op!r}")
        return results

    def _step_chunks(self, stepping: list[tuple[int, int, Any]]) -> list[tuple[int, int, tuple]]:
        chunks, live = {}, []
        for n, i, chunk in stepping:
            scene = self._scenes[i]
            chunks[i] = np.clip(checked_chunk(chunk, self.action_space, scene.obs is not None), -1.0, 1.0)
            if not scene._ended:
                live.append(i)
        steps = dict.fromkeys(chunks, 0)
        rewards = dict.fromkeys(chunks, 0.0)
        last_obs: dict[int, np.ndarray] = {}
        active = set(live)
        for row in range(self.n_exec):
            if not active:
                break
            for k, env in enumerate(self._envs):
                mine = [i for i in active if self.task_ids[i] == k]
                if not mine:
                    continue
                actions = np.zeros((env.unwrapped.num_envs, ACTION_DIM), dtype=np.float32)
                for i in mine:
                    actions[self.scene[i]] = chunks[i][row]
                obs, reward, _, _, info = env.step(torch.as_tensor(actions, device=env.unwrapped.device))
                obs, reward = _numpy(obs), _numpy(reward).reshape(-1)
                success = _numpy(info["success"]).reshape(-1).astype(bool)
                for i in mine:
                    s = self.scene[i]
                    steps[i] += 1
                    rewards[i] += float(reward[s])
                    last_obs[i] = obs[s]
                    if self._scenes[i]._count_step(bool(success[s])):
                        active.discard(i)
        for i in last_obs:
            self._scenes[i].obs = {"state": _padded(last_obs[i])}
        self._render(sorted(last_obs))
        out = []
        for n, i, _ in stepping:
            scene = self._scenes[i]
            out.append((n, i, (_copy(scene.obs), rewards[i], scene._terminated, scene._truncated,
                               scene._info(steps[i]))))
        return out

    def _reset_one(self, i: int, seed: int | None) -> tuple[dict, dict]:
        from stepnft.envs.maniskill.env import maniskill_seed

        scene = self._scenes[i]
        episode_seed = int(scene.np_random.integers(2**31)) if seed is None else maniskill_seed(int(seed))
        env = self._envs[self.task_ids[i]]
        idx = torch.as_tensor([int(self.scene[i])], device=env.unwrapped.device)
        obs, _ = env.reset(seed=[episode_seed], options={"env_idx": idx})
        scene.obs = {"state": _padded(_numpy(obs)[self.scene[i]])}
        self._render([i])
        scene._start_episode()
        return _copy(scene.obs), scene._info(steps=0)

    def _render(self, subs: Sequence[int]) -> None:
        """Each named camera of the tasks of ``subs``, one capture per task for all its scenes."""
        if not self.cameras or not subs:
            return
        for k in sorted({int(self.task_ids[i]) for i in subs}):
            base = self._envs[k].unwrapped
            for obj in base._hidden_objects:
                obj.hide_visual()
            base.scene.update_render(update_sensors=True, update_human_render_cameras=False)
            views = []
            for name in self.cameras:
                sensor = base._sensors[name]
                sensor.capture()
                rgb = sensor.get_obs(rgb=True, depth=False, position=False, segmentation=False)["rgb"]
                views.append(_numpy(rgb).transpose(0, 3, 1, 2))  # [scenes, 3, H, W]
            images = np.stack(views, axis=1).astype(np.uint8)  # [scenes, V, 3, H, W]
            for i in subs:
                if self.task_ids[i] == k:
                    self._scenes[i].obs["image"] = images[self.scene[i]]

    # --- gymnasium-style batch calls (cli checks, tests) -----------------------------------------
    def reset(self, *, seed: int | Sequence[int] | None = None, options: dict | None = None):
        """Resets every sub-env (``seed``: one per sub-env, or one int for the first and the
        next ones after it, as gymnasium's vector envs do); returns stacked observations."""
        if seed is None:
            seeds = [None] * self.num_envs
        elif isinstance(seed, int):
            seeds = [seed + i for i in range(self.num_envs)]
        else:
            seeds = list(seed)
            if len(seeds) != self.num_envs:
                raise ValueError(f"expected {self.num_envs} seeds, got {len(seeds)}")
        results = self._run([(i, "reset", s) for i, s in enumerate(seeds)])
        return _stack([r[0] for r in results]), _stack_info([r[1] for r in results])

    def step(self, actions: np.ndarray):
        """Steps every sub-env with its chunk ``actions[i]``; returns stacked results."""
        results = self._run([(i, "step", actions[i]) for i in range(self.num_envs)])
        obs, reward, terminated, truncated, info = zip(*results)
        return (_stack(obs), np.asarray(reward), np.asarray(terminated), np.asarray(truncated), _stack_info(info))

    def rng_state(self) -> list[dict]:
        """Each sub-env's RNG state (for unseeded resets), as ``ChunkVecEnv.rng_state``."""
        return [scene.np_random.bit_generator.state for scene in self._scenes]

    def set_rng_state(self, states: list[dict]) -> None:
        for scene, state in zip(self._scenes, states, strict=True):
            scene.np_random.bit_generator.state = state

    def close(self) -> None:
        for env in self._envs:
            env.close()
        self._envs = []


def _numpy(x) -> np.ndarray:
    return x.detach().cpu().numpy() if isinstance(x, torch.Tensor) else np.asarray(x)


def _padded(values: np.ndarray) -> np.ndarray:
    state = np.zeros(STATE_DIM, dtype=np.float32)
    values = np.asarray(values, dtype=np.float32).reshape(-1)
    state[: len(values)] = values
    return state


def _copy(obs: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
    return {k: v.copy() for k, v in obs.items()}


def _stack(obs: Sequence[dict[str, np.ndarray]]) -> dict[str, np.ndarray]:
    return {k: np.stack([o[k] for o in obs]) for k in obs[0]}


def _stack_info(infos: Sequence[dict]) -> dict[str, np.ndarray]:
    return {k: np.asarray([info[k] for info in infos]) for k in infos[0]}
