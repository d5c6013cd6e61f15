"""The collector: what a wave's batch holds (episodes, calls, recorded denoising steps)."""

import numpy as np
import pytest
import torch

from stepnft.algos.base import RolloutSpec
from stepnft.batch import Batch
from stepnft.envs.metaworld import make_metaworld_vec_env
from stepnft.policies.flow import FlowPolicy, FlowPolicyConfig
from stepnft.rollout.collector import Collector

GOAL_X, GOAL, HAND = 36, slice(36, 39), slice(0, 3)
MAX_STEPS = 58  # not a multiple of n_exec: the last chunk of a truncated episode is cut short


class SeekIfGoalBeyond(FlowPolicy):
    """A random flow policy whose executed actions steer to the reach goal when the goal's x is
    beyond ``threshold`` and stay still otherwise: one known env succeeds, the other fails.
    (Its processor is the identity on the state: mean 0, std 1, a wide clip.)"""

    threshold = 0.0

    def sample(self, obs, noise_level=0.0, generator=None, stochastic_steps="all", keep_path=False):
        out = super().sample(obs, noise_level, generator, stochastic_steps, keep_path)
        state = obs["state"]
        seek = (state[:, GOAL_X] > self.threshold)[:, None, None]
        out.actions = torch.zeros_like(out.actions)
        out.actions[..., :3] = torch.where(seek, 10.0 * (state[:, None, GOAL] - state[:, None, HAND]), 0.0)
        return out


@pytest.fixture(scope="module")
def wave_and_steps():
    venv = make_metaworld_vec_env(["reach-v3"], 2, n_exec=4, max_episode_steps=MAX_STEPS)
    seeds = [0, 1]
    goals_x = venv.reset(seed=seeds)[0]["state"][:, GOAL_X]
    assert goals_x[0] != goals_x[1]
    torch.manual_seed(0)
    policy = SeekIfGoalBeyond(FlowPolicyConfig(lang_dim=0, hidden_dim=16, num_layers=1, horizon=6, n_exec=4,
                                               state_clip=100.0))
    policy.threshold = float(goals_x.mean())
    seeker = int(np.argmax(goals_x))

    infos = []
    step = venv.step
    venv.step = lambda actions: (out := step(actions), infos.append(out[4]))[0]
    collector = Collector(venv, seed=0)
    batch = collector.play_wave(policy, 0.2, collector.env_generators, seeds=seeds, record=RolloutSpec(0.2))
    venv.close()
    return batch, infos, seeker


def test_one_env_succeeds_early_the_other_runs_to_the_cap(wave_and_steps):
    batch, infos, seeker = wave_and_steps
    assert batch.episode_success.tolist() == [i == seeker for i in range(2)]
    length = batch.episode_length
    assert length[seeker] < MAX_STEPS and length[1 - seeker] == MAX_STEPS
    np.testing.assert_array_equal(length.numpy(), infos[-1]["episode_steps"])
    assert batch.episode_seed.tolist() == [0, 1] and batch.episode_task.tolist() == [0, 0]
    assert batch.env_steps == int(length.sum())


def test_calls_hold_observation_mask_reward_and_done(wave_and_steps):
    batch, infos, seeker = wave_and_steps
    horizon = batch.mask.shape[1]
    steps = np.stack([info["steps"] for info in infos])  # [calls, N], 0 once an episode ended
    for env in range(2):
        mine = batch.episode == env
        executed = [s for s in steps[:, env] if s > 0]
        expected = torch.stack([torch.arange(horizon) < s for s in executed])
        assert torch.equal(batch.mask[mine], expected)
        assert int(batch.mask[mine].sum()) == batch.episode_length[env]
        assert batch.done[mine].tolist() == [False] * (len(executed) - 1) + [True]  # only the last call ends it
    assert not batch.mask[:, 4:].any()  # n_exec = 4 of horizon 6
    last_chunk = [s for s in steps[:, 1 - seeker] if s > 0][-1]
    assert last_chunk == MAX_STEPS % 4 == 2  # the truncated episode's last chunk ran 2 steps
    assert batch.obs["state"].shape == (batch.num_calls, 39) and batch.obs["task"].tolist() == [0] * batch.num_calls
    assert batch.reward.dtype == torch.float32 and (batch.reward[batch.episode == seeker] > 0).any()


def test_one_recorded_denoising_step_per_call_and_no_labels(wave_and_steps):
    batch, _, _ = wave_and_steps
    m = batch.num_calls
    assert m == int(np.ceil(batch.episode_length.numpy() / 4).sum())
    assert batch.num_steps == m and batch.call.tolist() == list(range(m))
    for key in ("x_t", "x_next", "v_old"):
        assert getattr(batch, key).shape == (m, 6, 4), key
    assert set(batch.t.tolist()) <= {1.0, 0.75, 0.5, 0.25} and len(set(batch.t.tolist())) > 1
    assert torch.allclose(batch.dt, torch.full((m,), 0.25))
    assert not torch.equal(batch.x_t, batch.x_next)
    assert not hasattr(batch, "y")  # labels are the algorithm's business
    assert torch.equal(batch.step_success, batch.episode_success[batch.episode])

    twice = Batch.concat([batch, batch])
    assert twice.num_episodes == 4 and twice.num_steps == 2 * m
    assert torch.equal(twice.step_episode[m:], batch.step_episode + 2)
    assert torch.equal(twice.steps_obs(torch.arange(m, 2 * m))["state"], batch.obs["state"])


