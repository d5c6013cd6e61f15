"""A LeRobot VLA's memory settings (stepnft.policies.lerobot.adapter): ``--precision bf16``,
gradient checkpointing per transformer layer, LoRA adapters (peft) with ``train: vlm``.

Runs in the LeRobot environment, like tests/policies/test_lerobot.py (whose tiny SmolVLA and
bandit observations it reuses); skipped elsewhere."""

import importlib.util
import json

import pytest
import torch

from test_lerobot import PARTS, HAVE_LEROBOT, load, needs_lerobot, raw_obs, rollout_batch, tiny_folder  # noqa: F401
from test_memory import BF16_TOLERANCE, kept_bytes

needs_peft = pytest.mark.skipif(importlib.util.find_spec("peft") is None,
                                reason="peft is not installed (bash scripts/bootstrap.sh --lerobot installs it)")


def _step_inputs(policy, calls: int = 6):
    """Processed observations of ``calls`` policy calls and two denoising points per call."""
    g = torch.Generator().manual_seed(3)
    obs = policy.prepare(raw_obs(calls, seed=3))
    rows = torch.arange(calls).repeat_interleave(2)
    x = torch.randn(len(rows), *policy.chunk_shape, generator=g)
    return obs, x, torch.rand(len(rows), generator=g), rows


def _relative(a, b) -> float:
    return float((a - b).norm() / b.norm())


@needs_lerobot
def test_bf16_halves_the_frozen_backbone_and_keeps_velocities_and_updates_close(tiny_folder):
    from stepnft.algos.stepnft import StepNFTConfig, stepnft_update

    policy = load(tiny_folder)  # train: expert: the VLM is frozen
    obs, x, t, rows = _step_inputs(policy)
    reference = policy(obs, x, t, context_rows=rows).detach()
    frozen = [p for p in policy.parameters() if not p.requires_grad]
    frozen_bytes, total_bytes = sum(p.nbytes for p in frozen), sum(p.nbytes for p in policy.parameters())
    policy.set_precision("bf16")
    assert all(p.dtype == torch.bfloat16 for p in frozen)
    assert sum(p.nbytes for p in frozen) * 2 == frozen_bytes
    assert sum(p.nbytes for p in policy.parameters()) == total_bytes - frozen_bytes // 2
    assert all(p.dtype == torch.float32 for p in policy.parameters() if p.requires_grad)
    v = policy(obs, x, t, context_rows=rows)
    assert v.dtype == torch.float32 and _relative(v.detach(), reference) < BF16_TOLERANCE
    cfg = StepNFTConfig(lr=1e-3, minibatch_size=16, update_epochs=1, max_drift=None, label_balance="none")
    metrics = stepnft_update(policy.train(), torch.optim.AdamW([p for p in policy.parameters() if p.requires_grad]),
                             rollout_batch(policy.eval()), cfg, torch.Generator().manual_seed(0))
    assert metrics["losses/update_steps"] > 0 and metrics["losses/skipped_nonfinite"] == 0


@needs_lerobot
@pytest.mark.parametrize("scope", ["expert", "vlm"])
def test_gradient_checkpointing_per_layer_gives_the_same_gradients_and_keeps_less(tiny_folder, scope):
    from stepnft.ema import make_ema_copy

    policy = load(tiny_folder, train=scope).train()
    obs, x, t, rows = _step_inputs(policy)
    keys = set(policy.state_dict())

    def grads() -> dict[str, torch.Tensor]:
        policy.zero_grad()
        policy(obs, x, t, context_rows=rows).square().mean().backward()
        return {k: p.grad.clone() for k, p in policy.named_parameters() if p.grad is not None}

    plain, plain_kept = grads(), kept_bytes(policy, obs, x, t, context_rows=rows)
    policy.set_gradient_checkpointing(True)
    checkpointed, kept = grads(), kept_bytes(policy, obs, x, t, context_rows=rows)
    assert kept < plain_kept and set(policy.state_dict()) == keys  # the same weights' names
    vlm = PARTS[policy.type]["vlm"]
    assert plain.keys() == checkpointed.keys() and any(vlm in k for k in plain) == (scope == "vlm")
    for name, grad in plain.items():
        torch.testing.assert_close(checkpointed[name], grad, rtol=1e-5, atol=1e-7, msg=name)
    ema = make_ema_copy(policy)  # a copy is checkpointed alike and samples as the policy does
    a = policy.sample(obs, generator=torch.Generator().manual_seed(0)).actions
    torch.testing.assert_close(ema.sample(obs, generator=torch.Generator().manual_seed(0)).actions, a)
    policy.set_gradient_checkpointing(False)
    assert not any(type(m).__name__.startswith("Checkpointed") for m in policy.modules())


