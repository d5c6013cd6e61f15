"""The collector: continuous collection of a plan's episodes (what the batch holds, in which
order), the same batch whatever the worker count or the timing, lanes that overlap."""

import random
import time

import numpy as np
import pytest
import torch

from stepnft.batch import Batch
from stepnft.envs.metaworld import make_metaworld_vec_env
from stepnft.envs.metaworld.env import MetaWorldChunkEnv
from stepnft.policies.flow import FlowPolicy, FlowPolicyConfig
from stepnft.rollout.collector import Collector, plan_lanes
from stepnft.rollout.plan import TRAINING_SEEDS, EpisodePlan, RolloutSpec

GOAL_X, GOAL, HAND = 36, slice(36, 39), slice(0, 3)
MAX_STEPS = 58  # not a multiple of n_exec: the last chunk of a truncated episode is cut short


class SeekIfGoalBeyond(FlowPolicy):
    """A random flow policy whose executed actions steer to the reach goal when the goal's x is
    beyond ``threshold`` and stay still otherwise: one known episode succeeds, the other fails.
    (Its processor is the identity on the state: mean 0, std 1, a wide clip.)"""

    threshold = 0.0

    def sample(self, obs, noise_level=0.0, generator=None, stochastic_steps="all", keep_path=False, **kwargs):
        out = super().sample(obs, noise_level, generator, stochastic_steps, keep_path, **kwargs)
        state = obs["state"]
        seek = (state[:, GOAL_X] > self.threshold)[:, None, None]
        out.actions = torch.zeros_like(out.actions)
        out.actions[..., :3] = torch.where(seek, 10.0 * (state[:, None, GOAL] - state[:, None, HAND]), 0.0)
        return out


class GoalSeeker(FlowPolicy):
    """A random flow policy pulled toward the reach goal: outcomes depend on state and noise."""

    def sample(self, obs, noise_level=0.0, generator=None, stochastic_steps="all", keep_path=False, **kwargs):
        out = super().sample(obs, noise_level, generator, stochastic_steps, keep_path, **kwargs)
        out.actions[..., :3] += 10.0 * (obs["state"][:, None, GOAL] - obs["state"][:, None, HAND])
        return out


def small_policy(cls=FlowPolicy, **kwargs) -> FlowPolicy:
    torch.manual_seed(0)
    return cls(FlowPolicyConfig(lang_dim=0, hidden_dim=16, num_layers=1, **kwargs))


def assert_same_batch(a: Batch, b: Batch) -> None:
    for key in ("episode_success", "episode_task", "episode_length", "episode_seed", "actions", "mask", "reward",
                "done", "episode", "call", "x_t", "x_next", "v_old", "t", "dt"):
        assert torch.equal(getattr(a, key), getattr(b, key)), key
    assert torch.equal(a.obs["state"], b.obs["state"])


@pytest.fixture(scope="module")
def seek_batch():
    """Two reach episodes on one sub-env each: one succeeds early, the other runs to the cap."""
    venv = make_metaworld_vec_env(["reach-v3"], 2, n_exec=4, max_episode_steps=MAX_STEPS)
    goals_x = venv.reset(seed=[0, 1])[0]["state"][:, GOAL_X]
    assert goals_x[0] != goals_x[1]
    policy = small_policy(SeekIfGoalBeyond, horizon=6, n_exec=4, state_clip=100.0)
    policy.threshold = float(goals_x.mean())
    plan = EpisodePlan(task=[0, 0], seed=[0, 1], noise_seed=[5, 6])
    batch = Collector(venv).play(policy, plan, 0.2, record=RolloutSpec(0.2))
    venv.close()
    return batch, int(np.argmax(goals_x))


def test_one_episode_succeeds_early_the_other_runs_to_the_cap(seek_batch):
    batch, seeker = seek_batch
    assert batch.episode_success.tolist() == [i == seeker for i in range(2)]
    length = batch.episode_length
    assert length[seeker] < MAX_STEPS and length[1 - seeker] == MAX_STEPS
    assert batch.episode_seed.tolist() == [0, 1] and batch.episode_task.tolist() == [0, 0]
    assert batch.env_steps == int(length.sum())


