"""Rollouts on Ray workers: the same episodes as the local collector, weights pushed only when
they changed, lost and hung workers restarted with their episodes dropped, evaluation on the
workers, nothing left running after close. One local Ray (2 CPUs) serves the module; the
merging of workers' parts is tested without Ray."""

import contextlib
import json
import os
import shutil
import signal
import socket
import subprocess
import sys
import tempfile
import textwrap
import threading
import time
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
import torch

from stepnft.batch import Batch
from stepnft.config import EnvConfig, RayConfig
from stepnft.envs import make_vec_env
from stepnft.evaluate import evaluate_policy
from stepnft.policies.flow import FlowPolicy, FlowPolicyConfig
from stepnft.rollout.collector import Collector
from stepnft.rollout.plan import EpisodePlan, RolloutSpec
from stepnft.rollout.ray_collector import merge_parts

GOAL, HAND = slice(36, 39), slice(0, 3)
ENV = EnvConfig(tasks=["reach-v3", "push-v3"], envs_per_task=3, max_episode_steps=80)
SEED = 7


class GoalSeeker(FlowPolicy):
    """A random flow policy steered toward the reach goal: successes depend on the initial
    state and the sampler's noise (so comparing outcomes means something)."""

    def sample(self, obs, noise_level=0.0, generator=None, stochastic_steps="all", keep_path=False, **kwargs):
        out = super().sample(obs, noise_level, generator, stochastic_steps, keep_path, **kwargs)
        out.actions[..., :3] += 10.0 * (obs["state"][:, None, GOAL] - obs["state"][:, None, HAND])
        return out


class SlowSeeker(GoalSeeker):
    """Sleeps in every policy call: long episodes that cost no CPU (to kill a worker mid-part)."""

    delay = 0.1

    def sample(self, obs, *args, **kwargs):
        time.sleep(self.delay)
        return super().sample(obs, *args, **kwargs)


def goal_seeker(seed: int = 0, cls=GoalSeeker) -> GoalSeeker:
    torch.manual_seed(seed)
    return cls(FlowPolicyConfig(lang_dim=0, hidden_dim=16, num_layers=1, state_clip=100.0))


def assert_same_batch(local: Batch, remote: Batch) -> None:
    """Episodes, links and masks exactly; floats nearly: a policy forward on a worker's smaller
    batch may round the last bits differently, and contacts in the simulator amplify that."""
    for key in ("episode_success", "episode_task", "episode_length", "episode_seed", "episode", "call", "mask", "done"):
        assert torch.equal(getattr(local, key), getattr(remote, key)), key
    for key in ("actions", "x_t", "x_next", "v_old", "t", "dt", "reward"):
        torch.testing.assert_close(getattr(local, key), getattr(remote, key), rtol=1e-2, atol=1e-2)
    torch.testing.assert_close(local.obs["state"], remote.obs["state"], rtol=1e-2, atol=1e-2)


# --- merging the workers' parts (no Ray needed) -------------------------------------------------
def test_merged_parts_of_a_plan_are_the_whole_plan_in_its_order():
    venv = make_vec_env(ENV, 4, SEED)
    policy = goal_seeker()
    spec = RolloutSpec(0.3, record_steps="all")
    plan = EpisodePlan(task=[0, 0, 0, 1, 1, 1], seed=range(100, 106), noise_seed=range(6))
    whole = Collector(venv).play(policy, plan, 0.3, record=spec)
    rows = [np.array([0, 3]), np.array([1, 4]), np.array([5, 2])]  # the workers' shares, any order
    parts = [Collector(venv).play(policy, plan.take(r), 0.3, record=spec) for r in rows]
    merged = merge_parts(parts, rows)
    assert_same_batch(whole, merged)
    assert whole.episode_success.any() and not whole.episode_success.all()

    keep = torch.tensor([True, True, True, False, True, True])  # drop plan row 4 with its calls and steps
    kept = merge_parts(parts, rows, keep)
    assert kept.num_episodes == 5 and kept.episode_seed.tolist() == [100, 101, 102, 103, 105]
    calls, steps = merged.episode != 4, merged.step_episode != 4
    assert torch.equal(kept.actions, merged.actions[calls]) and torch.equal(kept.x_t, merged.x_t[steps])
    assert torch.equal(kept.step_episode, merged.step_episode[steps] - (merged.step_episode[steps] > 4).long())
    venv.close()


