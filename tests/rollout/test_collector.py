"""Rollout waves: what each stored transition holds (masks, labels, recorded denoising step)."""

import numpy as np
import pytest
import torch

from stepnft.envs.metaworld import make_metaworld_vec_env
from stepnft.policies.flow import FlowPolicy, FlowPolicyConfig
from stepnft.rollout.collector import concat_transitions, run_wave

GOAL_X, GOAL, HAND = 36, slice(36, 39), slice(0, 3)
MAX_STEPS = 58  # not a multiple of n_exec: the last chunk of a truncated episode is cut short


class SeekIfGoalBeyond(FlowPolicy):
    """A random flow policy whose executed actions steer to the reach goal when the goal's x is
    beyond ``threshold`` and stay still otherwise: one known env succeeds, the other fails."""

    threshold = 0.0

    def sample(self, state, lang=None, noise_level=0.0, generator=None, stochastic_steps="all"):
        out = super().sample(state, lang, noise_level, generator, stochastic_steps)
        seek = (state[:, GOAL_X] > self.threshold)[:, None, None]
        out.actions = torch.zeros_like(out.actions)
        out.actions[..., :3] = torch.where(seek, 10.0 * (state[:, None, GOAL] - state[:, None, HAND]), 0.0)
        return out


@pytest.fixture(scope="module")
def wave_and_steps():
    venv = make_metaworld_vec_env(["reach-v3"], 2, n_exec=4, max_episode_steps=MAX_STEPS, autoreset=False)
    seeds = [0, 1]
    goals_x = venv.reset(seed=seeds)[0][:, GOAL_X]
    assert goals_x[0] != goals_x[1]
    torch.manual_seed(0)
    policy = SeekIfGoalBeyond(FlowPolicyConfig(lang_dim=0, hidden_dim=16, num_layers=1, horizon=6, n_exec=4))
    policy.threshold = float(goals_x.mean())
    seeker = int(np.argmax(goals_x))

    infos = []
    step = venv.step
    venv.step = lambda actions: (out := step(actions), infos.append(out[4]))[0]
    wave = run_wave(policy, venv, None, noise_level=0.2, generator=torch.Generator().manual_seed(0),
                    seeds=seeds, record=True)
    venv.close()
    return wave, infos, seeker


def test_one_env_succeeds_early_the_other_runs_to_the_cap(wave_and_steps):
    wave, infos, seeker = wave_and_steps
    assert wave.success.tolist() == [i == seeker for i in range(2)]
    assert wave.length[seeker] < MAX_STEPS and wave.length[1 - seeker] == MAX_STEPS
    np.testing.assert_array_equal(wave.length, infos[-1]["episode_steps"])


def test_mask_marks_exactly_the_executed_positions(wave_and_steps):
    wave, infos, seeker = wave_and_steps
    tr = wave.transitions
    horizon = tr["mask"].shape[1]
    steps = np.stack([info["steps"] for info in infos])  # [calls, N], 0 once an episode ended
    for env in range(2):
        executed = [s for s in steps[:, env] if s > 0]
        expected = torch.stack([torch.arange(horizon) < s for s in executed])
        assert torch.equal(tr["mask"][tr["env_index"] == env], expected)
        assert int(tr["mask"][tr["env_index"] == env].sum()) == wave.length[env]
    assert not tr["mask"][:, 4:].any()  # n_exec = 4 of horizon 6
    last_chunk = [s for s in steps[:, 1 - seeker] if s > 0][-1]
    assert last_chunk == MAX_STEPS % 4 == 2  # the truncated episode's last chunk ran 2 steps


def test_labels_are_the_episode_outcome(wave_and_steps):
    wave, _, seeker = wave_and_steps
    tr = wave.transitions
    assert torch.equal(tr["y"], torch.where(tr["env_index"] == seeker, 1.0, -1.0))


def test_recorded_denoising_step(wave_and_steps):
    wave, _, _ = wave_and_steps
    tr = wave.transitions
    m = tr["y"].shape[0]
    assert m == int(np.ceil(wave.length / 4).sum())  # one per policy call of each episode
    for key in ("x_t", "x_next", "v_old", "actions"):
        assert tr[key].shape == (m, 6, 4), key
    assert tr["state"].shape == (m, 39) and tr["task_id"].tolist() == [0] * m
    assert set(tr["t"].tolist()) <= {1.0, 0.75, 0.5, 0.25} and len(set(tr["t"].tolist())) > 1
    assert torch.allclose(tr["dt"], torch.full((m,), 0.25))
    assert not torch.equal(tr["x_t"], tr["x_next"])

    batch = concat_transitions([wave, wave])
    assert batch["y"].shape == (2 * m,) and torch.equal(batch["mask"][m:], tr["mask"])


def test_record_all_steps_stores_k_transitions_per_call():
    venv = make_metaworld_vec_env(["reach-v3"], 2, n_exec=4, max_episode_steps=12, autoreset=False)
    torch.manual_seed(0)
    policy = FlowPolicy(FlowPolicyConfig(lang_dim=0, hidden_dim=16, num_layers=1, horizon=4, n_exec=4))
    gen = torch.Generator().manual_seed(0)
    one = run_wave(policy, venv, None, 0.3, gen, seeds=[0, 1], record=True)
    every = run_wave(policy, venv, None, 0.3, gen, seeds=[0, 1], record=True, record_steps="all")
    k = policy.config.num_inference_steps
    assert len(every.transitions["y"]) == k * len(one.transitions["y"]) == k * 6
    # Each call's K transitions share its observation, mask and label and chain x_next -> x_t.
    tr = every.transitions
    for call in range(6):
        rows = slice(k * call, k * (call + 1))
        assert (tr["state"][rows] == tr["state"][k * call]).all()
        assert (tr["mask"][rows] == tr["mask"][k * call]).all()
        torch.testing.assert_close(tr["x_next"][rows][:-1], tr["x_t"][rows][1:])
        torch.testing.assert_close(tr["x_next"][rows][-1], tr["actions"][k * call])
        assert tr["t"][rows].tolist() == [1.0, 0.75, 0.5, 0.25]
    venv.close()
