import pytest
import torch

from stepnft.algos.stepnft import StepNFTConfig, label_weights, stepnft_update
from stepnft.policies.flow import FlowPolicy, FlowPolicyConfig


def test_label_weights_global_and_per_task():
    y = torch.tensor([1.0, -1, -1, -1, 1, -1])
    w = label_weights(y)
    # 2 positives, 4 negatives: each class gets half of the total weight 6.
    torch.testing.assert_close(w, torch.tensor([1.5, 0.75, 0.75, 0.75, 1.5, 0.75]))
    assert w[y > 0].sum() == pytest.approx(w[y < 0].sum())
    task = torch.tensor([0, 0, 0, 1, 1, 2])
    w = label_weights(y, task)
    # task 0: one success, two failures; task 1: one each; task 2: only a failure (weight 1).
    torch.testing.assert_close(w, torch.tensor([1.5, 0.75, 0.75, 1.0, 1.0, 1.0]))


def test_invalid_config_is_a_clear_error():
    with pytest.raises(ValueError, match="algo.label_balance"):
        StepNFTConfig(label_balance="yes")
    with pytest.raises(ValueError, match="algo.lr"):
        StepNFTConfig(lr=-1.0)


def _batch(n=256, seed=0):
    g = torch.Generator().manual_seed(seed)
    policy = FlowPolicy(FlowPolicyConfig(state_dim=3, lang_dim=0, action_dim=2, horizon=2, n_exec=2, hidden_dim=32))
    state = torch.randn(n, 3, generator=g)
    sample = policy.sample(state, noise_level=0.3, generator=g)
    y = (sample.actions[:, 0, 0] > 0).float() * 2 - 1
    batch = {"state": state, "x_t": sample.x_t, "x_next": sample.x_next, "v_old": sample.v_old,
             "actions": sample.actions, "t": sample.t, "dt": sample.dt, "y": y,
             "mask": torch.ones(n, 2, dtype=torch.bool)}
    return policy, batch


def test_update_runs_epochs_and_moves_toward_successes():
    policy, batch = _batch()
    cfg = StepNFTConfig(noise_level=0.3, lr=1e-3, update_epochs=3, minibatch_size=64)
    opt = torch.optim.AdamW(policy.parameters(), lr=cfg.lr)
    before = policy.sample(batch["state"], generator=torch.Generator().manual_seed(5)).actions[:, 0, 0].mean()
    metrics = stepnft_update(policy, opt, batch, cfg, torch.Generator().manual_seed(0))
    assert metrics["update_steps"] == 12 and metrics["drift_stopped"] == 0.0
    after = policy.sample(batch["state"], generator=torch.Generator().manual_seed(5)).actions[:, 0, 0].mean()
    assert after > before  # successes were the chunks with a positive first coordinate


def test_drift_limit_stops_epochs_early():
    policy, batch = _batch()
    cfg = StepNFTConfig(noise_level=0.3, lr=1e-2, update_epochs=20, minibatch_size=64, drift_limit=0.05)
    opt = torch.optim.AdamW(policy.parameters(), lr=cfg.lr)
    metrics = stepnft_update(policy, opt, batch, cfg, torch.Generator().manual_seed(0))
    assert metrics["drift_stopped"] == 1.0 and metrics["update_steps"] < 80


def test_informative_mask_drops_single_label_tasks():
    from stepnft.algos.stepnft import informative_mask

    y = torch.tensor([1.0, -1, 1, 1, -1, -1])
    task = torch.tensor([0, 0, 1, 1, 2, 2])
    assert informative_mask(y, task).tolist() == [True, True, False, False, False, False]


def test_episode_weights_equalise_episodes_and_combine_with_balance():
    from stepnft.algos.stepnft import episode_weights

    episode = torch.tensor([0, 0, 0, 1])  # a 3-call episode and a 1-call episode
    w = episode_weights(episode)
    assert w[:3].sum().item() == pytest.approx(w[3].item()) and w.mean().item() == pytest.approx(1.0)
    y = torch.tensor([-1.0, -1, -1, 1])
    balanced = label_weights(y, base=w)
    assert balanced[y > 0].sum().item() == pytest.approx(balanced[y < 0].sum().item())
