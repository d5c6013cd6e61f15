"""The collector: plays the episodes of a plan with a policy in a vector env and returns a
:class:`Batch`.

Continuous collection: every sub-env plays episodes of its task back to back, a new one as
soon as its last one ended, until the plan is done (the plan: ``stepnft.rollout.plan``). The
vector env's sub-envs form *lanes* (``venv.lanes``; ``stepnft.envs.base``), and each lane plays
a fixed share of the plan (episode ``j`` of a task goes to the lane of the task's sub-env ``j
mod n``), its sub-envs taking the lane's episodes of their task in plan order as they come free.
Where the lanes play depends on the machine, not the result:

- in this process, or with one simulator worker: this process samples every lane's actions,
  the lanes taking turns, so that the worker steps one lane while the next actions of the other
  are computed;
- with a worker per lane (``env.num_workers >= 2``) and the policy on the CPU: each worker plays
  its lane with a copy of the policy, nothing crosses a pipe per env step, and the parts are
  merged into plan order.

Everything a lane does follows from its episodes and the policy, never from timing, so the same
plan gives the same batch, bit for bit, with 0, 1 or 2 workers (more workers make more lanes,
which batch the policy's rows differently: the same episodes up to the last float bits).

:meth:`Collector.collect` draws an iteration's plan (per-task counts, groups of episodes
sharing one initial state) and records what the algorithm's :class:`RolloutSpec` asks;
evaluation plays fixed plans without recording. The collector assigns no labels: what an
episode's outcome means is the algorithm's business. ``play`` and ``state_dict`` are the seam a
remote (e.g. Ray) collector implements.
"""

from __future__ import annotations

import collections
import math
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np
import torch
from torch import Tensor

from stepnft.batch import CALL_KEYS, EPISODE_KEYS, STEP_KEYS, Batch
from stepnft.devices import to_device
from stepnft.envs.base import run_ops
from stepnft.envs.sharded import heartbeat
from stepnft.policies.base import Policy
from stepnft.rollout.plan import EpisodePlan, RolloutSpec

Progress = Callable[[int, int], None]
"""``progress(episodes_done, episodes)``, called as episodes end."""


class Collector:
    """Owns a chunk vector env and the generator that draws training plans."""

    def __init__(self, venv, seed: int = 0):
        self.venv = venv
        self.generator = torch.Generator().manual_seed(seed)

    @property
    def num_envs(self) -> int:
        return self.venv.num_envs

    def plan(self, episodes: int, spec: RolloutSpec, task_episodes: list[int] | None = None) -> EpisodePlan:
        """An iteration's episodes: ``task_episodes[k]`` of task ``k``, or ``episodes`` split
        equally (each task's share rounded up to whole groups of ``spec.group_size``)."""
        tasks = len(self.venv.tasks)
        if task_episodes is None:
            task_episodes = [math.ceil(episodes / tasks / spec.group_size) * spec.group_size] * tasks
        if len(task_episodes) != tasks:
            raise ValueError(f"task_episodes must give one count per task ({tasks}), got {task_episodes}")
        return EpisodePlan.draw(task_episodes, spec.group_size, self.generator)

    def collect(self, policy: Policy, episodes: int, spec: RolloutSpec,
                task_episodes: list[int] | None = None) -> Batch:
        """An iteration's episodes (:meth:`plan`), sampled and recorded as ``spec`` says."""
        return self.play(policy, self.plan(episodes, spec, task_episodes), spec.noise_level, record=spec)

    def play(self, policy: Policy, plan: EpisodePlan, noise_level: float, record: RolloutSpec | None = None,
             progress: Progress | None = None) -> Batch:
        """Every episode of ``plan``, in its order in the batch. With ``record`` the batch holds
        the policy calls and recorded denoising steps, else only the episode table. With a lane
        per worker process and the policy on the CPU, each worker plays its lane with a copy of
        the policy (no traffic per step); else this process samples for every lane."""
        if getattr(self.venv, "num_workers", 0) >= 2 and policy.device.type == "cpu":
            return _play_in_workers(self.venv, policy, plan, noise_level, record, progress)
        return _Play(self.venv, policy, plan, noise_level, record, progress).run()

    def state_dict(self) -> dict:
        """The plan generator's state: enough to resume exactly."""
        return {"generator": self.generator.get_state()}

    def load_state_dict(self, state: dict) -> None:
        self.generator.set_state(state["generator"])

    def pop_metrics(self) -> dict[str, float]:
        """Metrics of the collector itself since the last call (a remote collector's weight
        pushes and lost episodes); none here."""
        return {}

    def close(self) -> None:
        self.venv.close()