def test_calls_hold_observation_mask_reward_and_done_grouped_by_episode(seek_batch):
    batch, seeker = seek_batch
    assert batch.episode.tolist() == sorted(batch.episode.tolist())  # each episode's calls together
    for episode in range(2):
        mine = batch.episode == episode
        executed = batch.mask[mine].sum(dim=1)
        assert int(executed.sum()) == batch.episode_length[episode]
        assert (executed[:-1] == 4).all()  # full chunks until the last call
        assert batch.done[mine].tolist() == [False] * (int(mine.sum()) - 1) + [True]
    assert int(batch.mask[batch.episode == 1 - seeker][-1].sum()) == MAX_STEPS % 4 == 2
    assert not batch.mask[:, 4:].any()  # n_exec = 4 of horizon 6
    assert batch.obs["state"].shape == (batch.num_calls, 39) and batch.obs["task"].tolist() == [0] * batch.num_calls
    assert batch.reward.dtype == torch.float32 and (batch.reward[batch.episode == seeker] > 0).any()


def test_one_recorded_denoising_step_per_call_and_no_labels(seek_batch):
    batch, _ = seek_batch
    m = batch.num_calls
    assert m == int(np.ceil(batch.episode_length.numpy() / 4).sum())
    assert batch.num_steps == m and batch.call.tolist() == list(range(m))
    assert set(batch.t.tolist()) <= {1.0, 0.75, 0.5, 0.25} and len(set(batch.t.tolist())) > 1
    assert torch.allclose(batch.dt, torch.full((m,), 0.25))
    assert not hasattr(batch, "y")  # labels are the algorithm's business
    assert torch.equal(batch.step_success, batch.episode_success[batch.episode])


def test_record_all_steps_stores_k_transitions_per_call_and_each_observation_once():
    venv = make_metaworld_vec_env(["reach-v3"], 2, n_exec=4, max_episode_steps=12)
    policy = small_policy(horizon=4, n_exec=4)
    plan = EpisodePlan(task=[0, 0], seed=[0, 1], noise_seed=[0, 1])
    collector = Collector(venv)
    one = collector.play(policy, plan, 0.3, record=RolloutSpec(0.3))
    every = collector.play(policy, plan, 0.3, record=RolloutSpec(0.3, record_steps="all"))
    k = policy.config.num_inference_steps
    assert every.num_calls == one.num_calls == 6 and every.num_steps == k * one.num_steps == k * 6
    assert every.obs["state"].shape == (6, 39)  # stored once per call, not once per step
    for call in range(6):  # each call's K transitions chain x_next -> x_t and end at the chunk
        rows = slice(k * call, k * (call + 1))
        assert every.call[rows].tolist() == [call] * k
        torch.testing.assert_close(every.x_next[rows][:-1], every.x_t[rows][1:])
        torch.testing.assert_close(every.x_next[rows][-1], every.actions[call])
        assert every.t[rows].tolist() == [1.0, 0.75, 0.5, 0.25]
    venv.close()


def test_the_spec_says_whether_rollout_steps_are_mean_corrected():
    """Without the mean correction each recorded step is N(x_t - dt v_old, std^2): the collector
    passes the spec's choice to the sampler (the exploration ablation's rollouts)."""
    from stepnft.sampling import sde_step_mean_std
    venv = make_metaworld_vec_env(["reach-v3"], 2, n_exec=4, max_episode_steps=40)
    policy = small_policy(horizon=4, n_exec=4)
    plan = EpisodePlan(task=[0, 0], seed=[0, 1], noise_seed=[0, 1])
    collector = Collector(venv)
    noise = {}
    for corrected in (True, False):
        batch = collector.play(policy, plan, 0.5, record=RolloutSpec(0.5, record_steps="all", mean_correction=corrected))
        mean, std = sde_step_mean_std(batch.x_t, batch.v_old, batch.t, batch.dt, 0.5, mean_correction=corrected)
        noise[corrected] = (batch.x_next - mean) / std  # the draws, recovered under the spec's own step
    venv.close()
    # The first step of the first call starts from the same x_1 and draws the same noise either
    # way: only the mean differs (were the spec ignored, the plain run's recovered draw would be off
    # by the correction term).
    torch.testing.assert_close(noise[True][0], noise[False][0])
    assert noise[False].pow(2).mean().item() == pytest.approx(1.0, abs=0.15)