# --- on Ray ----------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def ray_instance():
    ray = pytest.importorskip("ray", reason='the Ray tests need the ray extra: pip install "stepnft[ray]"')
    # 4 logical CPUs: the module's 2 workers and a training run's 2 at once (mostly idle; the
    # machine's 2 cores do the work).
    ray.init(num_cpus=4, include_dashboard=False, object_store_memory=80 * 2**20, log_to_driver=False)
    # The test's policy class travels by value (the workers cannot import this test module).
    ray.cloudpickle.register_pickle_by_value(sys.modules[__name__])
    yield ray
    ray.shutdown()


@pytest.fixture(scope="module")
def collectors(ray_instance):
    """A Ray collector over 2 workers and a local one over the same sub-envs and seeds."""
    from stepnft.rollout.ray_collector import RayCollector

    remote = RayCollector(ENV, 4, SEED, RayConfig(workers=2, timeout_s=120, max_restarts=10))
    local = Collector(make_vec_env(ENV, 4, SEED), seed=SEED)
    yield local, remote
    remote.close()
    local.close()


@pytest.fixture
def synced(collectors):
    """Both collectors in the local one's current state (tests share them)."""
    local, remote = collectors
    remote.load_state_dict(local.state_dict())
    remote.pop_metrics()
    return local, remote


def test_same_episodes_as_the_local_collector(synced):
    local, remote = synced
    policy = goal_seeker()
    cases = [(RolloutSpec(0.3), 9, None), (RolloutSpec(0.3, record_steps="all"), 0, [2, 3]),
             (RolloutSpec(0.3, group_size=3), 6, None)]
    for spec, episodes, task_episodes in cases:
        mine, theirs = local.collect(policy, episodes, spec, task_episodes), remote.collect(policy, episodes, spec, task_episodes)
        assert_same_batch(mine, theirs)
    assert theirs.episode_seed.unique().numel() == 2  # one initial state per group of 3
    assert mine.episode_success.any()
    assert torch.equal(local.state_dict()["generator"], remote.state_dict()["generator"])
    assert evaluate_policy(policy, local, 5, seed=3) == evaluate_policy(policy, remote, 5, seed=3)


def test_weights_are_pushed_only_when_they_changed(synced):
    local, remote = synced
    policy = goal_seeker(1)
    spec = RolloutSpec(0.3)
    whole = sum(t.numel() * 4 for t in policy.state_dict().values()) / 2**20
    remote.collect(policy, 6, spec)
    assert remote.pop_metrics()["charts/weight_push_mb"] == pytest.approx(whole)  # the whole policy, put once
    remote.collect(policy, 6, spec)
    assert remote.pop_metrics()["charts/weight_push_mb"] == 0
    with torch.no_grad():
        policy.net[0].weight.add_(0.1)  # one tensor written in place, as an optimizer step does
    remote.load_state_dict(local.state_dict())
    assert_same_batch(local.collect(policy, 6, spec), remote.collect(policy, 6, spec))  # the workers' copies follow
    assert remote.pop_metrics()["charts/weight_push_mb"] == pytest.approx(policy.net[0].weight.numel() * 4 / 2**20)
    assert remote.push(policy) > 0 and remote.pop_metrics()["charts/weight_push_mb"] == 0


def test_a_worker_killed_mid_part_is_restarted_and_its_episodes_dropped(synced):
    local, remote = synced
    policy = goal_seeker(cls=SlowSeeker)
    with torch.no_grad():
        policy.net[-1].weight.zero_()
    remote.push(policy)
    pid = remote.worker_pids()[0]
    losses = remote.workers[0].losses
    state = local.state_dict()
    threading.Timer(0.4, os.kill, (pid, signal.SIGKILL)).start()  # a part takes >= 10 calls x 0.1 s
    batch = remote.collect(policy, 6, RolloutSpec(0.3))
    metrics = remote.pop_metrics()
    # Episode j of a task goes to worker j mod 2: worker 0 had plan rows 0, 2, 3, 5.
    assert metrics["charts/worker_restarts"] == 1 and metrics["charts/dropped_episodes"] == 4
    assert remote.workers[0].losses == losses + 1 and remote.worker_pids()[0] != pid
    whole = local.collect(policy, 6, RolloutSpec(0.3))
    assert batch.episode_seed.tolist() == whole.episode_seed[[1, 4]].tolist()
    assert batch.episode_length.tolist() == whole.episode_length[[1, 4]].tolist()
    local.load_state_dict(state)
    assert remote.collect(policy, 6, RolloutSpec(0.3)).num_episodes == 6  # the restarted worker plays again