def test_record_all_steps_stores_k_transitions_per_call_and_each_observation_once():
    venv = make_metaworld_vec_env(["reach-v3"], 2, n_exec=4, max_episode_steps=12)
    torch.manual_seed(0)
    policy = FlowPolicy(FlowPolicyConfig(lang_dim=0, hidden_dim=16, num_layers=1, horizon=4, n_exec=4))
    collector = Collector(venv, seed=0)
    one = collector.play_wave(policy, 0.3, collector.env_generators, seeds=[0, 1], record=RolloutSpec(0.3))
    every = collector.play_wave(policy, 0.3, collector.env_generators, seeds=[0, 1],
                                record=RolloutSpec(0.3, record_steps="all"))
    k = policy.config.num_inference_steps
    assert every.num_calls == one.num_calls == 6 and every.num_steps == k * one.num_steps == k * 6
    assert every.obs["state"].shape == (6, 39)  # stored once per call, not once per step
    # Each call's K transitions chain x_next -> x_t and end at the sampled chunk.
    for call in range(6):
        rows = slice(k * call, k * (call + 1))
        assert every.call[rows].tolist() == [call] * k
        torch.testing.assert_close(every.x_next[rows][:-1], every.x_t[rows][1:])
        torch.testing.assert_close(every.x_next[rows][-1], every.actions[call])
        assert every.t[rows].tolist() == [1.0, 0.75, 0.5, 0.25]
    venv.close()


def test_a_sub_env_draws_the_same_episode_whatever_else_plays():
    """Each sub-env samples from its own generator: splitting the sub-envs (over waves or
    workers) does not change any episode (the seam a remote collector relies on)."""
    venv = make_metaworld_vec_env(["reach-v3", "push-v3"], 2, n_exec=4, max_episode_steps=8)
    torch.manual_seed(0)
    policy = FlowPolicy(FlowPolicyConfig(lang_dim=0, hidden_dim=16, num_layers=1))
    spec, seeds = RolloutSpec(0.3), [5, 6, 7, 8]
    whole = Collector(venv, seed=3).play_wave(policy, 0.3, Collector(venv, seed=3).env_generators, seeds=seeds,
                                             record=spec)
    split = Collector(venv, seed=3)
    parts = [split.play_wave(policy, 0.3, split.env_generators, seeds=seeds, record=spec, active=np.arange(4) % 2 == r)
             for r in (0, 1)]
    for r, part in enumerate(parts):
        mine = torch.isin(whole.episode, torch.arange(r, 4, 2))
        torch.testing.assert_close(part.actions, whole.actions[mine])
        assert part.episode_success.tolist() == whole.episode_success[r::2].tolist()
    venv.close()


def test_collect_plays_whole_waves_and_resumes_its_streams_exactly():
    venv = make_metaworld_vec_env(["reach-v3", "push-v3"], 2, n_exec=4, max_episode_steps=8)
    torch.manual_seed(0)
    policy = FlowPolicy(FlowPolicyConfig(lang_dim=0, hidden_dim=16, num_layers=1))
    collector = Collector(venv, seed=0)
    spec = RolloutSpec(0.3)
    state = collector.state_dict()
    first = collector.collect(policy, 5, spec)  # 5 episodes on 4 envs: two waves
    assert first.num_episodes == 8 and first.episode_task.tolist() == [0, 0, 1, 1] * 2
    assert (first.episode_seed == -1).all()
    collector.load_state_dict(state)
    again = collector.collect(policy, 5, spec)
    assert torch.equal(first.x_next, again.x_next) and torch.equal(first.obs["state"], again.obs["state"])
    venv.close()


@pytest.mark.parametrize("num_workers", [0, 2])
def test_episodes_per_task_leave_the_other_sub_envs_idle(num_workers):
    venv = make_metaworld_vec_env(["reach-v3", "push-v3"], 2, n_exec=4, max_episode_steps=8, num_workers=num_workers)
    torch.manual_seed(0)
    policy = FlowPolicy(FlowPolicyConfig(lang_dim=0, hidden_dim=16, num_layers=1))
    collector = Collector(venv, seed=0)
    rng_before = venv.rng_state()
    batch = collector.collect(policy, 0, RolloutSpec(0.3), task_episodes=[3, 0])
    assert batch.episode_task.tolist() == [0, 0, 0] and batch.env_steps == 3 * 8
    assert (batch.obs["task"] == 0).all() and batch.num_calls == 3 * 2
    # The push sub-envs never simulated: their RNG streams did not move.
    assert venv.rng_state()[2:] == rng_before[2:] and venv.rng_state()[:2] != rng_before[:2]
    venv.close()


def test_groups_start_from_one_initial_state():
    venv = make_metaworld_vec_env(["reach-v3", "push-v3"], 4, n_exec=4, max_episode_steps=4)
    torch.manual_seed(0)
    policy = FlowPolicy(FlowPolicyConfig(lang_dim=0, hidden_dim=16, num_layers=1))
    collector = Collector(venv, seed=0)
    batch = collector.collect(policy, 8, RolloutSpec(0.3, group_size=2))
    seeds = batch.episode_seed.tolist()
    assert seeds[0] == seeds[1] != seeds[2] == seeds[3] and min(seeds) >= 2**24
    first_obs = batch.obs["state"][batch.done.new_zeros(batch.num_calls, dtype=torch.bool).index_fill(
        0, torch.tensor([0, 1]), True)]
    torch.testing.assert_close(first_obs[0], first_obs[1])  # the first call of each sub-env of the group
    with pytest.raises(ValueError, match="groups of 3"):
        collector.collect(policy, 8, RolloutSpec(0.3, group_size=3))
    venv.close()
