"""The policy's memory settings: ``--precision bf16`` and gradient checkpointing (stepnft.policies.base)."""

import pytest
import torch

from stepnft.demo_bandit import bandit_config, run_bandit_demo
from stepnft.losses import stepnft_loss
from stepnft.policies.flow import FlowPolicy, FlowPolicyConfig

BF16_TOLERANCE = 0.05
"""Relative error of a velocity or of the loss computed in bf16 against float32 on the same batch
(bfloat16 keeps 8 significant bits: ~0.4 % per rounding, a few roundings deep)."""


def _policy(**changes) -> FlowPolicy:
    torch.manual_seed(0)
    return FlowPolicy(FlowPolicyConfig(state_dim=6, lang_dim=8, action_dim=3, horizon=4, hidden_dim=64, **changes))


def _inputs(batch: int = 16, cameras: int = 0):
    g = torch.Generator().manual_seed(1)
    obs = {"state": torch.randn(batch, 6, generator=g), "lang": torch.randn(batch, 8, generator=g)}
    if cameras:
        obs["image"] = torch.rand(batch, cameras, 3, 16, 16, generator=g)
    return obs, torch.randn(batch, 4, 3, generator=g), torch.rand(batch, generator=g)


def _relative(a: torch.Tensor, b: torch.Tensor) -> float:
    return float((a - b).norm() / b.norm())


def test_bf16_stores_frozen_parameters_in_half_the_memory_and_computes_close_to_fp32():
    policy = _policy()
    policy.lang_proj.requires_grad_(False)  # a frozen part, as a VLA's backbone with train: expert
    obs, x, t = _inputs()
    reference = policy(obs, x, t).detach()
    frozen_bytes = sum(p.nbytes for p in policy.lang_proj.parameters())
    policy.set_precision("bf16")
    assert all(p.dtype == torch.bfloat16 for p in policy.lang_proj.parameters())
    assert sum(p.nbytes for p in policy.lang_proj.parameters()) * 2 == frozen_bytes
    assert all(p.dtype == torch.float32 for p in policy.net.parameters())  # trained: float32 master weights
    v = policy(obs, x, t)
    assert v.dtype == torch.float32 and _relative(v.detach(), reference) < BF16_TOLERANCE
    v.square().mean().backward()  # gradients reach the trained parameters, in float32
    assert policy.net[0].weight.grad.dtype == torch.float32
    sample = policy.sample(obs, noise_level=0.5, generator=torch.Generator().manual_seed(0))
    assert sample.actions.dtype == torch.float32 and torch.isfinite(sample.actions).all()
    policy.set_precision("fp32")
    assert all(p.dtype == torch.float32 for p in policy.parameters())
    with pytest.raises(ValueError, match="precision='fp16' is invalid"):
        policy.set_precision("fp16")


def test_the_loss_in_bf16_matches_fp32_on_the_same_batch_and_its_energies_are_float32():
    policy = _policy()
    obs, x_t, t = _inputs(32)
    g = torch.Generator().manual_seed(2)
    v_old = policy(obs, x_t, t).detach() + 0.05 * torch.randn(x_t.shape, generator=g)
    dt = torch.full_like(t, 0.25)
    x_next = x_t - dt[:, None, None] * v_old + 0.1 * torch.randn(x_t.shape, generator=g)
    y = torch.where(torch.rand(32, generator=g) < 0.5, 1.0, -1.0)

    def loss(precision: str):
        policy.set_precision(precision)
        value, terms = stepnft_loss(policy(obs, x_t, t), v_old, x_t, x_next, t, dt, 0.5, y)
        return value.detach(), terms

    (ref, ref_terms), (low, low_terms) = loss("fp32"), loss("bf16")
    assert low.dtype == torch.float32
    assert abs(low.item() - ref.item()) <= BF16_TOLERANCE * abs(ref.item())
    for name in ("E_pos", "E_neg"):
        assert abs(low_terms[name] - ref_terms[name]) <= BF16_TOLERANCE * abs(ref_terms[name]), name


def test_bf16_learns_the_bandit_as_fp32_does():
    """The toy bandit through the whole loop (SFT and π-StepNFT in bf16): from a weak start to
    the float32 run's level (fp32 reaches >= 0.8 in the same iterations: tests/test_demo_bandit.py)."""
    run = run_bandit_demo(bandit_config(iterations=8, precision="bf16"), log=lambda s: None)
    assert run["average"]["before"] <= 0.5 and run["average"]["after"] >= 0.8, run["average"]


def kept_bytes(policy, *inputs, **kwargs) -> int:
    """Bytes of the tensors the forward pass ``policy(*inputs, **kwargs)`` keeps for the backward pass."""
    kept = []

    def pack(tensor):
        kept.append(tensor.nbytes)
        return tensor

    with torch.autograd.graph.saved_tensors_hooks(pack, lambda tensor: tensor):
        policy(*inputs, **kwargs)
    return sum(kept)


@pytest.mark.parametrize("cameras", [0, 1])
def test_gradient_checkpointing_gives_the_same_gradients(cameras):
    policy = _policy(cameras=["corner"] * cameras, image_size=16) if cameras else _policy()
    obs, x, t = _inputs(8, cameras)

    def grads(checkpointing: bool) -> dict[str, torch.Tensor]:
        policy.zero_grad()
        policy.set_gradient_checkpointing(checkpointing)
        policy(obs, x, t).square().mean().backward()
        return {k: p.grad.clone() for k, p in policy.named_parameters()}

    plain, checkpointed = grads(False), grads(True)
    assert policy.gradient_checkpointing
    assert kept_bytes(policy, obs, x, t) < kept_bytes(policy.set_gradient_checkpointing(False), obs, x, t)
    for name, grad in plain.items():
        torch.testing.assert_close(checkpointed[name], grad, rtol=1e-6, atol=1e-7, msg=name)
    with torch.no_grad():  # sampling is untouched
        torch.testing.assert_close(policy(obs, x, t), policy.set_gradient_checkpointing(False)(obs, x, t))


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA GPU")
def test_bf16_on_cuda_autocasts_and_returns_float32_velocities():
    policy = _policy().cuda()
    policy.lang_proj.requires_grad_(False)
    obs, x, t = (tensor.cuda() if torch.is_tensor(tensor) else {k: v.cuda() for k, v in tensor.items()}
                 for tensor in _inputs())
    reference = policy(obs, x, t).detach()
    v = policy.set_precision("bf16")(obs, x, t)
    assert policy.lang_proj.weight.dtype == torch.bfloat16 and v.dtype == torch.float32
    assert _relative(v.detach(), reference) < BF16_TOLERANCE
