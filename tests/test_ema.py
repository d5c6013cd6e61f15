import pytest
import torch
from torch import nn

from stepnft.ema import ema_decay, ema_update, make_ema_copy


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
