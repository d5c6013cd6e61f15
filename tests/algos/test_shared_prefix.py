"""The update's context seam (``Policy.select_context``, ``Policy.forward(..., context_rows)``,
``step_velocity``): a policy that shares its prefix encodes each policy call once per minibatch
and its recorded steps read that context, with the velocities, losses and gradients of the
per-step path; the MLP flow policy keeps the per-step path bit for bit. A camera FlowPolicy
stands in for a VLA here (its CNN encoder has parameters, so gradients reach the context);
tests/policies/test_lerobot.py checks the same on a tiny SmolVLA."""

import copy
import functools

import pytest
import torch

from stepnft.algos import likelihood, stepnft as stepnft_module
from stepnft.algos.base import step_velocity
from stepnft.algos.grpo import GRPOConfig
from stepnft.algos.likelihood import policy_gradient_update
from stepnft.algos.stepnft import StepNFTConfig, stepnft_update
from stepnft.batch import Batch
from stepnft.policies.flow import FlowPolicy, FlowPolicyConfig

K = 4  # recorded steps per call (record_steps: all, the FlowPolicy's default num_inference_steps)


def camera_batch(calls: int = 24, seed: int = 0) -> tuple[FlowPolicy, Batch]:
    """A camera FlowPolicy and a batch of ``calls`` calls with all K steps recorded, half successful."""
    g = torch.Generator().manual_seed(seed)
    torch.manual_seed(seed)
    policy = FlowPolicy(FlowPolicyConfig(state_dim=3, lang_dim=0, action_dim=2, horizon=2, n_exec=2, hidden_dim=32,
                                         cameras=["c"], image_size=16, image_channels=4, image_features=8))
    obs = {"state": torch.randn(calls, 3, generator=g), "task": torch.arange(calls) % 2,
           "image": torch.randint(0, 256, (calls, 1, 3, 16, 16), dtype=torch.uint8, generator=g)}
    sample = policy.sample(policy.processor(obs), noise_level=0.3, generator=g, keep_path=True)
    steps = sample.recorded_steps(every_step=True)
    batch = Batch(episode_success=torch.arange(calls) % 2 == 0, episode_task=obs["task"].clone(),
                  episode_length=torch.full((calls,), 2), episode_seed=torch.full((calls,), -1), obs=obs,
                  actions=sample.actions, mask=torch.ones(calls, 2, dtype=torch.bool), reward=torch.zeros(calls),
                  done=torch.ones(calls, dtype=torch.bool), episode=torch.arange(calls), **steps)
    assert batch.num_steps == K * calls
    return policy, batch


def count_encodings(policy, monkeypatch) -> list[int]:
    """Observations encoded by each ``policy.encode`` call (appended to the returned list)."""
    rows, encode = [], policy.encode

    def counted(obs):
        rows.append(next(iter(obs.values())).shape[0])
        return encode(obs)

    monkeypatch.setattr(policy, "encode", counted)
    return rows


def sharing(policy: FlowPolicy) -> FlowPolicy:
    """A copy of ``policy`` that shares its context in the update (as a LeRobot VLA does)."""
    policy = copy.deepcopy(policy)
    policy.shares_prefix_in_update = True
    return policy


def test_the_mlp_flow_policy_keeps_the_per_step_path():
    assert FlowPolicy.shares_prefix_in_update is False


def test_a_shared_context_gives_the_per_step_velocities_and_gradients(monkeypatch):
    policy, batch = camera_batch()
    rows = torch.randperm(batch.num_steps, generator=torch.Generator().manual_seed(1))[:40]  # partial calls too
    weight = torch.randn(40, 2, 2, generator=torch.Generator().manual_seed(2))
    encoded = count_encodings(policy, monkeypatch)
    out = {}
    for share in (True, False):
        policy.zero_grad()
        v = step_velocity(policy, policy, batch, rows, share_prefix=share)
        (v * weight).sum().backward()
        out[share] = v.detach(), {n: p.grad.clone() for n, p in policy.named_parameters()}
    assert encoded == [len(batch.call[rows].unique()), 40]
    torch.testing.assert_close(out[True][0], out[False][0], rtol=1e-5, atol=1e-6)
    assert any(n.startswith("image_encoder") and g.abs().sum() > 0 for n, g in out[True][1].items())
    for name, grad in out[True][1].items():
        torch.testing.assert_close(grad, out[False][1][name], rtol=1e-5, atol=1e-6, msg=name)


def test_select_context_picks_rows_and_passes_gradients_back():
    policy, _ = camera_batch(calls=2)
    context = torch.arange(6.0).view(3, 2).requires_grad_()
    picked = policy.select_context(context, torch.tensor([2, 0, 2]))
    assert picked.tolist() == [[4.0, 5.0], [0.0, 1.0], [4.0, 5.0]]
    picked.sum().backward()
    assert context.grad.tolist() == [[1.0, 1.0], [0.0, 0.0], [2.0, 2.0]]


