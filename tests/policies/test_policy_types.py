"""``policy.type`` picks the policy config (stepnft.policies.configuration), as ``algo.name``
picks the algorithm's: a registered type builds from scratch with its own ``--policy.*``
settings, round-trips through config.yaml, and a type that cannot be built is one line."""

import dataclasses
from dataclasses import dataclass
from typing import Annotated, ClassVar

import pytest

from stepnft.cli import UsageError, _config_from_argv
from stepnft.config import TrainConfig, from_dict, load_config, save_config, to_dict
from stepnft.policies.base import POLICY_TYPES, make_policy, policy_config_class
from stepnft.policies.configuration import PolicyConfig
from stepnft.policies.flow import FlowPolicy, FlowPolicyConfig
from stepnft.settings import Range


@dataclass
class WideConfig(FlowPolicyConfig):
    """The flow MLP with a residual switch (a new setting of a new type)."""

    type: ClassVar[str] = "wide"
    residual: bool = False
    """Whether hidden layers add their input (unused by the test policy: a setting to carry)."""
    extra_layers: Annotated[int, Range(ge=0, le=8)] = 1
    """Hidden layers added to num_layers."""


class WidePolicy(FlowPolicy):
    type = "wide"
    config_class = WideConfig

    def __init__(self, config: WideConfig):
        super().__init__(dataclasses.replace(config, num_layers=config.num_layers + config.extra_layers))
        self.config = config


@dataclass
class NoSizes(PolicyConfig):
    type: ClassVar[str] = "nosizes"
    width: Annotated[int, Range(ge=1, le=64)] = 3


@dataclass
class Mislabelled(FlowPolicyConfig):
    residual: bool = False  # type left at "flow"


class NoSizesPolicy(FlowPolicy):
    type, config_class = "nosizes", NoSizes


class MislabelledPolicy(FlowPolicy):
    type, config_class = "mislabelled", Mislabelled


@pytest.fixture
def types(monkeypatch):
    for name, cls in (("wide", WidePolicy), ("nosizes", NoSizesPolicy), ("mislabelled", MislabelledPolicy)):
        monkeypatch.setitem(POLICY_TYPES, name, f"{__name__}:{cls.__name__}")


def test_policy_type_picks_the_config_class_and_round_trips_through_yaml(types, tmp_path):
    cfg = from_dict(TrainConfig, {"policy": {"type": "wide", "residual": True, "hidden_dim": 32}})
    assert type(cfg.policy) is WideConfig and cfg.policy.residual and cfg.policy.hidden_dim == 32
    assert to_dict(cfg)["policy"]["type"] == "wide"
    save_config(cfg, tmp_path / "c.yaml")
    assert load_config(tmp_path / "c.yaml") == cfg
    policy = make_policy(cfg.policy)
    assert isinstance(policy, WidePolicy) and len(policy.config.__dict__) > 0
    # A flow section writes no type: configs and checkpoints of earlier runs read the same.
    assert "type" not in to_dict(TrainConfig())["policy"]


def test_policy_type_flag_gives_that_types_defaults_and_flags(types):
    cfg, _ = _config_from_argv(["--policy.type", "wide", "--policy.extra-layers", "3"], "stepnft train", True)
    assert type(cfg.policy) is WideConfig and cfg.policy.extra_layers == 3 and not cfg.policy.residual
    cfg, _ = _config_from_argv(["--policy.type=flow", "--policy.hidden-dim", "8"], "stepnft train", True)
    assert type(cfg.policy) is FlowPolicyConfig and cfg.policy.hidden_dim == 8
    with pytest.raises(UsageError, match="extra-layers"):  # the flow type has no such setting
        _config_from_argv(["--policy.extra-layers", "3"], "stepnft train", True)
    with pytest.raises(UsageError, match=r"--policy.extra-layers must be an integer in \[0, 8\], got 9"):
        _config_from_argv(["--policy.type", "wide", "--policy.extra-layers", "9"], "stepnft train", True)


@pytest.mark.parametrize("type_name, message", [
    ("nope", "unknown policy type 'nope'; known: flow"),
    ("nosizes", "its config NoSizes lacks state_dim, action_dim, horizon, n_exec, which a run reads"),
    ("mislabelled", "its config Mislabelled says type 'flow': declare `type: ClassVar[str] = 'mislabelled'`"),
])
def test_a_policy_type_that_cannot_be_built_is_one_line(types, type_name, message):
    with pytest.raises(ValueError, match="policy.type: .*" + message.replace("(", r"\(").replace("[", r"\[")):
        from_dict(TrainConfig, {"policy": {"type": type_name}})
    with pytest.raises(UsageError) as err:
        _config_from_argv(["--policy.type", type_name], "stepnft train", True)
    assert message in str(err.value) and "\n" not in str(err.value)


def test_the_builtin_types_say_which_build_from_settings():
    assert policy_config_class("flow") is FlowPolicyConfig
    for name in ("smolvla", "pi0", "pi05"):  # LeRobot VLAs enter a run as a folder (--init)
        with pytest.raises(ValueError, match=f"policy type '{name}'"):
            policy_config_class(name)


def test_resume_refuses_another_policy_type(types, tmp_path):
    run = tmp_path / "run"
    run.mkdir()
    save_config(from_dict(TrainConfig, {"policy": {"type": "wide"}, "run_dir": str(run)}), run / "config.yaml")
    cfg, resumed = _config_from_argv(["--resume", str(run)], "stepnft train", True)
    assert resumed and type(cfg.policy) is WideConfig
    with pytest.raises(UsageError, match="drop: --policy.type"):
        _config_from_argv(["--resume", str(run), "--policy.type", "flow"], "stepnft train", True)