@needs_lerobot
def test_lora_needs_train_vlm():
    from stepnft.policies.lerobot.configuration import LeRobotPolicyConfig

    with pytest.raises(ValueError, match="lora_rank=4 adapts the VLM's layers: it needs train=vlm"):
        LeRobotPolicyConfig(train="expert", lora_rank=4)


@needs_lerobot
@needs_peft
def test_lora_adapters_train_instead_of_the_vlm_layers_and_save_apart(tiny_folder, tmp_path):
    from safetensors.torch import load_file

    from stepnft.algos.stepnft import StepNFTConfig, stepnft_update
    from stepnft.policies.base import load_policy

    whole = load(tiny_folder, train="vlm")
    policy = load(tiny_folder, train="vlm", lora_rank=2, lora_alpha=4)  # no lora.safetensors: fresh adapters
    obs, x, t, rows = _step_inputs(policy)
    # B starts at 0: the adapted model is the model
    torch.testing.assert_close(policy(obs, x, t, context_rows=rows), whole(obs, x, t, context_rows=rows))
    trained = {n for n, p in policy.named_parameters() if p.requires_grad}
    part = PARTS[policy.type]
    vlm_trained = {n for n in trained if part["vlm"] in n}
    assert vlm_trained and all("lora_" in n for n in vlm_trained)
    assert all(any(f"{p}_proj" in n for p in "qkvo") and part["lm"] in n for n in vlm_trained)
    assert any(part["expert"] in n for n in trained)
    assert any("state_proj" in n for n in trained) == (policy.type != "pi05")  # π0.5's state is in its prompt
    assert sum(p.numel() for n, p in policy.named_parameters() if n in trained) < \
        sum(p.numel() for p in whole.parameters() if p.requires_grad)

    before = {n: p.detach().clone() for n, p in policy.named_parameters()}
    cfg = StepNFTConfig(lr=1e-2, minibatch_size=16, update_epochs=1, max_drift=None, label_balance="none")
    stepnft_update(policy.train(), torch.optim.AdamW([p for p in policy.parameters() if p.requires_grad], lr=1e-2),
                   rollout_batch(policy.eval()), cfg, torch.Generator().manual_seed(0))
    changed = {n for n, p in policy.named_parameters() if not torch.equal(p, before[n])}
    assert changed <= trained and any("lora_B" in n for n in changed)

    folder = policy.save_pretrained(tmp_path / "saved")
    assert json.loads((folder / "config.json").read_text())["lora_rank"] == 2
    adapters = load_file(str(folder / "lora.safetensors"))
    base = load_file(str(folder / "lerobot" / "model.safetensors"))
    assert adapters and all("lora_" in k for k in adapters)
    assert not any("lora_" in k or "base_layer" in k for k in base)  # LeRobot's own layout: the base weights
    loaded = load_policy(folder)
    loaded.processor.bind_instructions(policy.processor.instructions)
    policy.eval()
    with torch.no_grad():
        a, b = policy(obs, x, t, context_rows=rows), loaded(obs, x, t, context_rows=rows)
    torch.testing.assert_close(b, a, rtol=0, atol=0)
    # merged into a plain folder: the same velocities, and LeRobot's own folder is the fine-tuned model
    from stepnft.policies.lerobot.__main__ import main

    assert main(["merge", "--policy", str(folder), "--out", str(tmp_path / "merged")]) == 0
    merged = load_policy(tmp_path / "merged")
    assert merged.config.lora_rank == 0 and not (tmp_path / "merged" / "lora.safetensors").exists()
    assert not any("lora_" in n for n, _ in merged.named_parameters())
    base = load_policy(folder / "lerobot")  # before merging, LeRobot's folder holds the base weights
    base.processor.bind_instructions(policy.processor.instructions)
    with torch.no_grad():
        assert not torch.allclose(base.eval()(obs, x, t, context_rows=rows), a, rtol=1e-4, atol=1e-5)
    plain = load_policy(tmp_path / "merged" / "lerobot")  # the LeRobot folder alone, as LeRobot saved it
    for other in (merged, plain):
        other.processor.bind_instructions(policy.processor.instructions)
        with torch.no_grad():
            torch.testing.assert_close(other.eval()(obs, x, t, context_rows=rows), a, rtol=1e-4, atol=1e-5)
    assert main(["merge", "--policy", str(tmp_path / "merged"), "--out", str(tmp_path / "again")]) == 2
    (folder / "config.json").write_text(json.dumps(json.loads((folder / "config.json").read_text()) | {"lora_rank": 3}))
    with pytest.raises(ValueError, match="does not match the policy's adapters"):
        load_policy(folder)
