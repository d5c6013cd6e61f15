"""The environment interface every simulator implements.

A :class:`Simulator` names its tasks and their instructions, builds single *chunk envs*
(gymnasium envs whose action is a chunk of ``n_exec`` low-level actions) and batches them in a
:class:`ChunkVecEnv`. The rest of stepnft sees only this interface: the collector plays
episodes through a ``ChunkVecEnv``, demonstrations come from ``Simulator.expert``, videos from
``Simulator.make_env(render_size=...)``.

Chunk env contract (one task):
    observation: dict with ``state`` float32 [S]; with cameras ``image`` uint8 [V, 3, H, W];
        with semantic perturbations ``instruction`` int64 (index into the task's
        ``Simulator.instruction_variants``)
    action: float32 [n_exec, A] in [-1, 1], run row by row
    step -> obs, summed reward, terminated, truncated, info with
        ``success`` (bool, success at any step of this episode so far),
        ``steps`` (env steps run by this call), ``episode_steps`` (since reset)
    ``reset(seed=s)`` gives an initial state that depends only on (task, s); an unseeded reset
    continues the env's own stream. Stepping an ended episode is a no-op: same observation,
    reward 0, the same flags, ``steps`` 0, so a batch can keep stepping its finished members.
    ``reset(options={"idle": True})`` sits a batch step out: the env does not simulate, leaves
    its RNG alone and is ended at once (truncated, ``episode_steps`` 0).

Vector envs (:class:`ChunkVecEnv` in this process, :class:`ShardedChunkVecEnv` in worker
processes) lay sub-envs out task by task and split them into *lanes* (:func:`lane_ids`, over
:func:`lane_count` lanes; every lane holds a share of every task). Besides
gymnasium's batch ``reset``/``step`` they take ``send_ops``/``receive_ops``: reset or step any
subset without waiting for the others, so the collector can compute one lane's actions while
another is stepped. With two or more workers each worker owns one lane, and
``ShardedChunkVecEnv.run_in_workers`` runs a function beside a worker's sub-envs (the collector
plays a whole lane there, policy included).
"""

from __future__ import annotations

import collections
import multiprocessing
from abc import ABC, abstractmethod
from collections.abc import Callable, Sequence
from functools import partial
from typing import Any, ClassVar

import gymnasium as gym
import numpy as np
from gymnasium.vector import AutoresetMode

from stepnft.envs.perturbations import Perturbations
from stepnft.envs.sharded import ShardedVectorEnv


LANES = 2
"""Lanes of a vector env in this process or in one worker process (see the module doc): two, so
that one is stepped while the actions of the other are computed. With more worker processes
there is one lane per worker. A run's episodes depend on its lanes, not on where they play: the
same seed gives the same batch with 0, 1 or 2 workers."""


def lane_count(num_workers: int) -> int:
    """Lanes of a vector env with ``num_workers`` worker processes: ``LANES``, or one per worker."""
    return max(LANES, num_workers)


def lane_ids(task_ids: np.ndarray, lanes: int = LANES) -> np.ndarray:
    """``[N]`` the lane of every sub-env: its place among the sub-envs of its task plus its task
    index, mod ``lanes``. Every lane gets a share of every task that has enough sub-envs, and
    tasks with fewer sub-envs than lanes are spread over the lanes."""
    task_ids = np.asarray(task_ids)
    place = np.zeros(len(task_ids), dtype=np.int64)
    for k in np.unique(task_ids):
        mine = np.flatnonzero(task_ids == k)
        place[mine] = np.arange(len(mine))
    return (place + task_ids) % lanes


class RenderingError(RuntimeError):
    """Offscreen rendering is unavailable on this machine."""


class Expert(ABC):
    """A scripted demonstrator: one low-level action per observation."""

    @abstractmethod
    def act(self, obs: dict[str, np.ndarray]) -> np.ndarray:
        """Action float [A] (clipped to [-1, 1] by the caller)."""

    def attach(self, env: gym.Env) -> None:
        """The chunk env the expert acts in, given by the recorder before its first reset (an
        expert that reads more than the observation, e.g. a Gymnasium env's raw one); default: nothing."""