def test_a_sub_env_starts_its_next_episode_as_soon_as_one_ends():
    """Six episodes of one task on two sub-envs: nobody waits for a wave; the batch lists them
    in plan order, and each episode is the one its plan entry makes (played alone, the same)."""
    venv = make_metaworld_vec_env(["reach-v3"], 2, n_exec=4, max_episode_steps=40)
    policy = small_policy(GoalSeeker, state_clip=100.0)
    plan = EpisodePlan(task=[0] * 6, seed=[10, 11, 12, 13, 14, 15], noise_seed=[0, 1, 2, 3, 4, 5])
    sent = []
    send = venv.send_ops
    venv.send_ops = lambda ops: (sent.append(ops), send(ops))[1]
    batch = Collector(venv).play(policy, plan, 0.3, record=RolloutSpec(0.3))
    assert batch.episode_seed.tolist() == [10, 11, 12, 13, 14, 15]
    assert batch.episode_success.any() and not batch.episode_success.all()  # unequal lengths
    resets = [(i, arg) for ops in sent for i, op, arg in ops if op == "reset"]
    assert sorted(arg for _, arg in resets) == list(range(10, 16))
    assert {i for i, _ in resets} == {0, 1}  # each sub-env played 3 (one per lane, in plan order)
    assert [arg for i, arg in resets if i == 0] == [10, 12, 14]
    # A sub-env whose episode ended was reset in the next message of its lane, not at a wave's end.
    for ops in sent:
        assert len({i for i, _, _ in ops}) == len(ops)
    alone = Collector(venv).play(policy, plan.take(np.array([3])), 0.3, record=RolloutSpec(0.3))
    assert alone.episode_success.tolist() == batch.episode_success[3:4].tolist()
    assert alone.episode_length.tolist() == batch.episode_length[3:4].tolist()
    venv.close()


@pytest.mark.parametrize("num_workers", [1, 2])
def test_the_same_batch_bit_for_bit_with_any_worker_count(num_workers):
    spec = RolloutSpec(0.4, record_steps="all", group_size=2)
    batches = []
    for workers in (0, num_workers):
        venv = make_metaworld_vec_env(["reach-v3", "push-v3"], 3, n_exec=4, max_episode_steps=24,
                                      num_workers=workers)
        collector = Collector(venv, seed=4)
        batches.append(collector.collect(small_policy(GoalSeeker, state_clip=100.0), 0, spec, task_episodes=[6, 4]))
        venv.close()
    assert_same_batch(*batches)


def test_the_same_batch_whatever_the_timing(monkeypatch):
    """Workers that answer after random delays (different in every run) change nothing."""
    step = MetaWorldChunkEnv.step

    def slow_step(self, chunk):
        time.sleep(random.SystemRandom().random() * 0.003)
        return step(self, chunk)

    monkeypatch.setattr(MetaWorldChunkEnv, "step", slow_step)  # the forked workers inherit it
    batches = []
    for _ in range(2):
        venv = make_metaworld_vec_env(["reach-v3", "push-v3"], 4, n_exec=4, max_episode_steps=20, num_workers=2)
        batches.append(Collector(venv, seed=1).collect(small_policy(GoalSeeker, state_clip=100.0), 12,
                                                       RolloutSpec(0.3)))
        venv.close()
    assert_same_batch(*batches)


def test_lanes_overlap_one_lane_is_sent_before_the_other_is_received():
    """One worker holds both lanes and this process samples: it computes one lane's actions
    while the worker steps the other."""
    venv = make_metaworld_vec_env(["reach-v3"], 4, n_exec=4, max_episode_steps=12, num_workers=1)
    events = []
    send, receive = venv.send_ops, venv.receive_ops
    venv.send_ops = lambda ops: (events.append("send"), send(ops))[1]
    venv.receive_ops = lambda: (events.append("receive"), receive())[1]
    Collector(venv).play(small_policy(), EpisodePlan([0] * 4, [0, 1, 2, 3], [0, 1, 2, 3]), 0.3)
    venv.close()
    # Both lanes' resets go out before anything comes back; after that every receive of one
    # lane is followed by its next send while the other lane's request is still in flight.
    assert events[:3] == ["send", "send", "receive"]
    in_flight = 0
    for event in events:
        in_flight += 1 if event == "send" else -1
        assert 0 <= in_flight <= 2
    assert events.count("send") == events.count("receive")


