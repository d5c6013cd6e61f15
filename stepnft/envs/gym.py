"""Any Gymnasium env as a stepnft simulator (``env.name: gym``).

A user brings an env id (a registered one, or ``module:Env-v0``, whose module Gymnasium imports
first, which registers it) and says in the config what stepnft cannot read off the env:

- which observation entries are the policy's ``state`` (``env.state_keys``: keys of a Dict
  observation, nested ones written ``a/b``, each flattened and concatenated in that order; none:
  a Box observation whole, or every vector entry of a Dict one) and which are camera images
  (``env.cameras``: entries holding ``[H, W, 3]`` uint8 frames, or ``render`` for the env's
  ``render()`` frames), resized to ``env.image_size``;
- what success is (``env.success``): ``auto`` reads ``info["is_success"]``, else
  ``info["success"]``; another name reads that info key; ``module:function`` calls
  ``function(obs, info) -> bool`` on the raw observation;
- each task's instruction (``env.instructions``; default: the id's name, ``PushT-v0``);
- where demonstrations come from: a user's expert (``env.expert: module:factory``, called as
  ``factory(task, seed)`` for a callable ``raw_obs -> action``), or a dataset on disk
  (``--demos.path``: a LeRobot dataset folder or robomimic-style HDF5, ``stepnft.envs.datasets``).

Actions: the policy acts in [-1, 1]; a Box action space with finite bounds is mapped onto them
linearly (a user's expert and a dataset speak the env's own units, mapped back the same way).
The env's own ``terminated``/``truncated`` end an episode too (a failure that ends the episode
counts as one). Seeding follows Gymnasium: ``reset(seed=s)`` starts from the state of seed ``s``,
an unseeded reset continues the env's stream, which checkpoints save (exact resume).

Nothing here names a third-party package; the env is built with ``gymnasium.make`` in the
process that steps it (a worker process or a Ray actor alike).
"""

from __future__ import annotations

import dataclasses
import functools
import importlib
from collections.abc import Callable, Sequence
from typing import Any

import gymnasium as gym
import numpy as np

from stepnft.envs.base import ChunkEpisode, Expert, Simulator, checked_chunk
from stepnft.envs.datasets import resized

AUTO_SUCCESS_KEYS = ("is_success", "success")
"""The info keys ``env.success: auto`` reads, in order (Gymnasium-Robotics and most robot envs
report ``is_success``; MetaWorld and ManiSkill ``success``)."""
RENDER = "render"
"""The camera name that means the env's own ``render()`` frame (``render_mode="rgb_array"``)."""


def task_name(env_id: str) -> str:
    """A task's name from its env id: the id's own name, without module or namespace
    (``gym_pusht:gym_pusht/PushT-v0`` -> ``PushT-v0``): it names files and metrics."""
    return env_id.rpartition(":")[2].rpartition("/")[2]


def load_object(target: str, what: str):
    """``module:attribute`` imported; a ValueError in one line when it cannot be."""
    module, _, attr = target.partition(":")
    if not module or not attr:
        raise ValueError(f"{what} {target!r} must be 'module:name'")
    try:
        obj = importlib.import_module(module)
    except Exception as err:  # ImportError, or an error while the module runs
        raise ValueError(f"{what} {target!r}: cannot import {module} ({type(err).__name__}: {err})") from None
    for part in attr.split("."):
        if not hasattr(obj, part):
            raise ValueError(f"{what} {target!r}: {module} has no {attr}")
        obj = getattr(obj, part)
    return obj


@dataclasses.dataclass(frozen=True)
class GymSpec:
    """What ``env.name: gym`` reads from an ``EnvConfig`` (hashable: one probe per spec and process)."""

    ids: tuple[str, ...]
    make_kwargs: tuple[tuple[str, Any], ...] = ()
    state_keys: tuple[str, ...] = ()
    cameras: tuple[str, ...] = ()
    success: str = "auto"
    instructions: tuple[tuple[str, str], ...] = ()
    expert: str | None = None

    @classmethod
    def from_config(cls, env_cfg) -> "GymSpec":
        return cls(tuple(env_cfg.id), tuple(sorted(env_cfg.make_kwargs.items())), tuple(env_cfg.state_keys),
                   tuple(env_cfg.cameras), env_cfg.success, tuple(sorted(env_cfg.instructions.items())),
                   env_cfg.expert)

    @property
    def tasks(self) -> list[str]:
        return [task_name(i) for i in self.ids]

    def env_id(self, task: str) -> str:
        """The Gymnasium id behind task name ``task`` (one of :attr:`tasks`)."""
        return self.ids[self.tasks.index(task)]