def test_a_sharing_policys_stepnft_update_encodes_each_call_once_with_the_per_step_losses(monkeypatch):
    """Minibatches of whole calls (minibatch_size // K of them), each call encoded once: K times
    fewer encodings than the per-step path on the same minibatches, the same losses and weights."""
    base, batch = camera_batch()
    cfg = StepNFTConfig(noise_level=0.3, lr=1e-3, minibatch_size=32, update_epochs=2, label_balance="none")
    runs = {}
    for share in (True, False):
        policy = sharing(base)
        encoded = count_encodings(policy, monkeypatch)
        if not share:  # the per-step path on the same (whole-call) minibatches
            monkeypatch.setattr(stepnft_module, "step_velocity", functools.partial(step_velocity, share_prefix=False))
        seen = []
        forward = policy.forward
        monkeypatch.setattr(policy, "forward", lambda obs, x_t, t, **kw: seen.append(x_t.shape[0]) or forward(
            obs, x_t, t, **kw))
        optimizer = torch.optim.AdamW(policy.parameters(), lr=cfg.lr)
        metrics = stepnft_update(policy, optimizer, batch, cfg, torch.Generator().manual_seed(0))
        runs[share] = metrics, encoded, seen, policy
    (shared, shared_enc, shared_rows, shared_policy), (step, step_enc, step_rows, step_policy) = runs[True], runs[False]
    assert shared["losses/update_steps"] == 2 * 24 // 8  # 8 calls (32 recorded steps) per minibatch
    assert shared_rows == step_rows == [32] * 6
    assert shared_enc == [8] * 6 and step_enc == [32] * 6  # K = 4 times fewer encodings
    assert shared.keys() == step.keys()
    for key, value in shared.items():
        assert value == pytest.approx(step[key], rel=1e-4, abs=1e-6), key
    for a, b in zip(shared_policy.parameters(), step_policy.parameters()):
        torch.testing.assert_close(a, b, rtol=1e-4, atol=1e-5)


def test_the_likelihood_update_shares_the_context_too(monkeypatch):
    """PPO and GRPO (``policy_gradient_update``) already take whole calls: each is encoded once."""
    base, batch = camera_batch()
    advantages = torch.where(torch.arange(24) % 2 == 0, 1.0, -1.0)
    cfg = GRPOConfig(noise_level=0.3, lr=1e-3, minibatch_size=32, update_epochs=1, group_size=2)
    runs = {}
    for share in (True, False):
        policy = sharing(base)
        encoded = count_encodings(policy, monkeypatch)
        if not share:
            monkeypatch.setattr(likelihood, "step_velocity", functools.partial(step_velocity, share_prefix=False))
        metrics = policy_gradient_update(policy, torch.optim.AdamW(policy.parameters(), lr=cfg.lr), batch,
                                         advantages, cfg, torch.Generator().manual_seed(0))
        runs[share] = metrics, encoded
    assert runs[True][1] == [8] * 3 and runs[False][1] == [32] * 3
    for key, value in runs[True][0].items():
        assert value == pytest.approx(runs[False][0][key], rel=1e-4, abs=1e-6), key


def test_the_mlp_update_is_the_per_step_path_bit_for_bit(monkeypatch):
    """FlowPolicy's π-StepNFT update is the path its published results ran: minibatches are each
    pass's randperm of recorded steps, and every velocity is the per-step forward (each step's
    observation processed and encoded on its own), so weights and metrics are equal bit for bit."""
    base, batch = camera_batch()
    cfg = StepNFTConfig(noise_level=0.3, lr=1e-3, minibatch_size=32, update_epochs=2)

    def previous_step_velocity(learner, policy, batch, rows):  # the update's velocity before the seam
        return learner(policy.prepare(batch.steps_obs(rows)), batch.x_t[rows], batch.t[rows])

    results, minibatches = [], []
    for velocity in (step_velocity, previous_step_velocity):
        policy = copy.deepcopy(base)
        rows_seen = []

        def spy(learner, policy, batch, rows, velocity=velocity, rows_seen=rows_seen):
            rows_seen.append(rows.clone())
            return velocity(learner, policy, batch, rows)

        monkeypatch.setattr(stepnft_module, "step_velocity", spy)
        metrics = stepnft_update(policy, torch.optim.AdamW(policy.parameters(), lr=cfg.lr), batch, cfg,
                                 torch.Generator().manual_seed(0))
        results.append((metrics, [p.detach().clone() for p in policy.parameters()]))
        minibatches.append(rows_seen)
    g = torch.Generator().manual_seed(0)
    previous = [idx for _ in range(cfg.update_epochs) for idx in torch.randperm(batch.num_steps, generator=g).split(32)]
    for rows_seen in minibatches:
        assert len(rows_seen) == len(previous) and all(torch.equal(a, b) for a, b in zip(rows_seen, previous))
    (now, now_weights), (before, before_weights) = results
    assert now == before  # every metric, exactly
    assert all(torch.equal(a, b) for a, b in zip(now_weights, before_weights))
