"""π-StepNFT's update on a hand-built batch: weights, epochs, direction, and what each
ablation switch changes."""

import dataclasses

import pytest
import torch

from stepnft.algos.base import make_algorithm
from stepnft.algos.stepnft import StepNFT, StepNFTConfig, episode_weights, informative_mask, label_weights, stepnft_update
from stepnft.batch import Batch
from stepnft.losses import stepnft_loss
from stepnft.policies.flow import FlowPolicy, FlowPolicyConfig


def make_batch(n=256, seed=0, noise_level=0.3, record_all=False):
    """One policy call per episode; an episode succeeds when its chunk's first coordinate is > 0."""
    g = torch.Generator().manual_seed(seed)
    torch.manual_seed(seed)
    policy = FlowPolicy(FlowPolicyConfig(state_dim=3, lang_dim=0, action_dim=2, horizon=2, n_exec=2, hidden_dim=32))
    state = torch.randn(n, 3, generator=g)
    obs = {"state": state, "task": torch.arange(n) % 2}
    sample = policy.sample(policy.processor(obs), noise_level=noise_level, generator=g, keep_path=record_all)
    steps = sample.recorded_steps(every_step=record_all)
    batch = Batch(
        episode_success=sample.actions[:, 0, 0] > 0, episode_task=obs["task"].clone(),
        episode_length=torch.full((n,), 2), episode_seed=torch.full((n,), -1), obs=obs, actions=sample.actions,
        mask=torch.ones(n, 2, dtype=torch.bool), reward=torch.zeros(n), done=torch.ones(n, dtype=torch.bool),
        episode=torch.arange(n), **steps)
    return policy, batch


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
    with pytest.raises(ValueError, match="algo.adam_betas"):
        StepNFTConfig(adam_betas=(0.9, 1.5))
    with pytest.raises(ValueError, match="sde_steps=one needs algo.record_steps=one"):
        StepNFTConfig(sde_steps="one", record_steps="all")
    StepNFTConfig(sde_steps="one", record_steps="one")


def test_update_runs_epochs_and_moves_toward_successes():
    policy, batch = make_batch()
    cfg = StepNFTConfig(noise_level=0.3, lr=1e-3, update_epochs=3, minibatch_size=64)
    opt = torch.optim.AdamW(policy.parameters(), lr=cfg.lr)
    obs = policy.processor(batch.obs)
    before = policy.sample(obs, generator=torch.Generator().manual_seed(5)).actions[:, 0, 0].mean()
    metrics = stepnft_update(policy, opt, batch, cfg, torch.Generator().manual_seed(0))
    assert metrics["losses/update_steps"] == 12 and metrics["losses/drift_stopped"] == 0.0
    assert 0 < metrics["charts/pos_sample_frac"] < 1
    after = policy.sample(obs, generator=torch.Generator().manual_seed(5)).actions[:, 0, 0].mean()
    assert after > before  # successes were the chunks with a positive first coordinate


def test_drift_limit_stops_epochs_early():
    policy, batch = make_batch()
    cfg = StepNFTConfig(noise_level=0.3, lr=1e-2, update_epochs=20, minibatch_size=64, drift_limit=0.05)
    opt = torch.optim.AdamW(policy.parameters(), lr=cfg.lr)
    metrics = stepnft_update(policy, opt, batch, cfg, torch.Generator().manual_seed(0))
    assert metrics["losses/drift_stopped"] == 1.0 and metrics["losses/update_steps"] < 80


def test_informative_mask_drops_single_label_tasks():
    y = torch.tensor([1.0, -1, 1, 1, -1, -1])
    task = torch.tensor([0, 0, 1, 1, 2, 2])
    assert informative_mask(y, task).tolist() == [True, True, False, False, False, False]


def test_minibatches_with_no_weight_take_no_optimizer_step():
    """With every task uniform, drop_uniform_tasks zeroes every weight: no Adam step may move
    the policy (zero gradients still would, through the optimizer's momentum)."""
    policy, batch = make_batch(n=64)
    batch.episode_success[:] = True
    cfg = StepNFTConfig(noise_level=0.3, lr=1e-2, minibatch_size=16, drop_uniform_tasks=True)
    opt = torch.optim.AdamW(policy.parameters(), lr=cfg.lr)
    before = [p.clone() for p in policy.parameters()]
    metrics = stepnft_update(policy, opt, batch, cfg, torch.Generator().manual_seed(0))
    assert metrics["losses/update_steps"] == 0 and metrics["losses/skipped_empty"] == 8
    assert all(torch.equal(a, b) for a, b in zip(before, policy.parameters()))


