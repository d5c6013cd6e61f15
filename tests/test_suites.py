"""Evaluation suites: deterministic under a seed, one held-out perturbation per episode in
equal shares, the policy's instruction binding restored, suites that cannot apply skipped."""

import numpy as np
import pytest
import torch

from stepnft.config import EnvConfig
from stepnft.envs import make_vec_env
from stepnft.policies.flow import FlowPolicy, FlowPolicyConfig
from stepnft.suites import (env_for_policy, evaluate_suite, evaluate_suites, format_suites, suite_perturbations,
                            summarize_suites)
from test_evaluate import goal_seeker

pytestmark = pytest.mark.filterwarnings("ignore:Constant:UserWarning")

ENV = EnvConfig(tasks=["reach-v3", "push-v3"], envs_per_task=2, max_episode_steps=16)


def test_suites_are_deterministic_under_a_seed():
    policy = goal_seeker()
    first = evaluate_suite(policy, ENV, "execution", episodes=4, seed=5)
    assert first == evaluate_suite(policy, ENV, "execution", episodes=4, seed=5)
    assert first["suite"] == "execution" and first["tasks"]["push-v3"]["episodes"] == 4
    # Seeds 5..8 cycle through the four perturbations: one episode of each per task.
    assert {name: r["episodes"] for name, r in first["breakdown"].items()} == {
        "action_noise": 2, "friction": 2, "mass": 2, "object_position": 2}
    ind = evaluate_suite(policy, ENV, "ind", episodes=4, seed=5)
    assert "breakdown" not in ind and ind["tasks"].keys() == first["tasks"].keys()


def test_semantic_suite_changes_only_the_instruction_embedding():
    torch.manual_seed(0)
    policy = FlowPolicy(FlowPolicyConfig(hidden_dim=16, num_layers=1))
    policy.processor.bind_instructions(["a", "b"])
    table = policy.processor.instruction_table
    nominal = make_vec_env(ENV, 4, seed=0)
    semantic = make_vec_env(ENV, 4, seed=0, perturbations=suite_perturbations("semantic"))
    seeds = [0, 1, 2, 3]
    raw, raw_sem = nominal.reset(seed=seeds)[0], semantic.reset(seed=seeds)[0]
    np.testing.assert_array_equal(raw["state"], raw_sem["state"])
    assert (raw_sem["instruction"] > 0).all()  # a held-out variant in every episode
    task = torch.as_tensor(nominal.task_ids)
    with policy.processor.bound(nominal.instruction_variants):
        canonical = policy.processor({"state": torch.as_tensor(raw["state"]), "task": task})
    with policy.processor.bound(semantic.instruction_variants):
        shifted = policy.processor({"state": torch.as_tensor(raw_sem["state"]), "task": task,
                                    "instruction": torch.as_tensor(raw_sem["instruction"])})
    torch.testing.assert_close(shifted["state"], canonical["state"])
    assert not torch.isclose(shifted["lang"], canonical["lang"]).all(dim=1).any()
    assert policy.processor.instruction_table is table  # the run's binding is back
    result = evaluate_suite(policy, ENV, "semantic", episodes=2, seed=0)
    assert result == evaluate_suite(policy, ENV, "semantic", episodes=2, seed=0)
    assert set(result["breakdown"]) == {"paraphrase", "distractor"}
    nominal.close()
    semantic.close()


def test_suites_that_cannot_apply_are_skipped():
    policy = goal_seeker()  # a state policy without language
    with pytest.raises(ValueError, match="vision suite does not apply to this policy: a state policy sees no image"):
        evaluate_suite(policy, ENV, "vision", episodes=2)
    results = evaluate_suites(policy, ENV, ["ind,vision", "semantic", "execution"], episodes=2, seed=0)
    assert "skipped" in results["suites"]["vision"] and "skipped" in results["suites"]["semantic"]
    row = summarize_suites(results["suites"])
    assert row["vision"] is None and results["ood_average"] == row["execution"] == row["ood_average"]
    assert "vision skipped" in format_suites(results)
    with pytest.raises(ValueError, match="unknown suite 'weather'"):
        evaluate_suites(policy, ENV, ["weather"], episodes=2)


def test_the_env_follows_a_camera_policy():
    cfg = FlowPolicyConfig(state_dim=4, cameras=["corner"])
    env = env_for_policy(EnvConfig(tasks=["reach-v3"]), cfg)
    assert env.cameras == ["corner"] and env.state_obs == "proprio"
    with pytest.raises(ValueError, match="the policy sees cameras"):
        env_for_policy(EnvConfig(tasks=["reach-v3"], cameras=["topview"]), cfg)
