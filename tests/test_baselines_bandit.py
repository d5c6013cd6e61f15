"""The baselines learn through the same loop as π-StepNFT, on the toy bandit, from one SFT
policy: PPO and GRPO with every denoising step stochastic and with one stochastic step per call."""

import dataclasses

import pytest

from stepnft.algos.grpo import GRPOConfig
from stepnft.algos.ppo import PPOConfig
from stepnft.algos.variants import variant_config
from stepnft.config import EvalConfig
from stepnft.demo_bandit import bandit_config, run_bandit_demo
from stepnft.train import run_sft


@pytest.fixture(scope="module")
def sft_policy(tmp_path_factory):
    root = tmp_path_factory.mktemp("bandit")
    cfg = bandit_config(run_dir=str(root / "sft"))
    cfg = dataclasses.replace(cfg, demos=dataclasses.replace(cfg.demos, path=str(root / "demos")))
    run_sft(cfg, log=lambda s: None)
    return str(root / "sft" / "policy")


def run(sft_policy, algo, iterations=6):
    cfg = bandit_config(init=sft_policy, iterations=iterations, algo=algo,
                        eval=EvalConfig(episodes=1000, seed=10_000, every=0))
    return run_bandit_demo(cfg, log=lambda s: None)


@pytest.mark.parametrize("algo", [
    PPOConfig(noise_level=0.3, lr=3e-4),
    PPOConfig(noise_level=0.3, lr=3e-4, sde_steps="one"),
    GRPOConfig(noise_level=0.3, lr=3e-4),
    GRPOConfig(noise_level=0.3, lr=3e-4, sde_steps="one"),
], ids=["ppo", "ppo-one", "grpo", "grpo-one"])
def test_baseline_learns_on_the_bandit(sft_policy, algo):
    result = run(sft_policy, algo)
    before, after = result["average"]["before"], result["average"]["after"]
    assert before < 0.5 and after >= 0.75 and after - before >= 0.3, (before, after)
    updates = result["history"][1:]
    assert all(r["losses/update_steps"] > 0 for r in updates)
    if algo.name == "ppo":
        assert all("losses/value_loss" in r for r in updates)


def test_ode_exploration_variant_does_not_learn(sft_policy):
    """The `ode` variant (π-StepNFT with noise 0) from the same start: no ranking signal."""
    result = run(sft_policy, variant_config("ode", bandit_config().algo), iterations=4)
    updates = result["history"][1:]
    assert all(abs(r["losses/E_pos"] - r["losses/E_neg"]) < 1e-3 for r in updates)
    assert result["average"]["after"] - result["average"]["before"] < 0.1