def plan_lanes(plan: EpisodePlan, task_ids: np.ndarray, lanes: np.ndarray) -> np.ndarray:
    """``[E]`` the lane of every episode: episode ``j`` of task ``k`` (in plan order) goes to
    the lane of the task's sub-env ``j mod n`` (``n`` its sub-envs), so each lane gets episodes
    in proportion to its sub-envs of the task."""
    out = np.empty(len(plan), dtype=np.int64)
    for k in np.unique(plan.task):
        mine = np.flatnonzero(plan.task == k)
        task_lanes = lanes[task_ids == k]
        if len(task_lanes) == 0:
            raise ValueError(f"the plan has episodes of task {k}, which has no sub-env")
        out[mine] = task_lanes[np.arange(len(mine)) % len(task_lanes)]
    return out


def _play_in_workers(venv, policy: Policy, plan: EpisodePlan, noise_level: float, record: RolloutSpec | None,
                     progress: Progress | None) -> Batch:
    """Each worker process plays its lane's part of ``plan`` (:func:`play_lane`); the parts are
    merged into plan order, the same batch as one process playing the lanes in turn."""
    lanes = np.asarray(venv.lanes)
    lane_of = plan_lanes(plan, np.asarray(venv.task_ids), lanes)
    rows = [np.flatnonzero(lane_of == lane) for lane in range(venv.num_workers)]  # worker w holds lane w
    layout = (list(venv.tasks), np.asarray(venv.task_ids))
    args = [(layout, policy, plan.take(r), noise_level, record) for r in rows]
    parts = venv.run_in_workers(play_lane, args)
    if progress is not None:
        progress(len(plan), len(plan))
    played = [(part, r) for part, r in zip(parts, rows) if part is not None]
    return merge_parts([p for p, _ in played], [r for _, r in played])


def play_lane(envs: list, sub_envs: list[int], layout: tuple[list[str], np.ndarray], policy: Policy,
              plan: EpisodePlan, noise_level: float, record: RolloutSpec | None) -> Batch | None:
    """In a worker process: its envs (sub-envs ``sub_envs`` of the vector env, one lane) play
    ``plan`` with this copy of the policy. ``layout``: the vector env's tasks and task ids."""
    if len(plan) == 0:
        return None
    # A worker is one core. One thread also keeps a forked child out of the OpenMP pool its
    # parent may have started, where it would hang; with --num-threads 1 (the default) the
    # parent computes the same bits.
    torch.set_num_threads(1)
    tasks, task_ids = layout
    return _Play(_LaneEnvs(envs, task_ids[sub_envs], tasks), policy, plan, noise_level, record, None).run()


class _LaneEnvs:
    """A worker's chunk envs, driven as a one-lane vector env (ops run at once, here)."""

    def __init__(self, envs: list, task_ids, tasks: list[str]):
        self.envs, self.task_ids, self.tasks = envs, np.asarray(task_ids), tasks
        self.lanes = np.zeros(len(envs), dtype=np.int64)
        self._replies: collections.deque = collections.deque()

    def send_ops(self, ops) -> None:
        self._replies.append(run_ops(self.envs, ops))
        heartbeat()  # the parent waits for a lane as long as it makes progress

    def receive_ops(self) -> list:
        return self._replies.popleft()


def merge_parts(parts: list[Batch], rows: list[np.ndarray], keep: Tensor | None = None) -> Batch:
    """One batch in plan order from parts of a plan played apart (``rows[j]``: the plan row of
    each episode of ``parts[j]``, in its order): episodes by plan row, each episode's calls
    together in their order, each call's steps together. ``keep`` ([E] bool over the parts'
    episodes in order): drop the others with their calls and steps."""
    batch = Batch.concat(parts)
    plan_row = torch.as_tensor(np.concatenate(rows), dtype=torch.int64)
    episodes = torch.argsort(plan_row)
    if keep is not None:
        episodes = episodes[keep[episodes]]
    new_episode = torch.full((batch.num_episodes,), -1, dtype=torch.int64)
    new_episode[episodes] = torch.arange(len(episodes))
    kept = torch.nonzero(new_episode[batch.episode] >= 0).squeeze(1)
    calls = kept[torch.argsort(new_episode[batch.episode[kept]], stable=True)]
    new_call = torch.full((batch.num_calls,), -1, dtype=torch.int64)
    new_call[calls] = torch.arange(len(calls))
    kept = torch.nonzero(new_call[batch.call] >= 0).squeeze(1)
    steps = kept[torch.argsort(new_call[batch.call[kept]], stable=True)]
    return Batch(
        **{k: getattr(batch, k)[episodes] for k in EPISODE_KEYS},
        obs=batch.calls_obs(calls),
        **{k: getattr(batch, k)[calls] for k in CALL_KEYS if k != "episode"}, episode=new_episode[batch.episode[calls]],
        **{k: getattr(batch, k)[steps] for k in STEP_KEYS if k != "call"}, call=new_call[batch.call[steps]],
    )