class Simulator(ABC):
    """One simulator: its tasks, dimensions and env factories."""

    name: ClassVar[str]
    """Registry name (``env.name``)."""
    label: ClassVar[str]
    """Human name used in messages."""
    distribution: ClassVar[str | None] = None
    """The installed package whose version demonstrations record (None: the one named ``name``)."""
    state_dim: ClassVar[int]
    action_dim: ClassVar[int]
    control_hz: ClassVar[float]
    """Env steps per simulated second (the frame rate of videos)."""

    def configured(self, env_cfg) -> "Simulator":
        """This simulator as ``env_cfg`` (an :class:`~stepnft.config.EnvConfig`) sets it up: itself,
        for simulators whose tasks and sizes are their own; ``env.name: gym`` reads its env ids,
        keys and success signal there (``stepnft.envs.simulator_for``)."""
        return self

    @abstractmethod
    def task_names(self) -> list[str]:
        """Every task this simulator offers."""

    @abstractmethod
    def instruction(self, task: str) -> str:
        """The natural-language instruction of ``task``."""

    @abstractmethod
    def make_env(self, task: str, n_exec: int = 1, max_episode_steps: int = 200, terminate_on_success: bool = True,
                 seed: int = 0, render_size: tuple[int, int] | None = None, **options: Any) -> gym.Env:
        """One chunk env (see the module doc); ``render_size=(h, w)`` enables ``render()``:
        upright uint8 frames ``[h, w, 3]``. ``options`` (``stepnft.envs.env_options``):
        ``cameras``, ``image_size``, ``state_obs``, ``perturbations``, for simulators that have them."""

    @abstractmethod
    def expert(self, task: str, seed: int) -> Expert:
        """A scripted demonstrator for ``task`` (its own randomness seeded by ``seed``)."""

    def state_dim_for(self, state_obs: str = "full") -> int:
        """Size of the state observation ``state_obs`` (``full``: every simulator's state)."""
        if state_obs != "full":
            raise ValueError(f"{self.label} offers only state_obs 'full', got {state_obs!r}")
        return self.state_dim

    def policy_state(self, states: np.ndarray, state_obs: str = "full") -> np.ndarray:
        """What a ``state_obs`` policy sees of full states ``[..., S]`` (demonstrations store full states)."""
        return states[..., : self.state_dim_for(state_obs)]

    def instruction_variants(self, task: str, perturbations: Perturbations | None = None) -> list[str]:
        """The instructions the ``instruction`` observation indexes under ``perturbations``
        (the canonical one first)."""
        if perturbations is not None and perturbations.semantic:
            raise ValueError(f"{self.label} has no instruction paraphrases: semantic perturbations need MetaWorld")
        return [self.instruction(task)]

    def has_dataset(self, path) -> bool:
        """Whether ``path`` holds demonstrations in one of this simulator's own published formats."""
        return False

    def load_dataset(self, path, cameras: Sequence[str] = (), image_size: int = 64) -> list:
        """The demonstrations at ``path`` (see :meth:`has_dataset`) as a list of
        :class:`stepnft.data.demos.DemoEpisode`; with ``cameras``, their views at ``image_size``."""
        raise ValueError(f"{self.label} reads no demonstration format of its own: give a stepnft demos folder")

    def validate_tasks(self, tasks: str | Sequence[str]) -> list[str]:
        """Checks task names; ``tasks`` is a list or a comma-separated string."""
        if isinstance(tasks, str):
            tasks = [task.strip() for task in tasks.split(",") if task.strip()]
        tasks = list(tasks)
        valid = self.task_names()
        if not tasks:
            raise ValueError(f"no {self.label} task given; valid names: {', '.join(valid)}")
        for task in tasks:
            if task not in valid:
                raise ValueError(f"unknown {self.label} task {task!r}; valid names: {', '.join(valid)}")
        return tasks

    def vec_env_layout(self, tasks: str | Sequence[str], envs_per_task: int = 1, perturbations=None) -> dict[str, Any]:
        """The layout of :meth:`make_vec_env`'s sub-envs without building them: the checked
        ``tasks``, their ``instructions``, ``instruction_variants`` and ``task_ids`` [N] (sub-env
        ``i`` runs ``tasks[i // envs_per_task]``)."""
        tasks = self.validate_tasks(tasks)
        if len(set(tasks)) != len(tasks):
            raise ValueError(f"each task may appear once, got {', '.join(tasks)}")
        if envs_per_task < 1:
            raise ValueError(f"envs_per_task must be >= 1, got {envs_per_task}")
        variants = [self.instruction_variants(t, perturbations) for t in tasks]
        return dict(tasks=tasks, instructions=[v[0] for v in variants], instruction_variants=variants,
                    task_ids=np.repeat(np.arange(len(tasks), dtype=np.int64), envs_per_task))

    def make_vec_env(self, tasks: str | Sequence[str], envs_per_task: int = 1, n_exec: int = 4,
                     max_episode_steps: int = 200, terminate_on_success: bool = True, seed: int = 0,
                     num_workers: int = 0, sub_envs: Sequence[int] | None = None, **options: Any) -> "ChunkVecEnv":
        """``len(tasks) * envs_per_task`` chunk envs; sub-env ``i`` runs ``tasks[i // envs_per_task]``.
        ``num_workers`` 0 steps them in this process, >= 1 in that many worker processes (which
        then also render in parallel). ``sub_envs`` builds only those sub-envs (each with the
        task and seed it has in the whole vector env, the task indices staying global): a remote
        worker's share. ``options`` go to every :meth:`make_env`."""
        layout = self.vec_env_layout(tasks, envs_per_task, options.get("perturbations"))
        tasks, task_ids = layout["tasks"], layout["task_ids"]
        # Distinct, well-mixed sub-env seeds, so runs with nearby `seed`s share no streams.
        env_seeds = np.random.SeedSequence(seed).generate_state(len(task_ids))
        keep = np.arange(len(task_ids)) if sub_envs is None else np.asarray(sub_envs, dtype=np.int64)
        env_fns = [partial(self.make_env, tasks[task_ids[i]], n_exec=n_exec, max_episode_steps=max_episode_steps,
                           terminate_on_success=terminate_on_success, seed=int(env_seeds[i]), **options) for i in keep]
        layout["task_ids"] = task_ids[keep]
        if num_workers > 0:
            context = None
            if options.get("cameras"):
                # A forked child inherits this process's GL driver state and hangs creating its
                # own context once this process has rendered (a video, a test): start the
                # workers from a clean server process that has imported the simulator.
                context = "forkserver" if "forkserver" in multiprocessing.get_all_start_methods() else "spawn"
                multiprocessing.set_forkserver_preload([type(self).__module__])
            return ShardedChunkVecEnv(env_fns, num_workers=num_workers, context=context, **layout)
        return ChunkVecEnv(env_fns, **layout)


