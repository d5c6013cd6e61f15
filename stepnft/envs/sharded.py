"""A vector env that splits its sub-envs into shards, one worker process each.

MuJoCo is CPU-bound and single-threaded, so a batch of MetaWorld envs is fastest with one
process per core, each stepping its share of the batch in a loop. `ShardedVectorEnv` does
that: shard w owns sub-envs ``shards[w]`` (a range); every `reset`/`step`/`call` sends one
message per shard, all shards work at once, and the replies are put back in sub-env order.
Per step that is one pipe round trip per shard (gymnasium's AsyncVectorEnv needs one per
sub-env), carrying only small pickled arrays.

A step takes as long as the slowest shard, so the shards should cost the same. Batches are
usually laid out task by task (sub-env i runs task ``i // envs_per_task``) and tasks differ in
cost per step (MetaWorld pick-place ~3x drawer-open), so the default ``assignment="interleave"``
deals the sub-envs out like cards (worker w owns ``range(w, N, num_workers)``), which gives
every worker the same mix of tasks; ``"contiguous"`` gives worker w one contiguous block.

Besides gymnasium's batch `reset`/`step`, :meth:`ShardedVectorEnv.send_ops` /
:meth:`~ShardedVectorEnv.receive_ops` reset or step any subset of the sub-envs without waiting:
each shard holding one of them gets one message, several requests may be in flight at once
(each worker answers its messages in order), and the replies come back in request order. A
caller can so compute the next actions of some sub-envs while the workers step others
(``stepnft.rollout.collector``'s lanes).

Autoreset is always DISABLED: the sub-envs must answer a step after their episode ended
themselves (as `MetaWorldChunkEnv` does, with a no-op). Given the same env factories, seeds
and actions, results are bit-identical to a `gymnasium.vector.SyncVectorEnv` in one process.

Failures never hang the caller: an exception in a sub-env comes back as a one-line
RuntimeError naming the sub-env (the remote traceback is attached as a note, the original
exception as ``__cause__`` when it can be pickled), and the env stays usable; a worker that
dies or does not answer within `timeout` seconds raises a RuntimeError and closes the env.
Workers are terminated by `close()`, on garbage collection and at interpreter exit.
"""

from __future__ import annotations

import collections
import multiprocessing
import os
import signal
import time
import traceback
import weakref
from collections.abc import Callable, Sequence
from multiprocessing.connection import Connection, wait
from typing import Any

import gymnasium as gym
import numpy as np
from gymnasium.vector import AutoresetMode
from gymnasium.vector.utils import batch_space, concatenate, create_empty_array, iterate

__all__ = ["ShardedVectorEnv", "shard_ranges", "ASSIGNMENTS"]

ASSIGNMENTS = ("interleave", "contiguous")


def shard_ranges(num_envs: int, num_workers: int, assignment: str = "contiguous") -> list[range]:
    """`num_workers` (at most `num_envs`) disjoint ranges covering ``range(num_envs)``, sizes
    differing by <= 1 (the first shards get the extra sub-envs).

    "contiguous": consecutive blocks; "interleave": shard w is ``range(w, num_envs, num_workers)``.
    """
    if num_envs < 1 or num_workers < 1:
        raise ValueError(f"need num_envs >= 1 and num_workers >= 1, got {num_envs}, {num_workers}")
    if assignment not in ASSIGNMENTS:
        raise ValueError(f"assignment must be one of {ASSIGNMENTS}, got {assignment!r}")
    num_workers = min(num_workers, num_envs)
    if assignment == "interleave":
        return [range(w, num_envs, num_workers) for w in range(num_workers)]
    size, extra = divmod(num_envs, num_workers)
    ranges, start = [], 0
    for w in range(num_workers):
        stop = start + size + (w < extra)
        ranges.append(range(start, stop))
        start = stop
    return ranges


def _default_workers() -> int:
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:  # not on Linux
        return os.cpu_count() or 1


# ----------------------------------------------------------------------------- worker side


def _error_reply(index: int, exc: BaseException) -> tuple:
    remote_tb = "".join(traceback.format_exception(type(exc), exc, exc.__traceback__))
    try:  # the exception itself, if it survives a pickle round trip (for __cause__)
        import pickle

        payload = pickle.loads(pickle.dumps(exc))
        pickle.dumps(payload)
    except Exception:
        payload = None
    message = f"{type(exc).__name__}: {exc}"
    return ("error", (index, message, remote_tb, payload))