def test_a_hung_worker_times_out_instead_of_deadlocking(synced):
    _, remote = synced
    policy = goal_seeker()
    remote.collect(policy, 6, RolloutSpec(0.3))  # workers hold the policy
    remote.pop_metrics()
    pid = remote.worker_pids()[1]
    os.kill(pid, signal.SIGSTOP)  # alive but silent
    # The healthy worker must finish within it, and the hung one's restart too, even on a loaded
    # machine (10 s was too short for the restart with both cores oversubscribed 4 times).
    remote.cfg = replace(remote.cfg, timeout_s=30.0)
    try:
        start = time.perf_counter()
        batch = remote.collect(policy, 6, RolloutSpec(0.3))
        assert time.perf_counter() - start < 120
    finally:
        remote.cfg = replace(remote.cfg, timeout_s=120)
    metrics = remote.pop_metrics()
    assert metrics["charts/dropped_episodes"] == 2 and batch.num_episodes == 4
    assert remote.worker_pids()[1] != pid
    assert remote.collect(policy, 6, RolloutSpec(0.3)).num_episodes == 6


def test_evaluation_plays_a_lost_part_again(synced):
    local, remote = synced
    policy = goal_seeker()
    remote.collect(policy, 6, RolloutSpec(0.3))
    os.kill(remote.worker_pids()[0], signal.SIGKILL)
    assert evaluate_policy(policy, remote, 4, seed=11) == evaluate_policy(policy, local, 4, seed=11)
    assert remote.pop_metrics()["charts/worker_restarts"] >= 1


def test_a_worker_lost_too_often_stops_with_an_error(synced):
    _, remote = synced
    policy = goal_seeker()
    remote.collect(policy, 6, RolloutSpec(0.3))
    limit = remote.cfg.max_restarts
    remote.cfg = replace(remote.cfg, max_restarts=remote.workers[0].losses)
    try:
        os.kill(remote.worker_pids()[0], signal.SIGKILL)
        time.sleep(0.5)
        with pytest.raises(RuntimeError, match="more than ray.max_restarts"):
            remote.collect(policy, 6, RolloutSpec(0.3))
    finally:
        remote.cfg = replace(remote.cfg, max_restarts=limit)


def test_workers_that_do_not_fit_the_cluster_say_so_and_time_out(ray_instance, capsys):
    from stepnft.rollout.ray_collector import RayCollector

    # 2 workers x 3 simulator processes need 6 CPUs; the test's Ray has 4: Ray would queue them
    # silently, so the collector says so at once and gives up after ray.timeout_s.
    env = replace(ENV, num_workers=3)
    with pytest.raises(RuntimeError, match="need 6 CPUs, the cluster has 4"):
        RayCollector(env, 4, SEED, RayConfig(workers=2, timeout_s=3))
    assert "need 6 CPUs (max(1, env.num_workers)=3 each) but the Ray cluster has 4" in capsys.readouterr().err