class _TaskLayout:
    """The multi-task layout every chunk vector env shares; sets ``tasks``, ``instructions``
    (per task), ``instruction_variants`` (per task, what the ``instruction`` observation indexes;
    bind a policy's processor to these), ``task_ids`` [N] and ``task_names`` [N], then builds the
    gymnasium class it is mixed into with autoreset disabled (the collector resets sub-envs
    itself), and ``lanes`` [N] (:func:`lane_ids`)."""

    def __init__(self, env_fns: list[Callable[[], gym.Env]], *, tasks: list[str], instructions: list[str],
                 task_ids: np.ndarray, instruction_variants: list[list[str]] | None = None,
                 lanes: np.ndarray | None = None, **vector_kwargs: Any):
        self.tasks = list(tasks)
        self.instructions = list(instructions)
        self.instruction_variants = instruction_variants or [[i] for i in self.instructions]
        self.task_ids = np.asarray(task_ids, dtype=np.int64)
        self.task_names = [self.tasks[i] for i in self.task_ids]
        self.lanes = lane_ids(self.task_ids) if lanes is None else np.asarray(lanes, dtype=np.int64)
        super().__init__(env_fns, **vector_kwargs)

    def reset(self, *, seed=None, options=None):
        if options and "reset_mask" in options and any(obs is None for obs in self._env_obs):
            # A partial reset batches every sub-env's observation: give the never-reset ones one
            # without simulating anything (an idle reset).
            super().reset(options={"idle": True})
        return super().reset(seed=seed, options=options)

    def rng_state(self) -> list[dict]:
        """Each sub-env's RNG state (JSON-serialisable), for checkpoints."""
        return [rng.bit_generator.state for rng in self.get_attr("np_random")]

    def set_rng_state(self, states: list[dict]) -> None:
        """Restore :meth:`rng_state`: unseeded resets then continue the same streams."""
        rngs = []
        for state in states:
            rng = np.random.Generator(np.random.PCG64())
            rng.bit_generator.state = state
            rngs.append(rng)
        self.set_attr("np_random", rngs)


def run_ops(envs: Sequence[gym.Env], ops: Sequence[tuple[int, str, Any]]) -> list:
    """The results of ``(i, "reset", seed)`` / ``(i, "step", chunk)`` ops on ``envs[i]``, in order."""
    return [envs[i].reset(seed=arg) if op == "reset" else envs[i].step(arg) for i, op, arg in ops]