_BEAT: dict[str, Any] = {"conn": None, "last": 0.0}
"""In a worker process while it runs a ``run`` function: its pipe to the parent and when it
last reported progress."""


def heartbeat() -> None:
    """Say "still making progress" to the parent, from a function running in a worker
    (``ShardedVectorEnv.run``), e.g. after each env step: the parent then gives the worker
    ``timeout`` seconds from its latest beat rather than from the start of the command, so a long
    run on a loaded machine is not taken for a hung worker, and a stuck one still is. At most four
    messages a second; does nothing outside a running ``run`` function."""
    conn = _BEAT["conn"]
    now = time.monotonic()
    if conn is not None and now - _BEAT["last"] >= 0.25:
        _BEAT["last"] = now
        conn.send(("alive", None))


def _worker(indices: Sequence[int], env_fns: list[Callable[[], gym.Env]], conn: Connection,
            parent_conn: Connection | None) -> None:
    """Owns sub-envs ``indices`` (built by `env_fns`, in that order); answers one reply per
    command, with one result per owned sub-env, in the same order (one per worker for ``run``)."""
    # Ctrl-C goes to the whole process group: let the parent handle it and close us.
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    if parent_conn is not None:
        parent_conn.close()
    envs = _build_envs(indices, env_fns, conn)
    if envs is None:
        return
    try:
        while True:
            try:
                command, data = conn.recv()
            except (EOFError, OSError):  # the parent is gone
                break
            if command == "close":
                conn.send(("ok", None))
                break
            current = [indices[0]]  # the sub-env being worked on, for error reports
            _BEAT.update(conn=conn if command == "run" else None, last=time.monotonic())
            try:
                reply = ("ok", _answer(envs, indices, command, data, current))
            except Exception as exc:  # noqa: BLE001 - sent back to the parent
                reply = _error_reply(current[0], exc)
            finally:
                _BEAT["conn"] = None
            try:
                conn.send(reply)
            except Exception as exc:  # noqa: BLE001 - e.g. an attribute that cannot be pickled
                conn.send(_error_reply(indices[0], exc))
    finally:
        for env in envs:
            _quiet_close(env)
        conn.close()


def _build_envs(indices: Sequence[int], env_fns: list[Callable[[], gym.Env]], conn: Connection) -> list | None:
    """The worker's envs, their spaces checked and sent to the parent; None (after reporting the
    error and closing what was built) if that failed."""
    envs: list[gym.Env] = []
    index = indices[0]
    try:
        for j, fn in enumerate(env_fns):
            index = indices[j]
            envs.append(fn())
        first = envs[0]
        for j, env in enumerate(envs):
            index = indices[j]
            if env.observation_space != first.observation_space:
                raise RuntimeError(f"observation space {env.observation_space} differs from "
                                   f"sub-env {indices[0]}'s {first.observation_space}")
            if env.action_space != first.action_space:
                raise RuntimeError(f"action space {env.action_space} differs from "
                                   f"sub-env {indices[0]}'s {first.action_space}")
        conn.send(("ok", (first.observation_space, first.action_space, dict(first.metadata),
                          getattr(first, "render_mode", None))))
        return envs
    except BaseException as exc:  # noqa: BLE001 - report everything, then quit
        try:
            conn.send(_error_reply(index, exc))
        finally:
            for env in envs:
                _quiet_close(env)
            conn.close()
        return None


