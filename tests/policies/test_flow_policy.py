import json

import pytest
import torch

from stepnft.policies.base import Policy, load_policy, make_policy
from stepnft.policies.flow import FlowPolicy, FlowPolicyConfig


def _raw(batch: int, state_dim: int, tasks: int = 2) -> dict:
    return {"state": torch.randn(batch, state_dim), "task": torch.arange(batch) % tasks}


@pytest.mark.parametrize("lang_dim", [0, 384])
def test_save_load_round_trip(tmp_path, lang_dim):
    cfg = FlowPolicyConfig(state_dim=5, lang_dim=lang_dim, action_dim=3, horizon=4, n_exec=2, hidden_dim=32, num_layers=2)
    policy = make_policy(cfg)
    assert isinstance(policy, FlowPolicy)
    policy.processor.fit(torch.randn(50, 5) * 3 + 1)
    instructions = ["pick up the puck", "open the door"]
    policy.processor.bind_instructions(instructions)
    policy.save_pretrained(tmp_path)
    saved = json.loads((tmp_path / "config.json").read_text())
    assert saved["type"] == "flow" and saved["horizon"] == 4
    loaded = Policy.from_pretrained(tmp_path)  # dispatches on the saved type
    assert isinstance(loaded, FlowPolicy) and loaded.config == cfg
    loaded.processor.bind_instructions(instructions)
    raw, x, t = _raw(7, 5), torch.randn(7, 4, 3), torch.rand(7)
    torch.testing.assert_close(policy.velocity(policy.processor(raw), x, t), loaded.velocity(loaded.processor(raw), x, t))
    out = loaded.sample(loaded.processor(raw), generator=torch.Generator().manual_seed(0))
    assert out.actions.shape == (7, 4, 3)
    torch.testing.assert_close(out.actions, policy.sample(policy.processor(raw), generator=torch.Generator().manual_seed(0)).actions)


def test_policies_saved_before_processors_still_load(tmp_path):
    """Folders from earlier releases kept the normalisation statistics among the weights."""
    from safetensors.torch import load_file, save_file

    policy = FlowPolicy(FlowPolicyConfig(state_dim=3, lang_dim=0, hidden_dim=8))
    policy.processor.fit(torch.randn(20, 3) + 4)
    policy.save_pretrained(tmp_path)
    weights = load_file(str(tmp_path / "model.safetensors")) | load_file(str(tmp_path / "processor.safetensors"))
    save_file(weights, str(tmp_path / "model.safetensors"))
    (tmp_path / "processor.safetensors").unlink()
    loaded = load_policy(tmp_path)
    torch.testing.assert_close(loaded.processor.state_mean, policy.processor.state_mean)


def test_missing_corrupt_and_wrong_type_checkpoint(tmp_path):
    with pytest.raises(FileNotFoundError, match="no policy checkpoint"):
        FlowPolicy.from_pretrained(tmp_path / "nope")
    FlowPolicy(FlowPolicyConfig(state_dim=2, lang_dim=0, hidden_dim=8)).save_pretrained(tmp_path)
    config = json.loads((tmp_path / "config.json").read_text())
    (tmp_path / "config.json").write_text(json.dumps({**config, "type": "vla-nobody-registered"}))
    with pytest.raises(ValueError, match="unknown policy type 'vla-nobody-registered'"):
        load_policy(tmp_path)
    (tmp_path / "config.json").write_text(json.dumps([1, 2]))
    with pytest.raises(ValueError, match="corrupt policy checkpoint.*JSON object"):
        load_policy(tmp_path)
    (tmp_path / "config.json").write_text(json.dumps(config))
    (tmp_path / "model.safetensors").write_bytes(b"garbage")
    with pytest.raises(ValueError, match="corrupt policy checkpoint"):
        FlowPolicy.from_pretrained(tmp_path)


def test_processor_floors_std_clamps_and_looks_up_instructions():
    policy = FlowPolicy(FlowPolicyConfig(state_dim=2, lang_dim=0, state_min_std=0.1, state_clip=3.0))
    policy.processor.fit(torch.tensor([[0.0, 5.0], [1.0, 5.0], [2.0, 5.0]]))
    assert policy.processor.state_std[1].item() == pytest.approx(0.1)
    obs = policy.processor({"state": torch.tensor([[1.0, 9.0]]), "task": torch.tensor([0])})
    assert obs["state"][0, 0].item() == pytest.approx(0.0) and obs["state"][0, 1].item() == pytest.approx(3.0)
    assert "lang" not in obs

    lang = FlowPolicy(FlowPolicyConfig(state_dim=2, lang_dim=384))
    with pytest.raises(ValueError, match="bind_instructions"):
        lang.processor({"state": torch.zeros(1, 2), "task": torch.tensor([0])})
    lang.processor.bind_instructions(["open the door", "close the door"])
    out = lang.processor({"state": torch.zeros(3, 2), "task": torch.tensor([1, 0, 1])})
    torch.testing.assert_close(out["lang"][0], lang.processor.instruction_table[1])
    torch.testing.assert_close(out["lang"][0], out["lang"][2])
    assert not torch.equal(out["lang"][0], out["lang"][1])


def test_the_context_is_encoded_once_per_sample():
    policy = FlowPolicy(FlowPolicyConfig(state_dim=2, lang_dim=0, hidden_dim=8, num_inference_steps=4))
    calls = []
    encode = policy.encode
    policy.encode = lambda obs: (calls.append(1), encode(obs))[1]
    policy.sample(policy.processor(_raw(3, 2)), noise_level=0.3, generator=torch.Generator().manual_seed(0))
    assert len(calls) == 1


def test_config_validation():
    with pytest.raises(ValueError, match="n_exec"):
        FlowPolicyConfig(horizon=2, n_exec=3)
    with pytest.raises(ValueError, match="unknown policy config keys"):
        FlowPolicyConfig.from_dict({"bogus": 1})