class ChunkVecEnv(_TaskLayout, gym.vector.SyncVectorEnv):
    """Chunk envs of several tasks stepped in this process, autoreset disabled.

    Call ``reset(seed=[s_0, ..., s_{N-1}])`` (or unseeded), then ``step`` the whole batch
    until ``terminated | truncated`` holds everywhere; finished sub-envs answer with no-ops and
    top-level ``info["success"]`` is each episode's result. Observations are dicts of arrays
    ``[N, ...]``; actions ``[N, n_exec, A]``.
    """

    def __init__(self, env_fns, **layout):
        super().__init__(env_fns, autoreset_mode=AutoresetMode.DISABLED, **layout)
        self._replies: collections.deque[list] = collections.deque()

    def step(self, actions: np.ndarray):
        # SyncVectorEnv refuses to step a finished sub-env when autoreset is disabled; chunk
        # envs treat that step as a no-op, so the whole batch can be stepped.
        self._autoreset_envs[:] = False
        return super().step(actions)

    def send_ops(self, ops: Sequence[tuple[int, str, Any]]) -> None:
        """``(i, "reset", seed)`` / ``(i, "step", chunk)`` on sub-env ``i``: run here, now
        (:meth:`ShardedChunkVecEnv.send_ops` runs them in the workers without waiting)."""
        self._replies.append(run_ops(self.envs, ops))

    def receive_ops(self) -> list:
        """The results of the oldest :meth:`send_ops` not yet received, in its op order."""
        return self._replies.popleft()


class ShardedChunkVecEnv(_TaskLayout, ShardedVectorEnv):
    """:class:`ChunkVecEnv` with the sub-envs dealt out to ``num_workers`` worker processes
    (MuJoCo is CPU-bound: one worker per core). With one worker it holds both lanes; with more,
    worker ``w`` holds lane ``w``. Same layout, info keys and results."""

    def __init__(self, env_fns, num_workers: int = 2, context: str | None = None, **layout):
        workers = min(num_workers, len(env_fns))
        lanes = lane_ids(layout["task_ids"], lane_count(workers))
        while workers > 1 and len(np.unique(lanes)) < lane_count(workers):  # too few sub-envs for a lane each
            workers -= 1
            lanes = lane_ids(layout["task_ids"], lane_count(workers))
        super().__init__(env_fns, num_workers=workers, context=context,
                         assignment=(lanes % workers).tolist(), lanes=lanes, **layout)

    def run_in_workers(self, fn, args: list) -> list:
        """``fn(envs, sub_envs, *args[w])`` in each worker ``w`` (its chunk envs and their indices
        in this vector env); returns one result per worker. ``fn`` must be importable by name."""
        return self.run(fn, args)


class ChunkEpisode:
    """The chunk env contract's episode bookkeeping (module doc), one piece for every simulator's
    chunk env: env steps since reset, success at any step so far, terminated (success, with
    ``terminate_on_success``), truncated (``max_episode_steps`` reached), and ``info``. The env
    sets ``max_episode_steps`` and ``terminate_on_success`` (tests may change the cap later)."""

    max_episode_steps: int
    terminate_on_success: bool
    _episode_steps = 0
    _success = _terminated = _truncated = False

    def _start_episode(self, idle: bool = False) -> None:
        """A new episode; ``idle``: one that is over at once (truncated), the contract's idle reset."""
        self._episode_steps, self._success, self._terminated, self._truncated = 0, False, False, idle

    @property
    def _ended(self) -> bool:
        return self._terminated or self._truncated

    def _count_step(self, success: bool) -> bool:
        """After one env step whose success is ``success``; True once the episode has ended."""
        self._episode_steps += 1
        self._success = self._success or success
        self._terminated = self._success and self.terminate_on_success
        self._truncated = self._episode_steps >= self.max_episode_steps
        return self._ended

    def _info(self, steps: int) -> dict[str, Any]:
        return {"success": self._success, "steps": steps, "episode_steps": self._episode_steps}


def checked_chunk(chunk, action_space: gym.spaces.Box, was_reset: bool) -> np.ndarray:
    """The ``step`` argument of a chunk env as float64 ``[n_exec, A]``, after the contract's
    checks: a reset came first (``was_reset``), and the chunk has ``action_space``'s shape."""
    if not was_reset:
        raise RuntimeError("call reset() before step()")
    chunk = np.asarray(chunk, dtype=np.float64)
    if chunk.shape != action_space.shape:
        raise ValueError(f"expected an action chunk of shape {action_space.shape}, got {chunk.shape}")
    return chunk