def _answer(envs: list[gym.Env], indices: Sequence[int], command: str, data: Any, current: list[int]) -> Any:
    """The results of one command; ``current[0]`` names the sub-env being worked on."""

    def each(items):
        for j, item in items:
            current[0] = indices[j]
            yield j, item

    if command == "reset":
        seeds, options, mask = data
        return [env.reset(seed=seeds[j], options=options) if mask is None or mask[j] else None
                for j, env in each(enumerate(envs))]
    if command == "step":
        return [env.step(action) for _, (env, action) in each(enumerate(zip(envs, data, strict=True)))]
    if command == "ops":
        return [envs[j].reset(seed=arg) if op == "reset" else envs[j].step(arg)
                for j, (op, arg) in each((j, (op, arg)) for j, op, arg in data)]
    if command == "run":
        fn, args = data
        return fn(envs, list(indices), *args)
    if command == "call":
        name, args, kwargs = data
        return [_called(env.get_wrapper_attr(name), args, kwargs) for _, env in each(enumerate(envs))]
    if command == "set_attr":
        name, values = data
        return [env.set_wrapper_attr(name, value) for _, (env, value) in each(enumerate(zip(envs, values, strict=True)))]
    raise ValueError(f"unknown command {command!r}")


def _called(attr: Any, args: tuple, kwargs: dict) -> Any:
    """``attr(*args, **kwargs)`` if it is callable, else ``attr`` (SyncVectorEnv's ``call``)."""
    return attr(*args, **kwargs) if callable(attr) else attr


def _quiet_close(env: gym.Env) -> None:
    try:
        env.close()
    except Exception:  # noqa: BLE001 - closing is best effort
        pass


# ----------------------------------------------------------------------------- parent side


class _Workers:
    """The worker processes and their pipes; `shutdown` is what `close()`, garbage
    collection and interpreter exit run (it must not refer to the vector env)."""

    def __init__(self) -> None:
        self.processes: list[multiprocessing.process.BaseProcess] = []
        self.conns: list[Connection] = []

    def shutdown(self, grace: float = 3.0) -> None:
        """Asks each worker to close its envs and exit; terminates, then kills, those that
        have not within `grace` seconds. Never raises; idempotent."""
        processes, conns = self.processes, self.conns
        self.processes, self.conns = [], []
        for process, conn in zip(processes, conns):
            if _quietly(process.is_alive, default=False):
                _quietly(conn.send, ("close", None))
        deadline = time.monotonic() + grace
        for process in processes:
            _quietly(process.join, max(0.0, deadline - time.monotonic()))
        for process in processes:
            if _quietly(process.is_alive, default=False):
                _quietly(process.terminate)
                _quietly(process.join, 1.0)
            if _quietly(process.is_alive, default=False):
                _quietly(process.kill)
                _quietly(process.join, 1.0)
        for conn in conns:
            _quietly(conn.close)
        for process in processes:
            _quietly(process.close)  # raises if it is somehow still alive


def _quietly(fn: Callable, *args: Any, default: Any = None) -> Any:
    try:
        return fn(*args)
    except Exception:  # noqa: BLE001 - shutting down is best effort
        return default


