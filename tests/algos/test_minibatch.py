"""The minibatch loop every algorithm runs (``MinibatchEpochs``): its order of minibatches, the
early stop looked at before stepping, the guard, and what it averages over."""

import math

import pytest
import torch

from stepnft.algos.base import MinibatchEpochs, NonFiniteGuard, RunDiverged
from stepnft.algos.stepnft import StepNFTConfig


def test_minibatches_are_the_randperm_of_each_pass_split():
    cfg = StepNFTConfig(update_epochs=3, minibatch_size=4)
    got = list(MinibatchEpochs(cfg, NonFiniteGuard(cfg)).minibatches(10, torch.Generator().manual_seed(7)))
    g = torch.Generator().manual_seed(7)
    expected = [idx for _ in range(3) for idx in torch.randperm(10, generator=g).split(4)]
    assert [len(i) for i in got] == [4, 4, 2] * 3
    assert all(torch.equal(a, b) for a, b in zip(got, expected))


def test_minibatches_of_samples_holding_several_steps_hold_minibatch_size_steps():
    """PPO's and GRPO's samples are policy calls of K recorded steps: minibatch_size // K of them
    (at least one), from the same random order."""
    cfg = StepNFTConfig(update_epochs=2, minibatch_size=8)
    epochs = MinibatchEpochs(cfg, NonFiniteGuard(cfg))
    got = list(epochs.minibatches(10, torch.Generator().manual_seed(7), steps_per_sample=4))
    g = torch.Generator().manual_seed(7)
    expected = [idx for _ in range(2) for idx in torch.randperm(10, generator=g).split(2)]
    assert [len(i) for i in got] == [2] * 10 and all(torch.equal(a, b) for a, b in zip(got, expected))
    assert [len(i) for i in epochs.minibatches(3, None, steps_per_sample=16)] == [1, 1, 1] * 2


def test_a_stop_ends_every_pass_and_draws_no_later_order():
    cfg = StepNFTConfig(update_epochs=5, minibatch_size=5)
    gen = torch.Generator().manual_seed(0)
    epochs = MinibatchEpochs(cfg, NonFiniteGuard(cfg))
    seen = 0
    for _ in epochs.minibatches(10, gen):
        seen += 1
        if epochs.stop_if(seen == 3):  # the first minibatch of the second pass
            break
    assert seen == 3 and epochs.counts("drift_stopped")["losses/drift_stopped"] == 1.0
    reference = torch.Generator().manual_seed(0)
    torch.randperm(10, generator=reference)
    torch.randperm(10, generator=reference)
    assert torch.equal(gen.get_state(), reference.get_state())  # two passes drawn, not five


def test_averages_counts_and_the_guard():
    cfg = StepNFTConfig(update_epochs=1, minibatch_size=1, nonfinite_patience=2, grad_clip=100.0)
    param = torch.nn.Parameter(torch.zeros(2))
    optimizer = torch.optim.SGD([param], lr=0.1)
    epochs = MinibatchEpochs(cfg, NonFiniteGuard(cfg))
    epochs.skip()
    for target in (1.0, 3.0, math.inf):
        loss = (param - target).pow(2).sum()
        if math.isfinite(loss.item()):
            epochs.measure({"loss": loss.item()})
        if epochs.step(loss, [param], optimizer) is not None:  # the guard skips the infinite loss
            epochs.measure_step({"value_loss": target})
    # Steps: loss 2 (param 0 -> 0.2, gradient norm sqrt(8)); loss 2 * 2.8^2 (gradient norm 2.8 sqrt(8)).
    means = epochs.means()
    assert means["loss"] == pytest.approx((2.0 + 2 * 2.8**2) / 2)  # over measured minibatches
    assert means["value_loss"] == 2.0 and means["grad_norm"] == pytest.approx(3.8 * math.sqrt(8) / 2)  # over steps
    assert list(means) == ["loss", "grad_norm", "value_loss"]
    assert epochs.counts("kl_stopped") == {"losses/update_steps": 2.0, "losses/kl_stopped": 0.0,
                                           "losses/skipped_empty": 1.0, "losses/skipped_nonfinite": 1.0}
    before = param.detach().clone()
    with pytest.raises(RunDiverged):  # a second non-finite step in a row reaches the patience of 2
        epochs.step(param.sum() * math.nan, [param], optimizer)
    assert torch.equal(param.detach(), before)


def test_nothing_measured_gives_no_step_metrics():
    cfg = StepNFTConfig()
    epochs = MinibatchEpochs(cfg, NonFiniteGuard(cfg))
    assert epochs.means() == {} and epochs.counts("x")["losses/update_steps"] == 0.0