@dataclass
class _Lane:
    """One lane's sub-envs, its queue of episodes per task, and what it sent last."""

    sub_envs: np.ndarray
    queue: dict[int, collections.deque]
    playing: dict[int, int] = field(default_factory=dict)
    """sub-env -> the plan row of the episode it plays."""
    obs: dict[int, dict] = field(default_factory=dict)
    """sub-env -> its latest observation."""
    sent: list[tuple[int, str]] = field(default_factory=list)
    """(sub-env, op) of the ops in flight."""
    call_rows: list[int] = field(default_factory=list)
    """The batch call row of each step op in flight."""


class _Play:
    """One :meth:`Collector.play`: the lanes take turns until the plan is done."""

    def __init__(self, venv, policy: Policy, plan: EpisodePlan, noise_level: float, record: RolloutSpec | None,
                 progress: Progress | None):
        self.venv, self.policy, self.plan, self.noise_level = venv, policy, plan, noise_level
        self.record, self.progress = record, progress
        self.task_ids = np.asarray(venv.task_ids)
        self.generators = plan.generators()
        n = len(plan)
        self.success, self.length, self.ended = np.zeros(n, bool), np.zeros(n, np.int64), 0
        self.calls: list[dict[str, Tensor]] = []  # one entry per policy call batch
        self.call_episode: list[int] = []  # plan row of every call, in call order
        self.call_info: list[list] = []  # [steps executed, reward, done] of every call
        self.steps: list[dict[str, Tensor]] = []
        lanes = np.asarray(venv.lanes)
        lane_of = plan_lanes(plan, self.task_ids, lanes)
        self.lanes = []
        for lane in range(int(lanes.max()) + 1):
            queue = {k: collections.deque(np.flatnonzero((lane_of == lane) & (plan.task == k)).tolist())
                     for k in range(len(venv.tasks))}
            self.lanes.append(_Lane(np.flatnonzero(lanes == lane), queue))

    def run(self) -> Batch:
        self.policy.eval()
        turns = collections.deque(lane for lane in self.lanes if self._send(lane, self._resets(lane)))
        while turns:
            lane = turns.popleft()
            self._receive(lane, self.venv.receive_ops())
            steps = self._act(lane)  # before the resets: a sub-env acts once its reset came back
            if self._send(lane, steps + self._resets(lane)):
                turns.append(lane)
        return self._batch()

    # --- one turn of a lane ---------------------------------------------------------------------
    def _resets(self, lane: _Lane) -> list[tuple[int, str, int]]:
        """Start the next queued episode on each free sub-env of the lane."""
        ops = []
        for i in lane.sub_envs:
            queue = lane.queue[int(self.task_ids[i])]
            if int(i) not in lane.playing and queue:
                row = queue.popleft()
                lane.playing[int(i)] = row
                ops.append((int(i), "reset", int(self.plan.seed[row])))
        return ops

    def _act(self, lane: _Lane) -> list[tuple[int, str, np.ndarray]]:
        """One policy call for every sub-env of the lane that is in an episode."""
        acting = sorted(lane.playing)
        if not acting:
            return []
        policy, record = self.policy, self.record
        rows = [lane.playing[i] for i in acting]
        keys = lane.obs[acting[0]].keys()
        obs = {k: torch.as_tensor(np.stack([lane.obs[i][k] for i in acting])) for k in keys}
        obs["task"] = torch.as_tensor(self.task_ids[acting])
        keep_path = record is not None and record.record_steps == "all"
        # Processed on the CPU, sampled on the policy's device, the chunk back on the CPU.
        sample = to_device(policy.sample(policy.prepare(obs), noise_level=self.noise_level,
                                         generator=[self.generators[r] for r in rows],
                                         stochastic_steps=record.stochastic_steps if record else "all",
                                         keep_path=keep_path,
                                         mean_correction=record.mean_correction if record else True), "cpu")
        chunk = policy.env_actions(sample.actions[:, :policy.config.n_exec]).clamp(-1.0, 1.0).numpy()
        lane.call_rows = list(range(len(self.call_episode), len(self.call_episode) + len(acting)))
        if record is not None:
            self.calls.append({"obs": obs, "actions": sample.actions})
            step = sample.recorded_steps(every_step=keep_path)
            step["call"] = step["call"] + len(self.call_episode)
            self.steps.append(step)
        self.call_episode += rows
        self.call_info += [[0, 0.0, False] for _ in acting]
        return [(i, "step", chunk[n]) for n, i in enumerate(acting)]

    def _send(self, lane: _Lane, ops: list) -> bool:
        lane.sent = [(i, op) for i, op, _ in ops]
        if ops:
            self.venv.send_ops(ops)
        return bool(ops)

    def _receive(self, lane: _Lane, results: list) -> None:
        """Take the results of the lane's ops: new observations, and for steps the call's
        outcome and the episodes that ended."""
        calls = iter(lane.call_rows)
        for (i, op), result in zip(lane.sent, results, strict=True):
            lane.obs[i] = result[0]
            if op == "reset":
                continue
            _, reward, terminated, truncated, info = result
            row, call = lane.playing[i], next(calls)
            self.call_info[call] = [int(info["steps"]), float(reward), bool(terminated or truncated)]
            self.length[row] += int(info["steps"])
            self.success[row] = bool(info["success"])
            if terminated or truncated:
                del lane.playing[i]
                self.ended += 1
                if self.progress is not None:
                    self.progress(self.ended, len(self.plan))

    # --- the batch ---------------------------------------------------------------------------------
    def _batch(self) -> Batch:
        """The batch in plan order: episodes as planned, each episode's calls together in call
        order, each call's recorded steps together."""
        plan = self.plan
        episodes = {"episode_success": torch.as_tensor(self.success), "episode_task": torch.as_tensor(plan.task),
                    "episode_length": torch.as_tensor(self.length), "episode_seed": torch.as_tensor(plan.seed)}
        if self.record is None:
            return Batch(**episodes, **_empty_tables(self.policy))
        episode_of = torch.as_tensor(self.call_episode, dtype=torch.int64)
        order = torch.argsort(episode_of, stable=True)  # calls are appended in time order
        new_call = torch.empty_like(order)
        new_call[order] = torch.arange(len(order))
        steps = {k: torch.cat([s[k] for s in self.steps]) for k in ("call", "x_t", "x_next", "v_old", "t", "dt")}
        step_order = torch.argsort(new_call[steps["call"]], stable=True)
        executed, reward, done = zip(*self.call_info)
        horizon = self.policy.chunk_shape[0]
        return Batch(
            **episodes,
            obs={k: torch.cat([c["obs"][k] for c in self.calls])[order] for k in self.calls[0]["obs"]},
            actions=torch.cat([c["actions"] for c in self.calls])[order],
            mask=(torch.arange(horizon)[None, :] < torch.as_tensor(executed)[:, None])[order],
            reward=torch.as_tensor(reward, dtype=torch.float32)[order], done=torch.as_tensor(done)[order],
            episode=episode_of[order],
            call=new_call[steps["call"]][step_order],
            **{k: v[step_order] for k, v in steps.items() if k != "call"},
        )


def _empty_tables(policy: Policy) -> dict:
    """Call and step tables with no rows (episodes played without recording)."""
    horizon, action_dim = policy.chunk_shape
    chunk = torch.zeros(0, horizon, action_dim)
    obs = {"state": torch.zeros(0), "task": torch.zeros(0, dtype=torch.int64)}
    return {"obs": obs, "actions": chunk, "mask": torch.zeros(0, horizon, dtype=torch.bool),
            "reward": torch.zeros(0), "done": torch.zeros(0, dtype=torch.bool),
            "episode": torch.zeros(0, dtype=torch.int64), "call": torch.zeros(0, dtype=torch.int64),
            "x_t": chunk, "x_next": chunk, "v_old": chunk, "t": torch.zeros(0), "dt": torch.zeros(0)}