class ShardedVectorEnv(gym.vector.VectorEnv):
    """Sub-envs from `env_fns`, split into `num_workers` shards, one process each.

    Args:
        env_fns: one factory per sub-env (picklable under "spawn"/"forkserver", e.g.
            ``functools.partial``; lambdas work if cloudpickle is installed).
        num_workers: processes (default: the usable CPU cores), at most ``len(env_fns)``.
        assignment: "interleave" (default; worker w owns sub-envs i with i % num_workers == w,
            which balances a task-by-task layout), "contiguous" (worker w owns one block), or
            an explicit sequence giving each sub-env's worker (0..num_workers-1, each used).
            Either way every result is in sub-env order, and identical.
        timeout: seconds any one shard may take to answer a command (or to build its envs).
        context: multiprocessing start method; default "fork" where available.
        copy: unused (results are always fresh arrays); accepted for SyncVectorEnv parity.

    Observations are batched as gymnasium's vector envs do (Box -> [N, ...], Dict -> dict
    of [N, ...]); infos are combined like SyncVectorEnv's (``info[key]`` [N] with mask
    ``info["_" + key]``). `reset(seed=...)` takes None, an int (sub-env i gets seed + i) or
    one seed per sub-env, like SyncVectorEnv, and honours ``options["reset_mask"]``.
    """

    def __init__(
        self,
        env_fns: Sequence[Callable[[], gym.Env]],
        num_workers: int | None = None,
        timeout: float = 120.0,
        context: str | None = None,
        copy: bool = True,
        assignment: str | Sequence[int] = "interleave",
    ) -> None:
        super().__init__()
        env_fns = list(env_fns)
        if not env_fns:
            raise ValueError("ShardedVectorEnv needs at least one env factory")
        if timeout <= 0:
            raise ValueError(f"timeout must be > 0, got {timeout}")
        self.num_envs = len(env_fns)
        if num_workers is not None and num_workers < 1:
            raise ValueError(f"num_workers must be >= 1, got {num_workers}")
        if isinstance(assignment, str):
            self.assignment = assignment
            self.shards: list[Sequence[int]] = shard_ranges(self.num_envs, num_workers or _default_workers(),
                                                            assignment)
        else:
            self.assignment = "explicit"
            self.shards = _explicit_shards(assignment, self.num_envs, num_workers)
        self.num_workers = len(self.shards)
        self.timeout = float(timeout)
        self.copy = copy
        self.autoreset_mode = AutoresetMode.DISABLED
        self._shard_index = np.empty(self.num_envs, dtype=np.int64)
        self._position = np.empty(self.num_envs, dtype=np.int64)  # a sub-env's place in its shard
        for w, shard in enumerate(self.shards):
            self._shard_index[list(shard)] = w
            self._position[list(shard)] = np.arange(len(shard))
        self._in_flight: collections.deque[tuple[list[int], list[tuple[int, int]]]] = collections.deque()

        self._workers = _Workers()
        self._finalizer = weakref.finalize(self, self._workers.shutdown)
        self._start_workers(env_fns, context)
        try:
            spaces = self._gather("building the sub-envs")  # one reply per worker
        except BaseException:
            self.close()
            raise
        obs_space, act_space, metadata, render_mode = spaces[0]
        for w, (o, a, _, _) in enumerate(spaces[1:], start=1):
            if o != obs_space or a != act_space:
                self.close()
                raise RuntimeError(
                    f"sub-env {self.shards[w][0]} has spaces ({o}, {a}), sub-env 0 has "
                    f"({obs_space}, {act_space}); every sub-env must share them")
        self.single_observation_space = obs_space
        self.single_action_space = act_space
        self.observation_space = batch_space(obs_space, self.num_envs)
        self.action_space = batch_space(act_space, self.num_envs)
        self.metadata = dict(metadata)
        self.metadata["autoreset_mode"] = self.autoreset_mode
        self.render_mode = render_mode
        self._env_obs: list[Any] = [None] * self.num_envs

    def _start_workers(self, env_fns: list[Callable[[], gym.Env]], context: str | None) -> None:
        """One worker process per shard (``context``: the start method; default fork)."""
        if context is None:
            context = "fork" if "fork" in multiprocessing.get_all_start_methods() else "spawn"
        ctx = multiprocessing.get_context(context)
        for shard in self.shards:
            fns = [env_fns[i] for i in shard]
            if context != "fork":
                fns = [_picklable(fn) for fn in fns]
            parent_conn, child_conn = ctx.Pipe()
            process = ctx.Process(
                target=_worker,
                args=(list(shard), fns, child_conn, parent_conn),
                name=f"ShardedVectorEnv-worker-{len(self._workers.processes)}",
                daemon=True,
            )
            try:
                process.start()
            except BaseException:
                parent_conn.close()
                self.close()
                raise
            finally:
                child_conn.close()
            self._workers.processes.append(process)
            self._workers.conns.append(parent_conn)

    # ------------------------------------------------------------------ public API

    def shard_of(self, i: int) -> int:
        """The worker (shard) that owns sub-env `i`."""
        return int(self._shard_index[i])

    @property
    def worker_pids(self) -> list[int | None]:
        """Process ids of the workers (shard order)."""
        return [p.pid for p in self._workers.processes]

    @property
    def np_random_seed(self) -> tuple[int, ...]:
        return self.get_attr("np_random_seed")

    @property
    def np_random(self) -> tuple[np.random.Generator, ...]:
        return self.get_attr("np_random")

    def reset(
        self,
        *,
        seed: int | Sequence[int | None] | None = None,
        options: dict[str, Any] | None = None,
    ) -> tuple[Any, dict[str, Any]]:
        if seed is None:
            seed = [None] * self.num_envs
        elif isinstance(seed, (int, np.integer)):
            seed = [int(seed) + i for i in range(self.num_envs)]
        seed = [int(s) if isinstance(s, np.integer) else s for s in seed]
        if len(seed) != self.num_envs:
            raise ValueError(f"If seeds are passed as a list the length must match "
                             f"num_envs={self.num_envs} but got length={len(seed)}.")
        mask = None
        if options is not None and "reset_mask" in options:
            options = dict(options)
            mask = options.pop("reset_mask")
            if not isinstance(mask, np.ndarray) or mask.shape != (self.num_envs,) \
                    or mask.dtype != np.bool_ or not mask.any():
                raise ValueError(f"options['reset_mask'] must be a bool array of shape "
                                 f"({self.num_envs},) with a True value, got {mask!r}")
        results = self._request("reset", [
            (_take(seed, shard), options, None if mask is None else _take(mask, shard))
            for shard in self.shards
        ])
        infos: dict[str, Any] = {}
        for i, result in enumerate(results):
            if result is None:
                continue
            self._env_obs[i], env_info = result
            infos = self._add_info(infos, env_info, i)
        return self._batch_obs(), infos

    def step(self, actions: Any) -> tuple[Any, np.ndarray, np.ndarray, np.ndarray, dict[str, Any]]:
        if any(obs is None for obs in self._env_obs):
            raise RuntimeError("call reset() before step()")
        single = list(iterate(self.action_space, actions))
        if len(single) != self.num_envs:
            raise ValueError(f"expected actions for {self.num_envs} sub-envs, got {len(single)}")
        results = self._request("step", [_take(single, s) for s in self.shards])
        rewards = np.zeros(self.num_envs, dtype=np.float64)
        terminations = np.zeros(self.num_envs, dtype=np.bool_)
        truncations = np.zeros(self.num_envs, dtype=np.bool_)
        infos: dict[str, Any] = {}
        for i, (obs, reward, terminated, truncated, env_info) in enumerate(results):
            self._env_obs[i] = obs
            rewards[i], terminations[i], truncations[i] = reward, terminated, truncated
            infos = self._add_info(infos, env_info, i)
        return self._batch_obs(), rewards, terminations, truncations, infos

    def call(self, name: str, *args: Any, **kwargs: Any) -> tuple[Any, ...]:
        """Each sub-env's `name` attribute, called with the arguments if it is callable."""
        return tuple(self._request("call", [(name, args, kwargs)] * self.num_workers, f"call({name!r})"))

    def get_attr(self, name: str) -> tuple[Any, ...]:
        """Each sub-env's `name` attribute (called, if callable, like SyncVectorEnv)."""
        return self.call(name)

    def set_attr(self, name: str, values: Any) -> None:
        """Sets `name` on every sub-env: one value each (list/tuple of length N), or the same."""
        if not isinstance(values, (list, tuple)):
            values = [values] * self.num_envs
        if len(values) != self.num_envs:
            raise ValueError("Values must be a list or tuple with length equal to the number of "
                             f"environments. Got `{len(values)}` values for {self.num_envs} environments.")
        self._request("set_attr", [(name, list(_take(values, s))) for s in self.shards],
                      f"set_attr({name!r})")

    def send_ops(self, ops: Sequence[tuple[int, str, Any]]) -> None:
        """Start ``ops`` without waiting: ``(i, "reset", seed)`` resets sub-env ``i`` with that
        seed, ``(i, "step", action)`` steps it (each sub-env at most once). One message goes to
        each worker owning one of them; :meth:`receive_ops` returns the results."""
        if not ops:
            raise ValueError("send_ops needs at least one op")
        per_shard: dict[int, list[tuple[int, str, Any]]] = {}
        where = []
        for i, op, arg in ops:
            if op not in ("reset", "step"):
                raise ValueError(f"unknown op {op!r}: use 'reset' or 'step'")
            w = self.shard_of(i)
            where.append((w, len(per_shard.setdefault(w, []))))
            per_shard[w].append((int(self._position[i]), op, arg))
        workers = sorted(per_shard)
        try:
            self._send("ops", [per_shard[w] for w in workers], workers)
        except BaseException as exc:
            self._out_of_step(exc)
            raise
        self._in_flight.append((workers, where))

    def receive_ops(self) -> list[Any]:
        """The results of the oldest :meth:`send_ops` not yet received, in its op order:
        ``(obs, info)`` for a reset, ``(obs, reward, terminated, truncated, info)`` for a step."""
        if not self._in_flight:
            raise RuntimeError("receive_ops: no ops in flight")
        workers, where = self._in_flight.popleft()
        try:
            replies = dict(zip(workers, self._gather("ops", workers)))
        except BaseException as exc:
            self._out_of_step(exc)
            raise
        return [replies[w][k] for w, k in where]

    def run(self, fn: Callable, per_worker: list[tuple]) -> list[Any]:
        """``fn(envs, sub_envs, *per_worker[w])`` in every worker ``w`` at once, with its envs and
        their sub-env indices; returns each worker's result, in worker order. ``fn`` travels by
        name (a module-level function)."""
        if len(per_worker) != self.num_workers:
            raise ValueError(f"run needs arguments for each of the {self.num_workers} workers, got {len(per_worker)}")
        try:
            self._send("run", [(fn, tuple(args)) for args in per_worker])
            return self._gather(f"run({getattr(fn, '__name__', fn)})")
        except KeyboardInterrupt:
            self.close()
            raise

    def _out_of_step(self, exc: BaseException) -> None:
        """After a failed send or receive: a sub-env's error leaves the env usable, but an
        interrupt may leave replies on their way, so the pipes are out of step: close."""
        if isinstance(exc, KeyboardInterrupt):
            self._in_flight.clear()
            self.close()

    def render(self) -> tuple[Any, ...]:
        return self.call("render")

    def close_extras(self, **kwargs: Any) -> None:
        self._finalizer()

    def __repr__(self) -> str:
        return f"ShardedVectorEnv(num_envs={self.num_envs}, num_workers={self.num_workers})"

    # ------------------------------------------------------------------ plumbing

    def _batch_obs(self) -> Any:
        out = create_empty_array(self.single_observation_space, n=self.num_envs, fn=np.zeros)
        return concatenate(self.single_observation_space, self._env_obs, out)

    def _request(self, command: str, per_shard: list[Any], what: str | None = None) -> list[Any]:
        """One message per shard, then the per-sub-env results of all shards, in sub-env order."""
        try:
            self._send(command, per_shard)
            replies = self._gather(what or command)
        except KeyboardInterrupt:
            # Replies may still be on their way: the pipes are out of step for good.
            self.close()
            raise
        results: list[Any] = [None] * self.num_envs
        for shard, payload in zip(self.shards, replies, strict=True):
            if len(payload) != len(shard):
                raise RuntimeError(f"a ShardedVectorEnv worker answered {what or command} with "
                                   f"{len(payload)} results for {len(shard)} sub-envs")
            for i, result in zip(shard, payload):
                results[i] = result
        return results

    def _send(self, command: str, per_shard: list[Any], workers: Sequence[int] | None = None) -> None:
        """One message to each of ``workers`` (default: all), ``per_shard`` in that order."""
        if self.closed or not self._finalizer.alive:
            raise RuntimeError("ShardedVectorEnv is closed")
        if self._in_flight and command != "ops":
            raise RuntimeError(f"{command}: receive the ops in flight first (receive_ops)")
        workers = range(self.num_workers) if workers is None else workers
        for w, data in zip(workers, per_shard, strict=True):
            conn = self._workers.conns[w]
            try:
                conn.send((command, data))
            except (BrokenPipeError, ConnectionResetError, EOFError, OSError) as exc:
                self._fail(f"ShardedVectorEnv worker {w} (sub-envs {_span(self.shards[w])}) is "
                           f"gone: sending {command!r} failed with {type(exc).__name__}{self._exit_note(w)}")

    def _gather(self, what: str, workers: Sequence[int] | None = None) -> list[Any]:
        """The reply payload of each of ``workers`` (default: all), in that order; raises the
        error of the lowest sub-env that failed."""
        workers = list(range(self.num_workers)) if workers is None else list(workers)
        # A worker has `timeout` seconds from the command, or from its latest heartbeat().
        deadline = dict.fromkeys(workers, time.monotonic() + self.timeout)
        pending = {w: self._workers.conns[w] for w in workers}
        replies: dict[int, tuple] = {}
        while pending:
            remaining = min(deadline[w] for w in pending) - time.monotonic()
            sentinels = {self._workers.processes[w].sentinel: w for w in pending}
            ready = wait(list(pending.values()) + list(sentinels), timeout=max(0.0, remaining))
            if not ready:
                late = [w for w in pending if deadline[w] <= time.monotonic()]
                if not late:
                    continue
                self._fail(f"ShardedVectorEnv worker(s) {', '.join(map(str, late))} did not answer {what} "
                           f"within {self.timeout:g} s (timeout); the env was closed")
            for w, conn in list(pending.items()):
                if conn in ready or (self._workers.processes[w].sentinel in ready and conn.poll()):
                    try:
                        reply = conn.recv()
                    except (EOFError, OSError, ConnectionResetError):
                        self._fail(self._died(w, what))
                    if reply[0] == "alive":
                        deadline[w] = time.monotonic() + self.timeout
                        continue
                    replies[w] = reply
                    del pending[w]
                elif self._workers.processes[w].sentinel in ready:
                    self._fail(self._died(w, what))
        results: list[Any] = []
        error = None
        for w in workers:
            status, payload = replies[w]
            if status == "error":
                if error is None or payload[0] < error[0]:
                    error = payload
            else:
                results.append(payload)
        if error is not None:
            index, message, remote_tb, cause = error
            line = " ".join(message.split())
            exc = RuntimeError(f"sub-env {index} (worker {self.shard_of(index)}) raised in "
                               f"{what}: {line}")
            if hasattr(exc, "add_note"):  # Python >= 3.11: shown in tracebacks, not in str()
                exc.add_note(f"Traceback in the worker:\n{remote_tb}")
            raise exc from cause
        return results

    def _died(self, w: int, what: str) -> str:
        return (f"ShardedVectorEnv worker {w} (sub-envs {_span(self.shards[w])}) died during "
                f"{what}{self._exit_note(w)}; the env was closed")

    def _exit_note(self, w: int) -> str:
        process = self._workers.processes[w]
        process.join(0.1)
        code = process.exitcode
        if code is None:
            return ""
        if code < 0:
            try:
                return f" (killed by {signal.Signals(-code).name})"
            except ValueError:
                return f" (exit code {code})"
        return f" (exit code {code})"

    def _fail(self, message: str) -> None:
        """A worker is lost or stuck: the shards are out of step, so close everything
        (with little grace: a stuck worker will not answer "close" anyway)."""
        self._workers.shutdown(grace=0.2)
        self.close()
        raise RuntimeError(message)


