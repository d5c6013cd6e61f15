"""Rollouts on Ray: a :class:`~stepnft.rollout.collector.Collector` whose episodes are played by
Ray actors, each owning a share of the sub-envs and a copy of the acting policy.

The driver keeps everything that decides *which* episodes are played (the plan: per-task
allocation, groups, reset and noise seeds; the local collector's code) and sends each worker
its part of the plan (episode ``j`` of a task to the ``j mod n``-th of the ``n`` workers that
hold sub-envs of it); each worker plays its part continuously with a local collector, and the
parts are merged back into plan order (:func:`merge_parts`). An episode's initial state and
noise come with the plan, so the batch is the local collector's (a policy forward on another
batch of rows may differ in the last float bits). Evaluation
(:func:`stepnft.evaluate.evaluate_policy`) plays its fixed plan through the same path.

Weights go with the first part played after they changed: a whole policy the first time a worker sees
it, afterwards only the tensors written since. Changes are seen through torch's version
counters, which every in-place write bumps (optimizer steps, the EMA update,
``load_state_dict``); a write through ``.data`` does not and would go unnoticed.

Failures: a worker that dies (process killed, node lost, out of memory) or does not answer its
part within ``ray.timeout_s`` (then it is killed) is restarted by Ray. Its episodes are dropped
and counted (``charts/dropped_episodes``) and training goes on with the other workers' episodes
(a plan that lost every episode is played again; with groups, incomplete groups are dropped).
Evaluation (nothing recorded: a fixed plan) plays the lost part again instead. A worker lost
more than ``ray.max_restarts`` times ends the run with an error; ``stepnft train --resume``
continues it from its last checkpoint.

Ray is imported only when a :class:`RayCollector` is built (``pip install "stepnft[ray]"``).
"""

from __future__ import annotations

import hashlib
import os
import pickle
import sys
import time
import weakref
from collections import OrderedDict
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import torch

from stepnft.batch import Batch
from stepnft.envs import RENDERING_ENV_VARS, env_options, make_vec_env, simulator_for
from stepnft.envs.base import lane_ids
from stepnft.envs.sharded import shard_ranges
from stepnft.policies.base import Policy
from stepnft.rollout.collector import Collector, Progress, merge_parts  # noqa: F401 - merge_parts: re-exported
from stepnft.rollout.plan import EpisodePlan, RolloutSpec

MAX_POLICIES = 3
"""Policies a worker keeps (e.g. π-StepNFT's EMA rollout policy and the evaluated one)."""


def import_ray():
    """The ``ray`` module, or an ImportError saying how to install it."""
    try:
        import ray
    except ImportError as err:
        raise ImportError('Ray rollout workers need Ray: pip install "stepnft[ray]" (or set --ray.workers 0)') from err
    return ray


def _named_tensors(policy: Policy) -> dict[str, torch.Tensor]:
    return dict(policy.named_parameters()) | dict(policy.named_buffers())


def _fingerprint(policy: Policy) -> tuple[str, dict[str, tuple[int, int]]]:
    """What a worker's copy must match: a key of the policy's class, tensor names and input
    processor (a change means a whole new copy), and each tensor's (storage, version)."""
    tensors = _named_tensors(policy)
    structure = hashlib.sha1(pickle.dumps((type(policy).__qualname__, sorted(tensors), policy.processor))).hexdigest()
    return structure, {name: (t.data_ptr(), t._version) for name, t in tensors.items()}


def _join_hint(address: str | None, err: Exception) -> str:
    """Ray's failure to join ``address``, with the two usual causes."""
    hint = f"{err} (--ray.address {address}): is the cluster running (`ray status`)?"
    if os.environ.get("RAY_AUTH_MODE") is None and address not in (None, "auto"):
        # Ray authenticates with a token once one exists (~/.ray/auth_token) but sends it to an
        # explicit address only when told to.
        hint += (" If it was started with token authentication, export RAY_AUTH_MODE=token (the token in "
                 "~/.ray/auth_token or RAY_AUTH_TOKEN), or use --ray.address auto on the head node")
    return hint