def test_episode_weights_equalise_episodes_and_combine_with_balance():
    episode = torch.tensor([0, 0, 0, 1])  # a 3-call episode and a 1-call episode
    w = episode_weights(episode)
    assert w[:3].sum().item() == pytest.approx(w[3].item()) and w.mean().item() == pytest.approx(1.0)
    y = torch.tensor([-1.0, -1, -1, 1])
    balanced = label_weights(y, base=w)
    assert balanced[y > 0].sum().item() == pytest.approx(balanced[y < 0].sum().item())


def first_minibatch_metrics(cfg: StepNFTConfig, record_all=False) -> dict:
    """The loss terms of the first minibatch (no step taken before it), on the same batch."""
    policy, batch = make_batch(noise_level=cfg.noise_level, record_all=record_all)
    with torch.no_grad():  # move the policy off v_old so Δ is not zero
        for p in policy.parameters():
            p.add_(0.01 * torch.randn(p.shape, generator=torch.Generator().manual_seed(p.numel())))
    opt = torch.optim.SGD(policy.parameters(), lr=0.0)
    return stepnft_update(policy, opt, batch, dataclasses.replace(cfg, update_epochs=1, minibatch_size=10_000))


BASE = StepNFTConfig(noise_level=0.3, label_balance="none", episode_weighting=False)


def test_ablation_switches_change_what_they_should():
    base = first_minibatch_metrics(BASE)
    assert base["losses/E_pos"] != base["losses/E_neg"]

    # β = 2 doubles the mirrored candidates' offset: E+ - E- is linear in β (docs/algorithm.md §4).
    beta2 = first_minibatch_metrics(dataclasses.replace(BASE, beta=2.0))
    assert beta2["losses/E_diff_signed"] == pytest.approx(2 * base["losses/E_diff_signed"], rel=1e-4)
    assert beta2["losses/delta_v_norm"] == pytest.approx(base["losses/delta_v_norm"])

    # x0 target: energies against the executed chunk instead of x_next (other values, same Δ).
    x0 = first_minibatch_metrics(dataclasses.replace(BASE, target="x0"))
    assert x0["losses/E_pos"] != pytest.approx(base["losses/E_pos"], rel=1e-3)
    assert x0["losses/delta_v_norm"] == pytest.approx(base["losses/delta_v_norm"])

    # Weighted MSE: the main term is r E+ + (1 - r) E- (≈ the energies, as the candidates are
    # close), not a softplus near ln 2.
    wmse = first_minibatch_metrics(dataclasses.replace(BASE, form="wmse"))
    assert wmse["losses/E_pos"] == pytest.approx(base["losses/E_pos"])
    assert base["losses/loss_main"] == pytest.approx(0.6931, abs=0.01)
    assert wmse["losses/loss_main"] == pytest.approx(0.5 * (base["losses/E_pos"] + base["losses/E_neg"]), rel=0.01)

    # ODE exploration (a = 0): the recorded step is deterministic, so the candidates tie.
    ode = first_minibatch_metrics(dataclasses.replace(BASE, noise_level=0.0))
    assert ode["losses/E_diff_signed"] == pytest.approx(0.0, abs=1e-3 * abs(base["losses/E_diff_signed"]))

    # Label balance: successes and failures then carry equal weight, so the loss changes.
    balanced = first_minibatch_metrics(dataclasses.replace(BASE, label_balance="global"))
    assert balanced["losses/loss_main"] != pytest.approx(base["losses/loss_main"], rel=1e-6)

    # Recording all K steps: K samples per call, same policy calls.
    every = first_minibatch_metrics(dataclasses.replace(BASE, record_steps="all"), record_all=True)
    assert every["losses/E_pos"] != base["losses/E_pos"]


def test_the_loss_sees_exactly_the_weighted_batch():
    """Cross-check: the update's first-minibatch loss equals stepnft_loss on the whole batch."""
    policy, batch = make_batch(n=32)
    cfg = dataclasses.replace(BASE, update_epochs=1, minibatch_size=32)
    y = batch.step_success.float() * 2 - 1
    v = policy.velocity(policy.processor(batch.obs), batch.x_t, batch.t)
    expected, _ = stepnft_loss(v, batch.v_old, batch.x_t, batch.x_next, batch.t, batch.dt, cfg.noise_level, y)
    metrics = stepnft_update(policy, torch.optim.SGD(policy.parameters(), lr=0.0), batch, cfg)
    assert metrics["losses/loss"] == pytest.approx(expected.item(), rel=1e-6)


