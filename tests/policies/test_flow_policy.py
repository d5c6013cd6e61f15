import json

import pytest
import torch

from stepnft.policies.flow import FlowPolicy, FlowPolicyConfig


@pytest.mark.parametrize("lang_dim", [0, 16])
def test_save_load_round_trip(tmp_path, lang_dim):
    cfg = FlowPolicyConfig(state_dim=5, lang_dim=lang_dim, action_dim=3, horizon=4, n_exec=2, hidden_dim=32, num_layers=2)
    policy = FlowPolicy(cfg)
    policy.set_normalization(torch.randn(50, 5) * 3 + 1)
    policy.save_pretrained(tmp_path)
    assert json.loads((tmp_path / "config.json").read_text())["horizon"] == 4
    loaded = FlowPolicy.from_pretrained(tmp_path)
    assert loaded.config == cfg
    state, lang = torch.randn(7, 5), (torch.randn(7, lang_dim) if lang_dim else None)
    x, t = torch.randn(7, 4, 3), torch.rand(7)
    torch.testing.assert_close(policy(state, lang, x, t), loaded(state, lang, x, t))
    out = loaded.sample(state, lang, generator=torch.Generator().manual_seed(0))
    assert out.actions.shape == (7, 4, 3)


def test_missing_and_corrupt_checkpoint(tmp_path):
    with pytest.raises(FileNotFoundError, match="no policy checkpoint"):
        FlowPolicy.from_pretrained(tmp_path / "nope")
    FlowPolicy(FlowPolicyConfig(state_dim=2, lang_dim=0, hidden_dim=8)).save_pretrained(tmp_path)
    (tmp_path / "model.safetensors").write_bytes(b"garbage")
    with pytest.raises(ValueError, match="corrupt policy checkpoint"):
        FlowPolicy.from_pretrained(tmp_path)


def test_normalization_floors_std_and_clamps():
    policy = FlowPolicy(FlowPolicyConfig(state_dim=2, lang_dim=0, state_min_std=0.1, state_clip=3.0))
    states = torch.tensor([[0.0, 5.0], [1.0, 5.0], [2.0, 5.0]])
    policy.set_normalization(states)
    assert policy.state_std[1].item() == pytest.approx(0.1)
    feats = policy.encode_obs(torch.tensor([[1.0, 9.0]]))
    assert feats[0, 0].item() == pytest.approx(0.0) and feats[0, 1].item() == pytest.approx(3.0)


def test_config_validation():
    with pytest.raises(ValueError, match="n_exec"):
        FlowPolicyConfig(horizon=2, n_exec=3)
    with pytest.raises(ValueError, match="unknown policy config keys"):
        FlowPolicyConfig.from_dict({"bogus": 1})