class RolloutWorker:
    """One Ray actor: sub-envs ``sub_envs`` of the run's vector env (the same tasks and seeds),
    stepped in this process (or ``env.num_workers`` processes), and copies of the policies
    that act on them, by slot."""

    def __init__(self, env_cfg, n_exec: int, seed: int, sub_envs: list[int], num_threads: int = 1):
        torch.set_num_threads(num_threads)
        self.collector = Collector(make_vec_env(env_cfg, n_exec, seed, sub_envs=sub_envs))
        self.policies: OrderedDict[int, Policy] = OrderedDict()
        # Ray may restart a dead worker before the driver notices: a new incarnation has fresh
        # envs and no policies, so it plays only for a driver that knows it was restarted.
        self.incarnation = os.urandom(8).hex()

    def pid(self) -> int:
        return os.getpid()

    def hello(self) -> str:
        """This incarnation."""
        return self.incarnation

    def sync(self, incarnation, slot, policy, weights, training) -> float | None:
        """:meth:`_sync` alone; None, doing nothing, when the driver expects another ``incarnation``."""
        if incarnation is not None and incarnation != self.incarnation:
            return None
        return self._sync(slot, policy, weights, training)

    def _sync(self, slot: int, policy: Policy | None, weights: dict[str, torch.Tensor] | None, training: bool) -> float:
        """Take a whole ``policy`` into ``slot`` or copy changed ``weights`` into it; returns seconds."""
        start = time.perf_counter()
        if policy is not None:
            self.policies[slot] = policy
        self.policies.move_to_end(slot)  # the driver mirrors this eviction order (RayCollector._hold)
        while len(self.policies) > MAX_POLICIES:
            self.policies.popitem(last=False)
        if weights:
            tensors = _named_tensors(self.policies[slot])
            with torch.no_grad():
                for name, value in weights.items():
                    tensors[name].copy_(value)
        self.policies[slot].train(training)
        return time.perf_counter() - start

    def play(self, incarnation, slot, policy, weights, training, plan: EpisodePlan, noise_level: float,
             record: RolloutSpec | None):
        """This worker's part of a plan (:meth:`Collector.play`), after syncing the policy.
        Returns this incarnation, the batch and the sync's seconds; or None, playing nothing,
        when the driver expects another ``incarnation``."""
        if incarnation is not None and incarnation != self.incarnation:
            return None
        sync_s = self._sync(slot, policy, weights, training)
        return self.incarnation, self.collector.play(self.policies[slot], plan, noise_level, record), sync_s


class RemoteEnvs:
    """The sub-envs as the driver sees them (the workers own them): the layout every
    collector reads (``tasks``, ``instructions``, ``instruction_variants``, ``task_ids``, ``lanes``)."""

    def __init__(self, tasks: list[str], instructions: list[str], instruction_variants: list[list[str]],
                 task_ids: np.ndarray):
        self.tasks, self.instructions, self.task_ids = list(tasks), list(instructions), np.asarray(task_ids)
        self.instruction_variants = [list(v) for v in instruction_variants]
        self.task_names = [self.tasks[i] for i in self.task_ids]
        self.lanes = lane_ids(self.task_ids)

    @property
    def num_envs(self) -> int:
        return len(self.task_ids)

    def close(self) -> None:
        """The workers own the sub-envs: :meth:`RayCollector.close` ends them."""


@dataclass
class _Worker:
    actor: Any
    sub_envs: np.ndarray
    incarnation: str | None = None
    """The actor's incarnation the driver knows; None after a loss (learnt again when it is back)."""
    weights: OrderedDict = field(default_factory=OrderedDict)
    """slot -> fingerprint of the weights its copy holds (mirrors the actor's eviction)."""
    losses: int = 0