def test_the_algorithm_owns_ema_optimizer_and_their_state():
    policy, batch = make_batch(n=64)
    algo = make_algorithm(StepNFTConfig(noise_level=0.3, lr=1e-2), policy, iterations=10,
                          generator=torch.Generator().manual_seed(0))
    assert isinstance(algo, StepNFT) and algo.acting_policy() is algo.ema and algo.eval_policy() is policy
    assert algo.ema.processor is policy.processor  # input processing is shared, not copied
    assert algo.rollout.noise_level == 0.3 and algo.rollout.record_steps == "all"
    algo.update(batch)
    assert algo.end_iteration(0) == {"charts/ema_decay": pytest.approx(0.1)}
    state = algo.state_dict()
    # the MLP shares no module with its EMA copy: its checkpoints keep the whole EMA state, as before
    assert state["ema"].keys() == algo.ema.state_dict().keys()
    other = make_algorithm(StepNFTConfig(noise_level=0.3, lr=1e-2), make_batch(n=64)[0], 10, torch.Generator())
    other.load_state_dict(state)
    assert all(torch.equal(a, b) for a, b in zip(other.ema.state_dict().values(), algo.ema.state_dict().values()))
    assert other.optimizer.state_dict()["state"].keys() == algo.optimizer.state_dict()["state"].keys()


def test_non_finite_steps_are_skipped_counted_and_stop_the_run_after_patience():
    from stepnft.algos.base import RunDiverged

    policy, batch = make_batch(n=64)
    batch.x_next[:5] = float("nan")  # a poisoned sample in every epoch's first minibatch or so
    cfg = StepNFTConfig(noise_level=0.3, minibatch_size=64, update_epochs=3, nonfinite_patience=10)
    opt = torch.optim.AdamW(policy.parameters(), lr=1e-3)
    before = [p.clone() for p in policy.parameters()]
    metrics = stepnft_update(policy, opt, batch, cfg, torch.Generator().manual_seed(0))
    assert metrics["losses/skipped_nonfinite"] == 3 and metrics["losses/update_steps"] == 0
    assert all(torch.equal(a, b) for a, b in zip(before, policy.parameters()))
    with pytest.raises(RunDiverged, match=r"not finite for 2 optimizer steps in a row.*algo.lr"):
        stepnft_update(policy, opt, batch, dataclasses.replace(cfg, nonfinite_patience=2))


def test_group_balance_compares_episodes_from_one_initial_state():
    from stepnft.algos.stepnft import episode_groups, sample_weights

    policy, batch = make_batch(n=8)
    batch.episode_seed[:] = torch.tensor([7, 7, 7, 7, 9, 9, 9, 9])
    batch.episode_task[:] = torch.tensor([0, 0, 0, 0, 0, 0, 1, 1])
    batch.episode_success[:] = torch.tensor([True, False, False, False, True, True, False, True])
    groups = episode_groups(batch)
    assert groups.tolist()[:4] == [groups[0].item()] * 4 and len(set(groups.tolist())) == 3
    y = batch.step_success.float() * 2 - 1
    w = sample_weights(batch, y, StepNFTConfig(label_balance="group", group_size=4, episode_weighting=False))
    # Group (task 0, seed 7): one success against three failures -> 2.0 and 2/3.
    torch.testing.assert_close(w[:4], torch.tensor([2.0, 2 / 3, 2 / 3, 2 / 3]))
    assert w[4:6].tolist() == [1.0, 1.0]  # a group with one outcome only keeps its weights
    assert StepNFT(policy, StepNFTConfig(group_size=4, label_balance="group"), 1, torch.Generator()).rollout.group_size == 4