def test_with_a_lane_per_worker_each_worker_plays_its_lane_with_a_copy_of_the_policy():
    venv = make_metaworld_vec_env(["reach-v3", "push-v3"], 2, n_exec=4, max_episode_steps=12, num_workers=2)
    assert venv.num_workers == 2 and venv.shards == [[0, 3], [1, 2]]  # worker w holds lane w
    assert venv.lanes.tolist() == [0, 1, 1, 0]  # each lane holds a sub-env of each task
    sent = []
    send = venv.send_ops
    venv.send_ops = lambda ops: (sent.append(ops), send(ops))[1]
    batch = Collector(venv, seed=2).collect(small_policy(GoalSeeker, state_clip=100.0), 8, RolloutSpec(0.3))
    venv.close()
    assert not sent  # no traffic per step: the workers sampled
    assert batch.num_episodes == 8 and batch.episode_task.tolist() == [0] * 4 + [1] * 4


def test_plan_lanes_follow_the_sub_envs_of_each_task():
    task_ids = np.array([0, 0, 0, 1])  # task 0: lanes 0, 1, 0; task 1: lane 0 only
    lanes = np.array([0, 1, 0, 0])
    plan = EpisodePlan(task=[0, 0, 0, 0, 1, 1], seed=range(6), noise_seed=range(6))
    assert plan_lanes(plan, task_ids, lanes).tolist() == [0, 1, 0, 0, 0, 0]
    with pytest.raises(ValueError, match="no sub-env"):
        plan_lanes(EpisodePlan([2], [0], [0]), task_ids, lanes)


def test_collect_draws_plans_per_task_and_resumes_its_stream_exactly():
    venv = make_metaworld_vec_env(["reach-v3", "push-v3"], 2, n_exec=4, max_episode_steps=8)
    policy = small_policy()
    collector = Collector(venv, seed=0)
    spec = RolloutSpec(0.3)
    state = collector.state_dict()
    first = collector.collect(policy, 5, spec)  # 5 episodes over 2 tasks: 3 each
    assert first.episode_task.tolist() == [0, 0, 0, 1, 1, 1]
    assert ((first.episode_seed >= TRAINING_SEEDS[0]) & (first.episode_seed < TRAINING_SEEDS[1])).all()
    assert len(set(first.episode_seed.tolist())) == 6
    collector.load_state_dict(state)
    assert_same_batch(first, collector.collect(policy, 5, spec))
    only = collector.collect(policy, 0, spec, task_episodes=[3, 0])
    assert only.episode_task.tolist() == [0, 0, 0] and (only.obs["task"] == 0).all()
    with pytest.raises(ValueError, match="one count per task"):
        collector.collect(policy, 0, spec, task_episodes=[3])
    venv.close()


def test_groups_start_from_one_initial_state():
    venv = make_metaworld_vec_env(["reach-v3", "push-v3"], 3, n_exec=4, max_episode_steps=4)
    collector = Collector(venv, seed=0)
    batch = collector.collect(small_policy(), 8, RolloutSpec(0.3, group_size=2))
    seeds = batch.episode_seed.tolist()
    assert len(seeds) == 8 and seeds[0] == seeds[1] != seeds[2] == seeds[3]
    first_call = [int((batch.episode == e).nonzero()[0]) for e in range(4)]
    torch.testing.assert_close(batch.obs["state"][first_call[0]], batch.obs["state"][first_call[1]])
    assert not torch.equal(batch.actions[first_call[0]], batch.actions[first_call[1]])  # own noise
    with pytest.raises(ValueError, match="multiples of the group size"):
        collector.collect(small_policy(), 0, RolloutSpec(0.3, group_size=3), task_episodes=[4, 3])
    venv.close()