def make_gym_env(env_id: str, make_kwargs: dict, max_episode_steps: int | None = None, render: bool = False) -> gym.Env:
    """``gymnasium.make`` with one-line errors (an id that is not registered, a module that does
    not import, kwargs the env refuses)."""
    kwargs = dict(make_kwargs)
    if render:
        kwargs.setdefault("render_mode", "rgb_array")
    if max_episode_steps is not None:
        kwargs["max_episode_steps"] = max_episode_steps
    try:
        return gym.make(env_id, disable_env_checker=True, **kwargs)
    except gym.error.Error as err:  # NameNotFound, VersionNotFound, ...
        raise ValueError(f"env.id {env_id!r}: {err} (register it, or give module:Env-v0 to import its module "
                         "first)") from None
    except (ImportError, ModuleNotFoundError) as err:
        raise ValueError(f"env.id {env_id!r}: cannot import its module ({err}); install the package that "
                         "provides it") from None
    except TypeError as err:
        raise ValueError(f"env.id {env_id!r} refuses env.make_kwargs {kwargs}: {err}") from None


def _entry(obs, key: str, what: str):
    value = obs
    for part in key.split("/"):
        if not isinstance(value, dict) or part not in value:
            keys = ", ".join(_leaf_keys(obs)) or "none (a Box observation)"
            raise ValueError(f"{what} {key!r} is not in the observation; its keys: {keys}")
        value = value[part]
    return value


def _leaf_keys(obs, prefix: str = "") -> list[str]:
    if not isinstance(obs, dict):
        return []
    keys = []
    for k, v in obs.items():
        keys += _leaf_keys(v, f"{prefix}{k}/") if isinstance(v, dict) else [f"{prefix}{k}"]
    return keys


def default_state_keys(obs) -> tuple[str, ...]:
    """Every vector entry of a Dict observation (no images), in its order; () for a Box one."""
    entries = {k: np.asarray(_entry(obs, k, "")) for k in _leaf_keys(obs)}
    return tuple(k for k, v in entries.items() if v.dtype != np.uint8 and v.ndim <= 1)


class ActionMap:
    """Box action space <-> the policy's [-1, 1]: linear where both bounds are finite."""

    def __init__(self, space: gym.Space):
        if not isinstance(space, gym.spaces.Box) or len(space.shape) != 1:
            raise ValueError(f"env.name gym needs a flat Box action space, the env has {space}")
        low, high = space.low.astype(np.float64), space.high.astype(np.float64)
        finite = np.isfinite(low) & np.isfinite(high)
        self.mid = np.where(finite, (low + high) / 2, 0.0)
        self.half = np.where(finite, (high - low) / 2, 1.0)
        self.dtype = space.dtype
        self.dim = space.shape[0]

    def to_env(self, action: np.ndarray) -> np.ndarray:
        return (self.mid + self.half * np.asarray(action, dtype=np.float64)).astype(self.dtype)

    def to_policy(self, action: np.ndarray) -> np.ndarray:
        return np.clip((np.asarray(action, dtype=np.float64) - self.mid) / self.half, -1.0, 1.0)


class Observer:
    """The raw observation and info -> the chunk env's ``state``, ``image`` and success."""

    def __init__(self, spec: GymSpec, raw_obs, image_size: int = 64):
        self.state_keys = spec.state_keys or default_state_keys(raw_obs)
        self.cameras = spec.cameras
        self.image_size = image_size
        self.success_fn = load_object(spec.success, "env.success") if ":" in spec.success else None
        self.success_key = None if self.success_fn else spec.success
        if isinstance(raw_obs, dict) and not self.state_keys:
            raise ValueError(f"the observation holds no vector entries for the state (keys: "
                             f"{', '.join(_leaf_keys(raw_obs))}): name them in env.state_keys")
        for key in self.state_keys:
            if not isinstance(raw_obs, dict):
                raise ValueError(f"env.state_keys {list(self.state_keys)}: the observation is a Box, not a Dict; "
                                 "leave env.state_keys empty")
            _entry(raw_obs, key, "env.state_keys entry")
        for camera in self.cameras:
            if camera != RENDER:
                frame = np.asarray(_entry(raw_obs, camera, "env.cameras entry"))
                if frame.dtype != np.uint8 or frame.ndim != 3 or frame.shape[-1] != 3:
                    raise ValueError(f"env.cameras entry {camera!r} holds {frame.dtype} {frame.shape}, not a uint8 "
                                     "[H, W, 3] image")
        self.state_dim = len(self.state(raw_obs))

    def state(self, raw_obs) -> np.ndarray:
        if not self.state_keys:
            return np.asarray(raw_obs, dtype=np.float32).ravel()
        return np.concatenate([np.asarray(_entry(raw_obs, k, ""), dtype=np.float32).ravel() for k in self.state_keys])

    def image(self, raw_obs, env: gym.Env) -> np.ndarray:
        frames = [np.asarray(env.render() if camera == RENDER else _entry(raw_obs, camera, ""), dtype=np.uint8)
                  for camera in self.cameras]
        return np.stack([resized(f, self.image_size, self.image_size).transpose(2, 0, 1) for f in frames])

    def success(self, raw_obs, info: dict) -> bool | None:
        """This step's success; None when the info holds no success signal."""
        if self.success_fn is not None:
            return bool(self.success_fn(raw_obs, info))
        keys = AUTO_SUCCESS_KEYS if self.success_key == "auto" else (self.success_key,)
        for key in keys:
            if key in info:
                return bool(np.asarray(info[key]).any())
        return None