class RayCollector(Collector):
    """The collector over ``ray_cfg.workers`` Ray actors; sub-env ``i`` lives on worker
    ``i % workers`` (each gets the same mix of tasks). Starts a local Ray unless one is
    running or ``ray_cfg.address`` names a cluster; :meth:`close` kills the workers (and the
    local Ray it started)."""

    def __init__(self, env_cfg, n_exec: int, seed: int, ray_cfg, num_threads: int = 1):
        ray = self._ray = import_ray()
        layout = simulator_for(env_cfg).vec_env_layout(env_cfg.tasks, env_cfg.envs_per_task,
                                                            env_options(env_cfg).get("perturbations"))
        num_envs = len(layout["task_ids"])
        if ray_cfg.workers > num_envs:
            raise ValueError(f"ray.workers={ray_cfg.workers} is more than the {num_envs} sub-envs "
                             f"(env.tasks x env.envs_per_task): use at most {num_envs}")
        super().__init__(RemoteEnvs(**layout), seed)
        self.cfg = ray_cfg
        self.workers: list[_Worker] = []
        self._metrics: dict[str, float] = {}
        self._slots: weakref.WeakKeyDictionary[Policy, int] = weakref.WeakKeyDictionary()
        self._next_slot = 0
        self._owns_ray = not ray.is_initialized()
        cpus = max(1, env_cfg.num_workers)  # a worker with env.num_workers steps its envs in that many processes
        if self._owns_ray:
            env_vars = {k: os.environ[k] for k in RENDERING_ENV_VARS if k in os.environ}
            try:
                ray.init(address=ray_cfg.address, num_cpus=None if ray_cfg.address else ray_cfg.workers * cpus,
                         include_dashboard=False, runtime_env={"env_vars": env_vars} if env_vars else None)
            except ConnectionError as err:
                raise ConnectionError(_join_hint(ray_cfg.address, err)) from err
        needed, available = ray_cfg.workers * cpus, ray.cluster_resources().get("CPU", 0)
        if needed > available:  # an existing cluster too small: Ray would queue the workers silently
            print(f"stepnft: the {ray_cfg.workers} Ray rollout workers need {needed:g} CPUs "
                  f"(max(1, env.num_workers)={cpus} each) but the Ray cluster has {available:g}; they wait for "
                  f"more nodes up to ray.timeout_s={ray_cfg.timeout_s}s (fewer --ray.workers or "
                  "--env.num-workers 0 fit now)", file=sys.stderr)
        try:
            actor_class = ray.remote(RolloutWorker).options(
                num_cpus=cpus, max_restarts=ray_cfg.max_restarts, max_task_retries=0, scheduling_strategy="SPREAD")
            for shard in shard_ranges(num_envs, ray_cfg.workers, "interleave"):
                actor = actor_class.remote(env_cfg, n_exec, seed, list(shard), num_threads)
                self.workers.append(_Worker(actor, np.asarray(shard)))
            hellos = ray.get([w.actor.hello.remote() for w in self.workers], timeout=ray_cfg.timeout_s)
        except BaseException as err:
            self.close()
            if isinstance(err, ray.exceptions.GetTimeoutError):
                raise RuntimeError(f"the Ray rollout workers did not start within ray.timeout_s={ray_cfg.timeout_s}s "
                                   f"(is stepnft installed on every node? they need {needed:g} CPUs, the "
                                   f"cluster has {available:g})") from err
            raise
        for w, incarnation in zip(self.workers, hellos):
            w.incarnation = incarnation

    # --- weights ------------------------------------------------------------------------------
    def _slot(self, policy: Policy) -> int:
        """A number for ``policy`` while it lives (workers keep their copies by slot)."""
        if policy not in self._slots:
            self._slots[policy] = self._next_slot
            self._next_slot += 1
        return self._slots[policy]

    def _weight_messages(self, policy: Policy, workers: list[int]) -> tuple[dict[int, tuple], int, tuple]:
        """``(slot, whole policy or None, changed tensors or None, training)`` for each of
        ``workers``, the payloads put into the object store once and shared (the cost goes to
        the metrics); and the slot and fingerprint the workers hold once they took them."""
        slot, (structure, versions) = self._slot(policy), _fingerprint(policy)
        start, sent_bytes, puts = time.perf_counter(), 0, {}
        messages = {}
        for k in workers:
            held = self.workers[k].weights.get(slot)
            if held is None or held[0] != structure:
                key = "whole"
            else:
                key = tuple(sorted(name for name, v in versions.items() if held[1].get(name) != v))
            if key not in puts:
                if key == "whole":
                    payload = policy
                    sent_bytes += sum(t.numel() * t.element_size() for t in _named_tensors(policy).values())
                else:
                    tensors = _named_tensors(policy)
                    payload = {name: tensors[name].detach().cpu() for name in key} or None
                    sent_bytes += sum(t.numel() * t.element_size() for t in (payload or {}).values())
                puts[key] = None if payload is None else self._ray.put(payload)
            messages[k] = (slot, puts[key], None, policy.training) if key == "whole" else \
                (slot, None, puts[key], policy.training)
        self._add_metric("time/weight_push_s", time.perf_counter() - start)
        self._add_metric("charts/weight_push_mb", sent_bytes / 2**20)
        return messages, slot, (structure, versions)

    def push(self, policy: Policy) -> float:
        """Bring every worker's copy of ``policy`` up to date now (playing does it itself);
        returns the seconds until all have it."""
        start = time.perf_counter()
        messages, slot, fingerprint = self._weight_messages(policy, list(range(len(self.workers))))
        replies = self._ray.get([w.actor.sync.remote(w.incarnation, *messages[k]) for k, w in enumerate(self.workers)],
                                timeout=self.cfg.timeout_s)
        for k, (w, reply) in enumerate(zip(self.workers, replies)):
            if reply is None:
                self._lose(k, "restarted since it was last seen", dropped=0)
            else:
                self._hold(w, slot, fingerprint)
        return time.perf_counter() - start

    @staticmethod
    def _hold(worker: _Worker, slot: int, fingerprint) -> None:
        worker.weights[slot] = fingerprint
        worker.weights.move_to_end(slot)
        while len(worker.weights) > MAX_POLICIES:
            worker.weights.popitem(last=False)

    # --- episodes -------------------------------------------------------------------------------
    def play(self, policy: Policy, plan: EpisodePlan, noise_level: float, record: RolloutSpec | None = None,
             progress: Progress | None = None) -> Batch:
        """:meth:`Collector.play` on the workers (see the module doc for lost workers);
        ``progress`` is told as each worker's part comes back."""
        parts = self._owners(plan)
        while True:
            done = self._play_parts(policy, plan, parts, noise_level, record, progress)
            if done:
                break
        rows = [parts[k] for k in sorted(done)]
        batches = [done[k] for k in sorted(done)]
        keep = None
        if record is not None and record.group_size > 1 and len(done) < len(parts):
            keep = _whole_groups(Batch.concat(batches), record.group_size)
        return merge_parts(batches, rows, keep)

    def _owners(self, plan: EpisodePlan) -> dict[int, np.ndarray]:
        """worker -> the plan rows it plays: episode ``j`` of a task to the ``j mod n``-th of
        the ``n`` workers holding sub-envs of that task."""
        owner = np.empty(len(plan), dtype=np.int64)
        for k in np.unique(plan.task):
            mine = np.flatnonzero(plan.task == k)
            holders = [w for w, worker in enumerate(self.workers) if (self.venv.task_ids[worker.sub_envs] == k).any()]
            owner[mine] = np.asarray(holders)[np.arange(len(mine)) % len(holders)]
        return {w: np.flatnonzero(owner == w) for w in np.unique(owner).tolist()}

    def _play_parts(self, policy, plan, parts, noise_level, record, progress) -> dict[int, Batch]:
        ray = self._ray
        jobs, done, played = list(parts), {}, 0
        while jobs:
            for k in jobs:
                if self.workers[k].incarnation is None:
                    self._call(k, "pid")  # a lost worker: wait until Ray has restarted it
            messages, slot, fingerprint = self._weight_messages(policy, jobs)
            refs = {self.workers[k].actor.play.remote(self.workers[k].incarnation, *messages[k], plan.take(parts[k]),
                                                      noise_level, record): k for k in jobs}
            lost, restarted = [], []
            pending = list(refs)
            while pending:
                ready, pending = ray.wait(pending, num_returns=1, timeout=self.cfg.timeout_s)
                if not ready:
                    break
                k, w = refs[ready[0]], self.workers[refs[ready[0]]]
                try:
                    reply = ray.get(ready[0])
                except _worker_lost_errors(ray) as err:
                    lost.append((k, str(err).strip().splitlines()[0] if str(err).strip() else type(err).__name__))
                    continue
                if reply is None:  # restarted by Ray since its last part: it played nothing
                    restarted.append(k)
                    continue
                w.incarnation, done[k], sync_s = reply
                self._hold(w, slot, fingerprint)
                self._add_metric("time/weight_push_s", sync_s)
                played += len(parts[k])
                if progress is not None:
                    progress(played, len(plan))
            for ref in pending:
                ray.kill(self.workers[refs[ref]].actor, no_restart=False)
                lost.append((refs[ref], f"no answer within ray.timeout_s={self.cfg.timeout_s}s"))
            for k, why in lost:
                self._lose(k, why, dropped=0 if record is None else len(parts[k]))
            for k in restarted:
                self._lose(k, "restarted since its last part", dropped=0)
            # Evaluation plays a fixed plan: a lost part is played again.
            jobs = restarted + ([k for k, _ in lost] if record is None else [])
        return done

    def _lose(self, k: int, why: str, dropped: int) -> None:
        """Worker ``k`` died or hung: Ray restarts it; its copies are gone."""
        w = self.workers[k]
        w.losses += 1
        w.incarnation = None
        w.weights.clear()
        self._add_metric("charts/worker_restarts", 1)
        self._add_metric("charts/dropped_episodes", dropped)
        if w.losses > self.cfg.max_restarts:
            raise RuntimeError(f"Ray rollout worker {k} was lost {w.losses} times (last: {why}), more than "
                               f"ray.max_restarts={self.cfg.max_restarts}; continue with `stepnft train --resume RUN_DIR`")
        print(f"stepnft: Ray rollout worker {k} lost ({why}); {dropped} episodes dropped", file=sys.stderr, flush=True)

    # --- metrics, shutdown -------------------------------------------------------------------
    def _add_metric(self, name: str, value: float) -> None:
        self._metrics[name] = self._metrics.get(name, 0.0) + float(value)

    def pop_metrics(self) -> dict[str, float]:
        """Since the last call: ``time/weight_push_s`` (driver serialisation + the slowest
        worker's copy), ``charts/weight_push_mb``, and after failures
        ``charts/worker_restarts`` and ``charts/dropped_episodes``."""
        out, self._metrics = self._metrics, {}
        return out

    def _call(self, k: int, method: str, *args):
        """``method`` of worker ``k``, waiting (up to ``ray.timeout_s``) while Ray restarts it."""
        ray, deadline = self._ray, time.monotonic() + self.cfg.timeout_s
        while True:
            try:
                return ray.get(getattr(self.workers[k].actor, method).remote(*args),
                               timeout=max(deadline - time.monotonic(), 0.01))
            except (ray.exceptions.ActorUnavailableError, ray.exceptions.GetTimeoutError):
                if time.monotonic() > deadline:
                    raise RuntimeError(f"Ray rollout worker {k} did not come back within ray.timeout_s="
                                       f"{self.cfg.timeout_s}s") from None
                time.sleep(0.2)
            except ray.exceptions.ActorDiedError as err:
                raise RuntimeError(f"Ray rollout worker {k} is gone for good ({str(err).splitlines()[0]}); "
                                   "continue with `stepnft train --resume RUN_DIR`") from err

    def worker_pids(self) -> list[int]:
        """The process id of each worker (e.g. to test what happens when one is killed)."""
        return [self._call(k, "pid") for k in range(len(self.workers))]

    def close(self) -> None:
        for w in self.workers:
            try:
                self._ray.kill(w.actor, no_restart=True)
            except Exception:  # noqa: BLE001 - already gone
                pass
        self.workers = []
        if self._owns_ray and self._ray.is_initialized():
            self._ray.shutdown()
        self._owns_ray = False


def _worker_lost_errors(ray) -> tuple[type[BaseException], ...]:
    """Errors that mean the worker (not the code it ran) is gone: Ray restarts it."""
    e = ray.exceptions
    return (e.RayActorError, e.WorkerCrashedError, e.OutOfMemoryError, e.NodeDiedError, e.ObjectLostError)


def _whole_groups(batch: Batch, group_size: int) -> torch.Tensor:
    """``[E]`` bool: episodes whose group (task, initial-state seed) came back whole."""
    key = batch.episode_task * 2**32 + batch.episode_seed
    _, inverse, counts = key.unique(return_inverse=True, return_counts=True)
    return counts[inverse] % group_size == 0
