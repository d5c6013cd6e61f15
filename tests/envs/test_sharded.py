import multiprocessing
import os
import signal
import time
from functools import partial

import gymnasium as gym
import numpy as np
import pytest
from gymnasium.vector import AutoresetMode

try:
    from stepnft.envs.metaworld import MetaWorldChunkEnv
except ImportError:  # the env module's newer home
    from stepnft.envs.metaworld.env import MetaWorldChunkEnv
from stepnft.envs.sharded import ShardedVectorEnv, heartbeat, shard_ranges

N_EXEC = 4
TASKS = ["reach-v3", "push-v3"]
ENVS_PER_TASK = 3


def env_fns(max_episode_steps: int = 20):
    return [
        partial(MetaWorldChunkEnv, task, n_exec=N_EXEC, max_episode_steps=max_episode_steps, seed=100 + i)
        for i, task in enumerate(t for t in TASKS for _ in range(ENVS_PER_TASK))
    ]


def task_layout(venv):
    return list(venv.get_attr("task"))


class SyncNoAutoreset(gym.vector.SyncVectorEnv):
    """SyncVectorEnv with autoreset disabled that lets finished sub-envs answer no-op steps."""

    def __init__(self, fns):
        super().__init__(fns, autoreset_mode=AutoresetMode.DISABLED)

    def step(self, actions):
        self._autoreset_envs[:] = False
        return super().step(actions)


def play_wave(venv, seeds, rng):
    """One wave from `reset(seed=seeds)` until every sub-env is done; all returns, in order."""
    out = [venv.reset(seed=seeds)]
    done = np.zeros(venv.num_envs, dtype=bool)
    while not done.all():
        actions = rng.uniform(-1, 1, size=(venv.num_envs, N_EXEC, 4)).astype(np.float32)
        out.append(venv.step(actions))
        done |= out[-1][2] | out[-1][3]
    return out


def assert_identical(a, b):
    if isinstance(a, dict):
        assert a.keys() == b.keys()
        for key in a:
            assert_identical(a[key], b[key])
    elif isinstance(a, (tuple, list)):
        assert len(a) == len(b)
        for x, y in zip(a, b):
            assert_identical(x, y)
    elif isinstance(a, np.ndarray):
        assert isinstance(b, np.ndarray) and a.dtype == b.dtype and a.shape == b.shape
        assert np.array_equal(a, b)  # bit-identical: no tolerance
    else:
        assert type(a) is type(b) and a == b


@pytest.fixture
def sharded():
    venv = ShardedVectorEnv(env_fns(), num_workers=2, timeout=30)
    yield venv
    venv.close()


def test_shard_ranges_are_balanced():
    assert shard_ranges(5, 2) == [range(0, 3), range(3, 5)]
    assert shard_ranges(2, 4) == [range(0, 1), range(1, 2)]
    assert shard_ranges(6, 3) == [range(0, 2), range(2, 4), range(4, 6)]
    assert shard_ranges(5, 2, "interleave") == [range(0, 5, 2), range(1, 5, 2)]
    assert shard_ranges(2, 4, "interleave") == [range(0, 2, 2), range(1, 2, 2)]
    assert shard_ranges(20, 2, "interleave") == [range(0, 20, 2), range(1, 20, 2)]
    for n in range(1, 12):
        for w in range(1, 5):
            for assignment in ("contiguous", "interleave"):
                shards = shard_ranges(n, w, assignment)
                assert sorted(i for s in shards for i in s) == list(range(n))
                assert max(map(len, shards)) - min(map(len, shards)) <= 1
    with pytest.raises(ValueError, match="assignment"):
        shard_ranges(4, 2, "round-robin")


def test_default_assignment_interleaves(sharded):
    assert sharded.assignment == "interleave"
    assert [sharded.shard_of(i) for i in range(6)] == [0, 1, 0, 1, 0, 1]
    # Each worker gets the same mix of tasks.
    assert task_layout(sharded) == ["reach-v3"] * 3 + ["push-v3"] * 3


@pytest.mark.parametrize("assignment, num_envs", [
    ("contiguous", 6), ("interleave", 6), ("contiguous", 5), ("interleave", 5)])