class GymChunkEnv(ChunkEpisode, gym.Env):
    """One Gymnasium env behind the chunk env contract (``stepnft.envs.base``)."""

    def __init__(self, spec: GymSpec, task: str, n_exec: int = 1, max_episode_steps: int = 200,
                 terminate_on_success: bool = True, seed: int = 0, render_size: tuple[int, int] | None = None,
                 image_size: int = 64):
        env_id = spec.env_id(task)
        renders = render_size is not None or RENDER in spec.cameras
        self._env = make_gym_env(env_id, dict(spec.make_kwargs), max_episode_steps, render=renders)
        self.render_size = render_size
        self.n_exec, self.max_episode_steps, self.terminate_on_success = n_exec, max_episode_steps, terminate_on_success
        self.actions = ActionMap(self._env.action_space)
        raw, _ = self._env.reset(seed=seed)  # seeds the env's stream: unseeded resets continue it
        self.observer = Observer(spec, raw, image_size)
        spaces = {"state": gym.spaces.Box(-np.inf, np.inf, (self.observer.state_dim,), np.float32)}
        if spec.cameras:
            spaces["image"] = gym.spaces.Box(0, 255, (len(spec.cameras), 3, image_size, image_size), np.uint8)
        self.observation_space = gym.spaces.Dict(spaces)
        self.action_space = gym.spaces.Box(-1.0, 1.0, (n_exec, self.actions.dim), np.float32)
        self.raw_obs = None
        """The env's own last observation (what a user's expert reads)."""
        self.episodes = 0
        """Episodes begun (an expert's cue to start afresh)."""
        self._obs: dict | None = None

    # The collector saves and restores every sub-env's stream (exact resume): the Gymnasium env's.
    @property
    def np_random(self) -> np.random.Generator:
        return self._env.unwrapped.np_random

    @np_random.setter
    def np_random(self, value: np.random.Generator) -> None:
        self._env.unwrapped.np_random = value

    @property
    def raw_env(self) -> gym.Env:
        """The user's Gymnasium env this chunk env steps (in its own action units: ``actions.to_env``)."""
        return self._env

    def _observe(self, raw) -> dict:
        self.raw_obs = raw
        obs = {"state": self.observer.state(raw)}
        if self.observer.cameras:
            obs["image"] = self.observer.image(raw, self._env)
        return obs

    def reset(self, *, seed: int | None = None, options: dict[str, Any] | None = None):
        if options and options.get("idle"):  # sit a batch step out: no simulation, the stream untouched
            self._start_episode(idle=True)
            if self._obs is None:
                self._obs = {k: np.zeros(s.shape, s.dtype) for k, s in self.observation_space.spaces.items()}
            return {k: v.copy() for k, v in self._obs.items()}, self._info(0)
        raw, _ = self._env.reset(seed=seed)
        self._obs = self._observe(raw)
        self._start_episode()
        self.episodes += 1
        return {k: v.copy() for k, v in self._obs.items()}, self._info(0)

    def step(self, chunk: np.ndarray):
        chunk = checked_chunk(chunk, self.action_space, self._obs is not None)
        if self._ended:
            return {k: v.copy() for k, v in self._obs.items()}, 0.0, self._terminated, self._truncated, self._info(0)
        reward, steps = 0.0, 0
        for action in np.clip(chunk, -1.0, 1.0):
            raw, r, terminated, truncated, info = self._env.step(self.actions.to_env(action))
            reward, steps = reward + float(r), steps + 1
            success = self.observer.success(raw, info)
            if success is None:
                raise ValueError(f"the env's info has no success signal (keys: {', '.join(info) or 'none'}): set "
                                 "env.success to its key, or to module:function(obs, info) -> bool")
            ended = self._count_step(success)
            # The env's own end (a failure it detects, its time limit) ends the episode too.
            self._terminated, self._truncated = self._terminated or terminated, self._truncated or truncated
            if ended or terminated or truncated:
                break
        self._obs = self._observe(raw)
        return {k: v.copy() for k, v in self._obs.items()}, reward, self._terminated, self._truncated, self._info(steps)

    def render(self) -> np.ndarray:
        frame = np.asarray(self._env.render(), dtype=np.uint8)
        return frame if self.render_size is None else resized(frame, *self.render_size)

    def close(self) -> None:
        self._env.close()


