import pytest
import torch
from torch import nn

from stepnft.ema import ema_decay, ema_state_dict, ema_update, load_ema_state_dict, make_ema_copy, shared_state_names


def test_schedule_endpoints_and_monotone():
    assert ema_decay(0, 100) == pytest.approx(0.1)
    assert ema_decay(100, 100) == pytest.approx(0.995)
    assert ema_decay(500, 100) == pytest.approx(0.995)
    assert ema_decay(50, 100) == pytest.approx((0.1 + 0.995) / 2)
    values = [ema_decay(i, 100) for i in range(101)]
    assert all(b >= a for a, b in zip(values, values[1:]))


class WithBackbone(nn.Module):
    def __init__(self):
        super().__init__()
        self.backbone = nn.Linear(3, 3)
        self.backbone.requires_grad_(False)
        self.head = nn.Linear(3, 2)
        self.register_buffer("stat", torch.zeros(2))


def test_update_rule_and_frozen_modules_shared():
    model = WithBackbone()
    ema = make_ema_copy(model)
    assert ema.backbone is model.backbone
    assert ema.head is not model.head and not any(p.requires_grad for p in ema.head.parameters())
    old = ema.head.weight.clone()
    with torch.no_grad():
        model.head.weight.add_(1.0)
        model.stat.fill_(7.0)
    ema_update(ema, model, decay=0.25)
    torch.testing.assert_close(ema.head.weight, 0.25 * old + 0.75 * model.head.weight)
    assert torch.all(ema.stat == 7.0)
    ema_update(ema, model, decay=1.0)
    torch.testing.assert_close(ema.head.weight, 0.25 * old + 0.75 * model.head.weight)


def test_the_ema_state_leaves_out_the_shared_frozen_modules_and_restores_exactly():
    model = WithBackbone()
    ema = make_ema_copy(model)
    with torch.no_grad():
        model.head.weight.add_(1.0)
        model.stat.fill_(3.0)
    ema_update(ema, model, decay=0.5)
    assert shared_state_names(ema, model) == {"backbone.weight", "backbone.bias"}
    state = ema_state_dict(ema, model)
    assert state.keys() == {"head.weight", "head.bias", "stat"}  # the backbone is saved with the model
    again = make_ema_copy(model)
    load_ema_state_dict(again, model, state)
    assert again.backbone is model.backbone
    assert all(torch.equal(a, b) for a, b in zip(again.state_dict().values(), ema.state_dict().values()))
    # a whole state dict, as checkpoints held before, loads the same
    whole = make_ema_copy(model)
    load_ema_state_dict(whole, model, ema.state_dict())
    assert all(torch.equal(a, b) for a, b in zip(whole.state_dict().values(), ema.state_dict().values()))
    with pytest.raises(ValueError, match="1 entries missing \\(head.bias\\)"):
        load_ema_state_dict(make_ema_copy(model), model, {k: v for k, v in state.items() if k != "head.bias"})