def test_matches_sync_vector_env_bit_for_bit(assignment, num_envs):
    fns = env_fns()[:num_envs]
    sharded = ShardedVectorEnv(fns, num_workers=2, timeout=30, assignment=assignment)
    reference = SyncNoAutoreset(fns)
    try:
        assert sharded.num_envs == num_envs and sharded.num_workers == 2
        owners = [i // 3 for i in range(num_envs)] if assignment == "contiguous" else [i % 2 for i in range(num_envs)]
        assert [sharded.shard_of(i) for i in range(num_envs)] == owners
        assert sharded.autoreset_mode == AutoresetMode.DISABLED
        assert sharded.single_observation_space == reference.single_observation_space
        assert sharded.observation_space == reference.observation_space
        assert sharded.action_space == reference.action_space
        seed_lists = [[0, 1, 2, 0, 1, 2][:num_envs], [7, 8, 9, 10, 11, 12][:num_envs]]
        for wave, seeds in enumerate(seed_lists):
            ours = play_wave(sharded, seeds, np.random.default_rng(wave))
            theirs = play_wave(reference, seeds, np.random.default_rng(wave))
            assert len(ours) == len(theirs) > 2
            assert_identical(ours, theirs)
            assert ours[-1][4]["steps"].shape == (num_envs,)
        # An unseeded reset continues each sub-env's own stream, identically; so does an int
        # seed (sub-env i gets seed + i) and a partial reset (the mask routed per sub-env).
        assert_identical(sharded.reset(), reference.reset())
        assert_identical(sharded.reset(seed=40), reference.reset(seed=40))
        mask = np.arange(num_envs) % 3 != 1
        seeds = list(range(50, 50 + num_envs))
        assert_identical(sharded.reset(seed=seeds, options={"reset_mask": mask}),
                         reference.reset(seed=seeds, options={"reset_mask": mask}))
        actions = np.random.default_rng(9).uniform(-1, 1, (num_envs, N_EXEC, 4)).astype(np.float32)
        assert_identical(sharded.step(actions), reference.step(actions))
        assert sharded.get_attr("task") == reference.get_attr("task")
        assert sharded.call("_info", 3) == reference.call("_info", 3)
    finally:
        sharded.close()
        reference.close()


def test_set_attr_and_get_attr_keep_sub_env_order_when_interleaved(sharded):
    assert sharded.assignment == "interleave"
    limits = [N_EXEC * (i + 1) for i in range(6)]  # sub-env i truncates after i + 1 vector steps
    sharded.set_attr("max_episode_steps", limits)
    assert sharded.get_attr("max_episode_steps") == tuple(limits)
    sharded.set_attr("max_episode_steps", tuple(limits))  # a tuple works too
    # The values reached the right sub-envs: they truncate one after the other.
    sharded.reset(seed=list(range(6)))
    zeros = np.zeros((6, N_EXEC, 4), np.float32)
    for k in range(6):
        _, _, terminated, truncated, info = sharded.step(zeros)
        assert (truncated | terminated).tolist() == [i <= k for i in range(6)]
        assert info["episode_steps"].tolist() == [min(limit, N_EXEC * (k + 1)) for limit in limits]


def test_np_random_round_trip(sharded):
    states = [rng.bit_generator.state for rng in sharded.get_attr("np_random")]
    first = sharded.reset()[0]
    rngs = []
    for state in states:
        rng = np.random.Generator(np.random.PCG64())
        rng.bit_generator.state = state
        rngs.append(rng)
    sharded.set_attr("np_random", rngs)
    assert [r.bit_generator.state for r in sharded.get_attr("np_random")] == states
    assert_identical(sharded.reset()[0], first)
    sharded.set_attr("max_episode_steps", 7)  # one value for all
    assert sharded.get_attr("max_episode_steps") == (7,) * 6
    with pytest.raises(ValueError, match="length"):
        sharded.set_attr("max_episode_steps", [1, 2])


def test_worker_exception_is_one_line_and_env_survives(sharded):
    sharded.reset(seed=0)
    with pytest.raises(RuntimeError) as error:
        sharded.step(np.zeros((6, 2 * N_EXEC, 4), np.float32))
    message = str(error.value)
    assert "\n" not in message
    assert message.startswith("sub-env 0 (worker 0)")
    assert "ValueError" in message and "(4, 4)" in message
    assert isinstance(error.value.__cause__, ValueError)
    # Every shard fails here; the first sub-env that raised is reported.
    with pytest.raises(RuntimeError, match=r"^sub-env 0 \(worker 0\) raised in call.*AttributeError"):
        sharded.call("no_such_method")
    # Both shards still answer.
    _, _, _, _, info = sharded.step(np.zeros((6, N_EXEC, 4), np.float32))
    assert info["steps"].tolist() == [N_EXEC] * 6


def test_killed_worker_raises_instead_of_hanging(sharded):
    sharded.reset(seed=0)
    os.kill(sharded.worker_pids[1], signal.SIGKILL)
    start = time.monotonic()
    with pytest.raises(RuntimeError, match="worker 1.*(died|gone)"):
        sharded.step(np.zeros((6, N_EXEC, 4), np.float32))
    assert time.monotonic() - start < 10
    assert sharded.closed and not multiprocessing.active_children()
    with pytest.raises(RuntimeError, match="closed"):
        sharded.reset()


class DictEnv(gym.Env):
    """Dict observations and a non-scalar info, to check the batching of both."""

    observation_space = gym.spaces.Dict({
        "pos": gym.spaces.Box(-10.0, 10.0, (2,), np.float32),
        "count": gym.spaces.Discrete(100),
    })
    action_space = gym.spaces.Box(-1.0, 1.0, (2,), np.float32)

    def reset(self, *, seed=None, options=None):
        super().reset(seed=seed)
        self.pos = self.np_random.normal(size=2).astype(np.float32)
        self.count = 0
        return self._obs(), {"pos": self.pos.copy(), "count": 0}

    def step(self, action):
        self.pos = self.pos + np.asarray(action, np.float32)
        self.count += 1
        return self._obs(), float(self.pos.sum()), self.count >= 3, False, {"pos": self.pos.copy(), "count": self.count}

    def _obs(self):
        return {"pos": self.pos.copy(), "count": self.count}


def test_dict_observations_match_sync_vector_env():
    fns = [DictEnv] * 5
    venv, reference = ShardedVectorEnv(fns, num_workers=2), SyncNoAutoreset(fns)
    try:
        assert venv.observation_space == reference.observation_space
        rng_a, rng_b = np.random.default_rng(3), np.random.default_rng(3)
        ours = [venv.reset(seed=np.arange(5))] + [venv.step(rng_a.uniform(-1, 1, (5, 2)).astype(np.float32)) for _ in range(4)]
        theirs = [reference.reset(seed=list(range(5)))] + [reference.step(rng_b.uniform(-1, 1, (5, 2)).astype(np.float32)) for _ in range(4)]
        assert_identical(ours, theirs)
        assert ours[1][0]["pos"].shape == (5, 2) and ours[1][4]["pos"].shape == (5, 2)
    finally:
        venv.close()
        reference.close()


@pytest.mark.parametrize("assignment, worker", [("contiguous", 1), ("interleave", 0)])
def test_failing_factory_raises_and_cleans_up(assignment, worker):
    fns = env_fns()[:2] + [partial(MetaWorldChunkEnv, "no-such-task-v3")]
    with pytest.raises(RuntimeError, match=rf"^sub-env 2 \(worker {worker}\) raised in building the sub-envs: ValueError"):
        ShardedVectorEnv(fns, num_workers=2, assignment=assignment)
    assert not multiprocessing.active_children()


def test_bad_assignment_is_refused():
    with pytest.raises(ValueError, match="assignment"):
        ShardedVectorEnv([DictEnv] * 2, num_workers=2, assignment="random")
    assert not multiprocessing.active_children()


class SlowEnv(gym.Env):
    observation_space = gym.spaces.Box(-1.0, 1.0, (2,), np.float32)
    action_space = gym.spaces.Discrete(2)

    def reset(self, *, seed=None, options=None):
        super().reset(seed=seed)
        return np.zeros(2, np.float32), {}

    def step(self, action):
        time.sleep(60)
        return np.zeros(2, np.float32), 0.0, False, False, {}


def test_unresponsive_worker_times_out():
    venv = ShardedVectorEnv([SlowEnv, SlowEnv], num_workers=2, timeout=1.0)
    venv.reset()
    start = time.monotonic()
    with pytest.raises(RuntimeError, match="did not answer step within 1 s"):
        venv.step(np.zeros(2, np.int64))
    assert time.monotonic() - start < 5
    assert venv.closed and not multiprocessing.active_children()


def _busy(envs, sub_envs, seconds, beat):
    """A run function that works for ``seconds``, reporting progress if ``beat``."""
    end = time.monotonic() + seconds
    while time.monotonic() < end:
        time.sleep(0.05)
        if beat:
            heartbeat()
    return len(envs)


def test_a_long_run_that_reports_progress_is_waited_for_and_a_silent_one_times_out():
    venv = ShardedVectorEnv(env_fns()[:2], num_workers=2, timeout=60)
    venv.timeout = 1.0  # after the envs are built (slow on a loaded machine)
    heartbeat()  # outside a worker: nothing happens
    assert venv.run(_busy, [(3.0, True), (0.1, False)]) == [1, 1]  # 3 s on a 1 s timeout
    assert venv.run(_busy, [(0.1, False), (0.1, False)]) == [1, 1]  # no beat left in the pipe
    with pytest.raises(RuntimeError, match=r"worker\(s\) 1 did not answer run\(_busy\) within 1 s"):
        venv.run(_busy, [(3.0, True), (3.0, False)])
    assert venv.closed and not multiprocessing.active_children()


def test_close_leaves_no_children():
    venv = ShardedVectorEnv(env_fns()[:3], num_workers=3)
    assert len(multiprocessing.active_children()) == 3
    venv.reset(seed=1)
    venv.close()
    venv.close()  # idempotent
    assert not multiprocessing.active_children()
    # Garbage collection closes the workers too.
    venv = ShardedVectorEnv(env_fns()[:2], num_workers=2)
    pids = venv.worker_pids
    del venv
    assert not multiprocessing.active_children()
    for pid in pids:
        with pytest.raises(ProcessLookupError):
            os.kill(pid, 0)


# --- ops on any subset, several requests in flight ------------------------------------------------
def test_ops_on_subsets_match_the_envs_stepped_alone():
    """send_ops / receive_ops: resets and steps of some sub-envs, two requests in flight at once,
    results in op order; the same as stepping each env by itself."""
    venv = ShardedVectorEnv(env_fns(), num_workers=2, timeout=30, assignment=[0, 0, 1, 1, 0, 1])
    reference = [fn() for fn in env_fns()]
    try:
        assert venv.assignment == "explicit" and venv.shards == [[0, 1, 4], [2, 3, 5]]
        rng = np.random.default_rng(0)
        venv.send_ops([(5, "reset", 7), (0, "reset", 8), (2, "reset", 9)])
        venv.send_ops([(3, "reset", 10)])  # in flight with the first request
        assert_identical(venv.receive_ops(), [reference[5].reset(seed=7), reference[0].reset(seed=8),
                                              reference[2].reset(seed=9)])
        assert_identical(venv.receive_ops(), [reference[3].reset(seed=10)])
        for _ in range(3):
            chunks = rng.uniform(-1, 1, size=(3, N_EXEC, 4)).astype(np.float32)
            ops = [(2, "step", chunks[0]), (5, "step", chunks[1]), (3, "step", chunks[2])]
            venv.send_ops(ops)
            assert_identical(venv.receive_ops(), [reference[i].step(c) for i, _, c in ops])
        with pytest.raises(RuntimeError, match="no ops in flight"):
            venv.receive_ops()
        venv.send_ops([(1, "step", np.zeros((2 * N_EXEC, 4), np.float32))])  # never reset, wrong shape
        with pytest.raises(RuntimeError, match=r"^sub-env 1 \(worker 0\) raised in ops"):
            venv.receive_ops()
        venv.send_ops([(1, "reset", 3)])  # a sub-env's error leaves the env usable
        assert_identical(venv.receive_ops(), [reference[1].reset(seed=3)])
        with pytest.raises(ValueError, match="unknown op"):
            venv.send_ops([(1, "render", None)])
    finally:
        venv.close()
        for env in reference:
            env.close()


def test_explicit_assignment_is_checked():
    with pytest.raises(ValueError, match="assignment must give each"):
        ShardedVectorEnv([DictEnv] * 3, num_workers=2, assignment=[0, 1])
    with pytest.raises(ValueError, match="without sub-envs"):
        ShardedVectorEnv([DictEnv] * 3, num_workers=3, assignment=[0, 2, 2])