def test_train_joins_an_existing_cluster(tmp_path):
    """`--ray.address` joins a cluster started with `ray start`: the run's workers play there and
    the cluster outlives the run (the driver only disconnects)."""
    pytest.importorskip("ray", reason='the Ray tests need the ray extra: pip install "stepnft[ray]"')
    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        port = probe.getsockname()[1]
    temp_dir = tempfile.mkdtemp(prefix="stepnft-ray-", dir="/tmp")  # Ray's socket paths must stay short
    # Token authentication is Ray's business (docs/scaling.md says how to pass the token): off here.
    env = os.environ | {"RAY_AUTH_MODE": "disabled"}
    head = subprocess.Popen([str(Path(sys.executable).with_name("ray")), "start", "--head", "--block", "--port",
                             str(port), "--num-cpus", "2", "--node-ip-address", "127.0.0.1", "--include-dashboard",
                             "false", "--temp-dir", temp_dir], env=env, stdout=subprocess.DEVNULL,
                            stderr=subprocess.DEVNULL, start_new_session=True)
    try:
        torch.manual_seed(0)
        FlowPolicy(FlowPolicyConfig(lang_dim=0, hidden_dim=32, num_layers=1)).save_pretrained(tmp_path / "init")
        run = tmp_path / "run"
        argv = [sys.executable, "-m", "stepnft.cli", "train", "--run-dir", str(run), "--init", str(tmp_path / "init"),
                "--policy.lang-dim", "0", "--policy.hidden-dim", "32", "--policy.num-layers", "1", "--iterations", "2",
                "--episodes-per-iteration", "4", "--env.tasks", "reach-v3", "--env.envs-per-task", "4",
                "--env.max-episode-steps", "20", "--eval.episodes", "4", "--eval.every", "0",
                "--algo.minibatch-size", "32", "--ray.workers", "2", "--ray.address", f"127.0.0.1:{port}",
                "--ray.timeout-s", "120"]
        deadline = time.time() + 90
        while True:  # the head is up when its GCS port answers
            with socket.socket() as probe:
                if probe.connect_ex(("127.0.0.1", port)) == 0:
                    break
            assert head.poll() is None and time.time() < deadline, "ray start --head did not come up"
            time.sleep(0.5)
        out = subprocess.run(argv, capture_output=True, text=True, timeout=300, env=env)
        assert out.returncode == 0, out.stderr[-2000:]
        assert "Connecting to existing Ray cluster" in out.stderr
        assert json.loads((run / "summary.json").read_text())["iterations"] == 2
        assert head.poll() is None  # the run left the cluster running
    finally:
        head.terminate()
        try:
            head.wait(timeout=60)
        finally:
            with contextlib.suppress(ProcessLookupError):
                os.killpg(head.pid, signal.SIGKILL)
            shutil.rmtree(temp_dir, ignore_errors=True)


def test_a_cluster_that_cannot_be_joined_gets_a_hint(monkeypatch):
    ray = pytest.importorskip("ray", reason='the Ray tests need the ray extra: pip install "stepnft[ray]"')
    from stepnft.rollout.ray_collector import RayCollector

    def refuse(*args, **kwargs):
        raise ConnectionError("Failed to connect to Ray cluster at 10.0.0.1:6379")

    monkeypatch.setattr(ray, "is_initialized", lambda: False)
    monkeypatch.setattr(ray, "init", refuse)
    monkeypatch.delenv("RAY_AUTH_MODE", raising=False)
    with pytest.raises(ConnectionError, match="is the cluster running.*export RAY_AUTH_MODE=token"):
        RayCollector(ENV, 4, SEED, RayConfig(workers=2, address="10.0.0.1:6379"))


SHUTDOWN_SCRIPT = textwrap.dedent("""
    import json, os, time
    from stepnft.config import EnvConfig, RayConfig
    from stepnft.rollout.plan import RolloutSpec
    from stepnft.policies.flow import FlowPolicy, FlowPolicyConfig
    from stepnft.rollout.ray_collector import RayCollector

    def descendants():
        children = {}
        for entry in filter(str.isdigit, os.listdir("/proc")):
            try:
                with open(f"/proc/{entry}/stat") as f:
                    fields = f.read().rsplit(")", 1)[1].split()
            except (FileNotFoundError, ProcessLookupError):
                continue
            if fields[0] != "Z":  # zombies are dead
                children.setdefault(int(fields[1]), []).append(int(entry))
        found, todo = [], [os.getpid()]
        while todo:
            for child in children.get(todo.pop(), []):
                found.append(child)
                todo.append(child)
        return found

    env = EnvConfig(name="bandit", tasks=["bandit"], envs_per_task=4, max_episode_steps=2)
    collector = RayCollector(env, 2, 0, RayConfig(workers=2, timeout_s=120))
    # (pid, start time): the machine's pid range is small (32768 here), so a pid may be reused
    workers = [(pid, open(f"/proc/{pid}/stat").read().rsplit(")", 1)[1].split()[19])
               for pid in collector.worker_pids()]
    policy = FlowPolicy(FlowPolicyConfig(state_dim=2, action_dim=2, horizon=2, n_exec=2, lang_dim=0, hidden_dim=8))
    batch = collector.collect(policy, 4, RolloutSpec(0.3))
    running = descendants()
    collector.close()
    deadline = time.time() + 30
    while descendants() and time.time() < deadline:
        time.sleep(0.2)
    print(json.dumps({"episodes": batch.num_episodes, "workers": workers, "running": running,
                      "left": descendants()}))
""")