class GymExpert(Expert):
    """A user's expert (``env.expert``) acting on the raw observation of the env it is attached
    to, its actions mapped to the policy's [-1, 1]. The factory is called anew for every episode
    (experts often keep a phase), with a seed drawn from (``seed``, episode number)."""

    def __init__(self, factory: Callable[[str, int], Callable[[Any], np.ndarray]], task: str, seed: int):
        self._factory, self._task, self._seed = factory, task, seed
        self._env, self._act, self._episode = None, None, None

    def attach(self, env: GymChunkEnv) -> None:
        self._env = env

    def act(self, obs: dict[str, np.ndarray]) -> np.ndarray:
        if self._env is None:
            raise RuntimeError("attach the expert to its env first (GymExpert.attach)")
        if self._episode != self._env.episodes:  # a new episode: a fresh expert
            self._episode = self._env.episodes
            seed = int(np.random.SeedSequence([self._seed, self._episode]).generate_state(1)[0])
            self._act = self._factory(self._task, seed)
        return self._env.actions.to_policy(self._act(self._env.raw_obs))


class GymSimulator(Simulator):
    """``env.name: gym``: configured from an ``EnvConfig`` (:meth:`configured`), which builds one
    env of the first task to read the sizes and check the config's keys before any work."""

    name = "gym"
    label = "Gymnasium env"
    distribution = "gymnasium"
    spec: GymSpec | None = None
    image_size = 64
    action_maps: dict[str, ActionMap] = {}
    """Each task's :class:`ActionMap` (read by :func:`_configured`'s probe)."""

    def configured(self, env_cfg) -> "GymSimulator":
        return _configured(GymSpec.from_config(env_cfg), env_cfg.image_size)

    def _spec(self) -> GymSpec:
        if self.spec is None:
            raise ValueError("env.name gym needs its env config: build it with stepnft.envs.simulator_for(env_cfg)")
        return self.spec

    def task_names(self) -> list[str]:
        return self._spec().tasks

    def instruction(self, task: str) -> str:
        return dict(self._spec().instructions).get(task, task)

    def make_env(self, task, n_exec=1, max_episode_steps=200, terminate_on_success=True, seed=0, render_size=None,
                 **options):
        unknown = sorted(set(options) - {"cameras", "image_size"})
        if unknown:
            raise ValueError(f"{self.label} has no {', '.join(unknown)} options (perturbations, state_obs and a shaped "
                             "reward are the simulators' own)")
        spec = self._spec()
        if "cameras" in options:
            spec = dataclasses.replace(spec, cameras=tuple(options["cameras"]))
        return GymChunkEnv(spec, task, n_exec, max_episode_steps, terminate_on_success, seed, render_size,
                           options.get("image_size", self.image_size))

    def expert(self, task: str, seed: int) -> Expert:
        spec = self._spec()
        if spec.expert is None:
            raise ValueError(f"{self.label} {task} has no expert to record demonstrations with: set env.expert to "
                             "module:factory (factory(task, seed) -> callable(obs) -> action), or point --demos.path "
                             "at a LeRobot dataset folder or HDF5 demonstrations")
        return GymExpert(load_object(spec.expert, "env.expert"), task, seed)

    def has_dataset(self, path) -> bool:
        from stepnft.envs.datasets import dataset_format

        return dataset_format(path) is not None

    def load_dataset(self, path, cameras: Sequence[str] = (), image_size: int = 64) -> list:
        from stepnft.envs.datasets import load_dataset

        return load_dataset(path, self, self.action_maps, cameras, image_size, self._spec().state_keys)


@functools.lru_cache(maxsize=16)
def _configured(spec: GymSpec, image_size: int) -> GymSimulator:
    """A :class:`GymSimulator` for ``spec``: one env per task built, reset and stepped once with
    the middle action, so a missing success signal, key or module is one line before any work."""
    sim = GymSimulator()
    sim.spec, sim.image_size, sim.action_maps = spec, image_size, {}
    dims = set()
    for task in spec.tasks:
        env = sim.make_env(task, image_size=image_size)
        try:
            env.reset(seed=0)
            env.step(np.zeros(env.action_space.shape, np.float32))  # raises without a success signal
            dims.add((env.observer.state_dim, env.actions.dim))
            sim.action_maps[task] = env.actions
            sim.control_hz = float(env._env.metadata.get("render_fps") or 20.0)
        finally:
            env.close()
    if len(dims) > 1:
        raise ValueError(f"one policy serves every task: env.id {list(spec.ids)} have different (state, action) sizes "
                         f"{sorted(dims)}")
    sim.state_dim, sim.action_dim = dims.pop()
    sim.label = f"Gymnasium env {', '.join(spec.ids)}"
    return sim