def test_progress_labels_credit_the_calls_that_raised_the_reward():
    from tests.algos.test_policy_gradient import make_batch as make_episodes
    from stepnft.algos.stepnft import call_progress, step_labels

    # Two interleaved episodes of one task: ep 0 (calls 0, 2, 4) fails, ep 1 (calls 1, 3) succeeds.
    _, batch = make_episodes([0, 1, 0, 1, 0], success=[False, True])
    batch.mask[4, 1] = False  # the last call of ep 0 executed one env step of two
    batch.reward = torch.tensor([2.0, 0.0, 6.0, 4.0, 1.0])  # per-step levels: ep 0 1, 3, 1; ep 1 0, 2
    lam = 0.5
    # ep 0: G4 = 1, G2 = 0.5*3 + 0.5*1 = 2, G0 = 0.5*1 + 0.5*2 = 1.5 -> progress 1.5-1, 2-1, 1-3
    # ep 1: G3 = 2, G1 = 0.5*0 + 0.5*2 = 1 -> progress 1-0, 2-0
    torch.testing.assert_close(call_progress(batch, lam), torch.tensor([0.5, 1.0, 1.0, 2.0, -2.0]))

    episode_labels = step_labels(batch, StepNFTConfig())
    torch.testing.assert_close(episode_labels, (batch.step_success.float() * 2 - 1))
    y_call = step_labels(dataclasses.replace(batch, call=torch.arange(5)),
                         StepNFTConfig(labels="progress", progress_lambda=lam, progress_mix=0.5))
    p = torch.tensor([0.5, 1.0, 1.0, 2.0, -2.0])
    expected = 0.5 * torch.tensor([-1.0, 1, -1, 1, -1]) + 0.5 * torch.tanh(p / p.std(unbiased=False))
    torch.testing.assert_close(y_call, expected)
    # The failing episode's call that raised the reward is pushed away less than the one that lost it.
    assert y_call[2] > y_call[4] and y_call.abs().max() <= 1
    # A reward that never moves (sparse, or none) leaves the outcome labels as they are.
    flat = dataclasses.replace(batch, call=torch.arange(5), reward=torch.zeros(5))
    torch.testing.assert_close(step_labels(flat, StepNFTConfig(labels="progress")), torch.tensor([-1.0, 1, -1, 1, -1]))
    with pytest.raises(ValueError, match="algo.progress_mix"):
        StepNFTConfig(labels="progress", progress_mix=1.5)


def test_task_diagnostics_report_each_task_and_leave_the_update_unchanged():
    results = {}
    for diagnose in (False, True):
        policy, batch = make_batch(seed=3)
        cfg = StepNFTConfig(noise_level=0.3, lr=1e-3, update_epochs=2, minibatch_size=64, task_diagnostics=diagnose)
        opt = torch.optim.AdamW(policy.parameters(), lr=cfg.lr)
        metrics = stepnft_update(policy, opt, batch, cfg, torch.Generator().manual_seed(0))
        results[diagnose] = (metrics, [p.detach().clone() for p in policy.parameters()])
    (plain, before), (diagnosed, after) = results[False], results[True]
    for a, b in zip(before, after):  # no random draw, no gradient: the same update
        torch.testing.assert_close(a, b, rtol=0, atol=0)
    assert {k: v for k, v in diagnosed.items() if not k.startswith("per_task/")} == plain
    # One entry per task; the label share is what the batch holds (episode success, one call each).
    y = batch.episode_success.float() * 2 - 1
    for k in range(2):
        rows = batch.step_task == k
        task = {name.removeprefix("per_task/"): values[k] for name, values in diagnosed.items() if "per_task/" in name}
        assert task["labels/pos_frac"] == pytest.approx(float((y[batch.step_episode[rows]] > 0).float().mean()))
        assert 0 < task["labels/weight_share"] < 1
        assert task["losses/E_pos"] > 0 and task["losses/E_neg"] > 0 and task["losses/delta_v_norm"] > 0


def test_a_task_without_a_success_can_be_labelled_by_its_progress_alone():
    from tests.algos.test_policy_gradient import make_batch as make_episodes
    from stepnft.algos.stepnft import call_progress, step_labels

    _, batch = make_episodes([0, 1, 0, 1, 0], success=[False, False])  # one task, no success
    batch = dataclasses.replace(batch, call=torch.arange(5), reward=torch.tensor([2.0, 0.0, 6.0, 4.0, 1.0]))
    p = call_progress(batch, 0.8)
    mixed = step_labels(batch, StepNFTConfig(labels="progress"))
    assert bool((mixed <= 0).all())  # the mixed label: every call pushed away
    alone = step_labels(batch, StepNFTConfig(labels="progress", failed_task_labels="progress"))
    torch.testing.assert_close(alone, torch.tanh(p / p.std(unbiased=False)))
    assert bool((alone > 0).any()) and bool((alone < 0).any())  # the calls that made progress are pulled toward
    # A task with a success keeps the mixed label.
    _, won = make_episodes([0, 1, 0, 1, 0], success=[False, True])
    won = dataclasses.replace(won, call=torch.arange(5), reward=batch.reward)
    torch.testing.assert_close(step_labels(won, StepNFTConfig(labels="progress", failed_task_labels="progress")),
                               step_labels(won, StepNFTConfig(labels="progress")))