def test_close_leaves_no_ray_or_worker_process_behind(ray_instance, tmp_path):
    out = subprocess.run([sys.executable, "-c", SHUTDOWN_SCRIPT], capture_output=True, text=True, timeout=240,
                         cwd=os.getcwd())
    assert out.returncode == 0, out.stderr[-2000:]
    report = json.loads(out.stdout.strip().splitlines()[-1])
    assert report["episodes"] == 4 and {pid for pid, _ in report["workers"]} <= set(report["running"])  # Ray ran under it
    assert report["left"] == []

    def alive(pid: int, started: str) -> bool:
        """The worker itself still runs: its pid holds a live process with the worker's start time."""
        try:
            fields = open(f"/proc/{pid}/stat").read().rsplit(")", 1)[1].split()
        except (FileNotFoundError, ProcessLookupError):
            return False
        return fields[0] != "Z" and fields[19] == started

    deadline = time.time() + 30  # a killed worker that Ray's shutdown reparented may take a moment to exit under load
    while any(alive(*w) for w in report["workers"]) and time.time() < deadline:
        time.sleep(0.2)
    assert not [pid for pid, started in report["workers"] if alive(pid, started)]


class Crash(Exception):
    pass


def test_a_killed_worker_loses_no_iteration_and_a_killed_driver_resumes(ray_instance, tmp_path, monkeypatch):
    """Worker 0 killed as iteration 2 starts: the run goes on. The driver then dies in iteration
    4 (after the checkpoint of 2): ``--resume`` (on one worker now) redoes 3 and 4 as before."""
    from stepnft.algos.stepnft import StepNFT
    from stepnft.cli import main
    from stepnft.rollout.ray_collector import RayCollector
    from stepnft.runs import read_metrics

    policy_args = ["--policy.lang-dim", "0", "--policy.hidden-dim", "32", "--policy.num-layers", "1"]
    torch.manual_seed(0)
    FlowPolicy(FlowPolicyConfig(lang_dim=0, hidden_dim=32, num_layers=1)).save_pretrained(tmp_path / "init")
    run = tmp_path / "run"
    args = ["train", "--run-dir", str(run), "--init", str(tmp_path / "init"), *policy_args, "--iterations", "4",
            "--checkpoint-every", "2", "--episodes-per-iteration", "4", "--env.tasks", "reach-v3",
            "--env.envs-per-task", "4", "--env.max-episode-steps", "20", "--eval.episodes", "4", "--eval.every", "0",
            "--algo.minibatch-size", "32", "--ray.workers", "2", "--ray.timeout-s", "120"]
    play, update, plays, updates = RayCollector.play, StepNFT.update, [], []

    def kill_before_the_second_training_plan(self, policy, plan, noise_level, record=None, progress=None):
        plays.append(record)
        if record is not None and sum(r is not None for r in plays) == 2:
            os.kill(self.worker_pids()[0], signal.SIGKILL)
        return play(self, policy, plan, noise_level, record, progress)

    def crash_on_fourth_update(*a, **kw):
        updates.append(1)
        if len(updates) == 4:
            raise Crash
        return update(*a, **kw)

    monkeypatch.setattr(RayCollector, "play", kill_before_the_second_training_plan)
    monkeypatch.setattr(StepNFT, "update", crash_on_fourth_update)
    with pytest.raises(Crash):
        main(args)
    first = read_metrics(run / "metrics.jsonl")
    assert [r["iteration"] for r in first] == [0, 1, 2, 3]
    assert first[2]["charts/worker_restarts"] == 1 and "charts/worker_restarts" not in first[3]
    monkeypatch.setattr(StepNFT, "update", update)

    assert main(["train", "--resume", str(run), "--ray.workers", "1"]) == 0
    records = read_metrics(run / "metrics.jsonl")
    assert [r["iteration"] for r in records] == [0, 1, 2, 3, 4, 4] and records[-1]["final"]
    assert records[3]["env_steps"] == first[3]["env_steps"]
    assert records[3]["losses/E_pos"] == pytest.approx(first[3]["losses/E_pos"], rel=1e-3)
    assert json.loads((run / "summary.json").read_text())["iterations"] == 4