def _explicit_shards(assignment: Sequence[int], num_envs: int, num_workers: int | None) -> list[list[int]]:
    """Shards from each sub-env's worker; every worker must own at least one sub-env."""
    owner = [int(w) for w in assignment]
    workers = max(owner, default=-1) + 1
    if len(owner) != num_envs or min(owner, default=0) < 0 or (num_workers is not None and workers > num_workers):
        raise ValueError(f"assignment must give each of the {num_envs} sub-envs a worker in 0..{(num_workers or workers) - 1}, "
                         f"got {list(assignment)}")
    shards = [[i for i, w in enumerate(owner) if w == k] for k in range(workers)]
    if not all(shards):
        raise ValueError(f"assignment leaves a worker without sub-envs: {list(assignment)}")
    return shards


def _span(shard: Sequence[int]) -> str:
    if len(shard) == 1:
        return str(shard[0])
    if isinstance(shard, range):
        step = f" step {shard.step}" if shard.step != 1 else ""
        return f"{shard.start}..{shard[-1]}{step}"
    return ",".join(map(str, shard))


def _take(seq: Any, shard: Sequence[int]) -> Any:
    """The items of a list/tuple/array at the sub-envs of `shard` (a slice for a range)."""
    if isinstance(shard, range):
        return seq[shard.start:shard.stop:shard.step]
    return [seq[i] for i in shard]


def _picklable(fn: Callable) -> Callable:
    """Wraps `fn` for cloudpickle when that is installed (lambdas, closures), else as is."""
    try:
        import cloudpickle  # noqa: F401
    except ImportError:
        return fn
    from gymnasium.vector.utils import CloudpickleWrapper

    return CloudpickleWrapper(fn)
