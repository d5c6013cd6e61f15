"""The SFT stage in its steps: demonstrations (data), chunks and the fitted processor (fit),
flow-matching training (train); :func:`sft_stage` is exactly their composition."""

import numpy as np
import torch

from stepnft.algos.sft import SFTConfig, fit_processor, sft_chunks, sft_stage, sft_train
from stepnft.config import DemoConfig, EnvConfig
from stepnft.data.demos import load_or_generate_demos
from stepnft.envs import get_simulator
from stepnft.envs.bandit import ACTION_DIM, CONTEXT_DIM, HORIZON
from stepnft.envs.episodes import DemoEpisode
from stepnft.policies.base import make_policy
from stepnft.policies.flow import FlowPolicyConfig

POLICY = FlowPolicyConfig(state_dim=CONTEXT_DIM, lang_dim=0, action_dim=ACTION_DIM, horizon=HORIZON, n_exec=HORIZON,
                          hidden_dim=32)
ENV = EnvConfig(name="bandit", tasks=["bandit"], max_episode_steps=HORIZON)
SFT = SFTConfig(steps=20, batch_size=16, lr=1e-3)


def test_the_stage_is_its_steps_composed(tmp_path):
    demos = DemoConfig(path=str(tmp_path / "demos"), episodes=40, successful_only=False)
    torch.manual_seed(0)
    staged = sft_stage(ENV, demos, POLICY, SFT, seed=3, log=lambda line: None)

    sim = get_simulator("bandit")
    episodes = load_or_generate_demos(demos, ENV, sim, log=lambda line: None)
    torch.manual_seed(0)
    policy = make_policy(POLICY)
    data = sft_chunks(episodes, ENV, sim, POLICY.horizon, only_successful=False)
    fit_processor(policy, data, [sim.instruction("bandit")])
    losses = sft_train(policy, data, SFT, torch.Generator().manual_seed(3))
    assert len(losses) == SFT.steps
    for key, value in policy.state_dict().items():
        assert torch.equal(value, staged.state_dict()[key]), key
    assert torch.equal(policy.processor.state_mean, staged.processor.state_mean)


def test_fit_processor_keeps_a_saved_policys_statistics_when_asked():
    policy = make_policy(POLICY)
    data = {"obs": {"state": torch.tensor([[1.0, 2.0], [3.0, 6.0]])}}
    fit_processor(policy, data, ["instruction"])
    assert policy.processor.state_mean.tolist() == [2.0, 4.0] and policy.processor.instructions == ["instruction"]
    fit_processor(policy, {"obs": {"state": torch.zeros(2, 2)}}, ["other"], keep_statistics=True)
    assert policy.processor.state_mean.tolist() == [2.0, 4.0] and policy.processor.instructions == ["other"]


def test_chunks_show_the_policy_the_state_its_env_shows():
    length = 5
    episode = DemoEpisode(task="reach-v3", instruction="reach", seed=0, success=True,
                          observations=np.arange((length + 1) * 39, dtype=np.float32).reshape(length + 1, 39),
                          actions=np.zeros((length, 4), np.float32), rewards=np.zeros(length, np.float32),
                          successes=np.arange(length) == length - 1)
    sim = get_simulator("metaworld")
    proprio = sft_chunks([episode], EnvConfig(tasks=["reach-v3"], state_obs="proprio"), sim, horizon=3)
    full = sft_chunks([episode], EnvConfig(tasks=["reach-v3"]), sim, horizon=3)
    assert full["obs"]["state"].shape == (length, 39) and proprio["obs"]["state"].shape == (length, 4)
    assert torch.equal(proprio["obs"]["state"], full["obs"]["state"][:, :4])
    assert proprio["actions"].shape == (length, 3, 4) and "image" not in proprio["obs"]
