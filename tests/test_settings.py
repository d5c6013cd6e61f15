"""Every setting is declared once and checked from its declaration (``stepnft.settings``): one
checker for every config section, the same message whether a value came from Python, YAML or
flags, and every config file in configs/ valid."""

import dataclasses
import math
import re
import typing
from pathlib import Path

import pytest

from stepnft.algos.base import ALGORITHMS, AlgoConfig, config_class
from stepnft.algos.grpo import GRPOConfig
from stepnft.algos.ppo import PPOConfig
from stepnft.algos.sft import SFTConfig
from stepnft.algos.stepnft import StepNFTConfig
from stepnft.cli import CONFIG_SECTIONS
from stepnft.config import (DemoConfig, DemosCommand, EnvConfig, EvalCommand, EvalConfig, RayConfig, TrainConfig,
                            load_config, read_yaml)
from stepnft.policies.flow import FlowPolicyConfig
from stepnft.settings import SETTINGS_FILE_BYTES_MAX, Range, SettingError, Settings, check_fields, describe

BAD_VALUES = [
    # (config class, field, bad value, expected message)
    (TrainConfig, "seed", -1, "seed must be an integer in [0, 2147483647], got -1"),
    (TrainConfig, "iterations", 2.5, "iterations must be an integer in [0, 100000000], got 2.5"),
    (TrainConfig, "iterations", True, "iterations must be an integer in [0, 100000000], got True"),
    (TrainConfig, "allocation_floor", math.inf, "allocation_floor must be a finite number in [0, 1], got inf"),
    (TrainConfig, "task_allocation", "fair", "task_allocation must be one of equal, informative, got 'fair'"),
    (TrainConfig, "device", "gpu", "device must be cpu, cuda or cuda:N, got 'gpu'"),
    (TrainConfig, "env_step_budget", 0, "env_step_budget must be an integer in [1, 1000000000000] or None, got 0"),
    (EnvConfig, "envs_per_task", 0, "env.envs_per_task must be an integer in [1, 4096], got 0"),
    (EnvConfig, "image_size", 4, "env.image_size must be an integer in [8, 480], got 4"),
    (EnvConfig, "state_obs", "pixels", "env.state_obs must be one of full, proprio, interest, got 'pixels'"),
    (EnvConfig, "reward", "dense", "env.reward must be one of native, shaped, got 'dense'"),
    (EnvConfig, "terminate_on_success", 1, "env.terminate_on_success must be true or false, got 1"),
    (EnvConfig, "tasks", 5, "env.tasks must be a list of names, got 5"),
    (DemoConfig, "action_noise", math.nan, "demos.action_noise must be a finite number in [0, 10], got nan"),
    (DemoConfig, "task_episodes", {"reach-v3": 0}, "demos.task_episodes must be a mapping of names to values, each "
                                                   "an integer in [1, 1048576], got {'reach-v3': 0}"),
    (EvalConfig, "during_episodes", 0, "eval.during_episodes must be an integer in [1, 16777216], got 0"),
    (RayConfig, "timeout_s", -1.0, "ray.timeout_s must be a finite number in (0, 604800], got -1.0"),
    (RayConfig, "timeout_s", math.inf, "ray.timeout_s must be a finite number in (0, 604800], got inf"),
    (SFTConfig, "lr", math.inf, "sft.lr must be a finite number in (0, 1], got inf"),
    (SFTConfig, "weight_decay", -1e-4, "sft.weight_decay must be a finite number in [0, 1], got -0.0001"),
    (SFTConfig, "steps", 1.0, "sft.steps must be an integer in [0, 100000000], got 1.0"),
    (SFTConfig, "time_law", "normal", "sft.time_law must be one of uniform, beta, got 'normal'"),
    (SFTConfig, "adam_betas", (0.9, 1.0), "sft.adam_betas must be 2 values, each a finite number in [0, 1), got (0.9, 1.0)"),
    (FlowPolicyConfig, "n_exec", 2.5, "policy.n_exec must be an integer in [1, 1024], got 2.5"),
    (FlowPolicyConfig, "num_inference_steps", 0, "policy.num_inference_steps must be an integer in [1, 1000], got 0"),
    (FlowPolicyConfig, "state_clip", "5", "policy.state_clip must be a finite number in (0, 1000000], got '5'"),
    (StepNFTConfig, "lr", 0.0, "algo.lr must be a finite number in (0, 1], got 0.0"),
    (StepNFTConfig, "noise_level", math.inf, "algo.noise_level must be a finite number in [0, 10], got inf"),
    (StepNFTConfig, "max_drift", -0.5, "algo.max_drift must be a finite number in (0, 1000000] or None, got -0.5"),
    (StepNFTConfig, "label_balance", "yes", "algo.label_balance must be one of none, global, task, group, got 'yes'"),
    (StepNFTConfig, "update_epochs", False, "algo.update_epochs must be an integer in [1, 1000], got False"),
    (PPOConfig, "noise_level", math.inf, "algo.noise_level must be a finite number in [0, 10], got inf"),
    (PPOConfig, "critic_lr", math.inf, "algo.critic_lr must be a finite number in (0, 1], got inf"),
    (PPOConfig, "clip_coef", math.inf, "algo.clip_coef must be a finite number in (0, 10], got inf"),
    (PPOConfig, "gamma", -0.1, "algo.gamma must be a finite number in [0, 1], got -0.1"),
    (PPOConfig, "critic_hidden_dim", 0, "algo.critic_hidden_dim must be an integer in [1, 16384], got 0"),
    (PPOConfig, "sde_steps", "two", "algo.sde_steps must be one of all, one, got 'two'"),
    (GRPOConfig, "target_kl", math.nan, "algo.target_kl must be a finite number in (0, 100] or None, got nan"),
    (GRPOConfig, "minibatch_size", 0, "algo.minibatch_size must be an integer in [1, 1048576], got 0"),
    (EvalCommand, "video_episodes", 0, "video_episodes must be an integer in [1, 1000], got 0"),
    (EvalCommand, "suite", [1], "suite must be a list of names, got [1]"),
]


@pytest.mark.parametrize("cls, key, value, expected", BAD_VALUES,
                         ids=[f"{c.__name__}.{k}={v!r}" for c, k, v, _ in BAD_VALUES])
def test_every_bad_value_is_a_value_error_naming_its_setting(cls, key, value, expected):
    with pytest.raises(ValueError) as caught:
        cls(**{key: value})
    assert str(caught.value) == expected
    assert isinstance(caught.value, SettingError)
    flag = "--" + expected.split(" ")[0].replace("_", "-")
    assert caught.value.as_flags().startswith(flag + " must be ")


@pytest.mark.parametrize("cls, kwargs, expected", [
    (StepNFTConfig, {"sde_steps": "one"}, "algo.sde_steps=one needs algo.record_steps=one"),
    (StepNFTConfig, {"label_balance": "group"}, "algo.label_balance=group needs algo.group_size >= 2, got 1"),
    (GRPOConfig, {"group_size": 1}, "algo.group_size must be >= 2 for GRPO"),
    (PPOConfig, {"noise_level": 0.0}, "algo.noise_level must be > 0 for PPO and GRPO"),
    (StepNFTConfig, {"name": "ppo"}, "algo.name must be stepnft for StepNFTConfig, got 'ppo'"),
    (EvalConfig, {"validation_seed": 50}, "eval.validation_seed (50) must be >= eval.seed + eval.episodes (100)"),
    (EnvConfig, {"max_episode_steps": 501}, "env.max_episode_steps must be in [1, 500] for metaworld, got 501"),
    (EnvConfig, {"name": "gazebo"}, "env.name must be one of metaworld, bandit, libero, maniskill, gym, got 'gazebo'"),
    (EnvConfig, {"randomize": ["lighting"]}, "env.randomize vision perturbations change only camera images"),
    (EnvConfig, {"name": "bandit", "tasks": ["bandit"], "max_episode_steps": 8, "reward": "shaped"},
     "env.reward shaped: bandit's reward is success only and it has no shaped option; use native, got 'shaped'"),
    (DemoConfig, {"max_attempts": 3, "task_episodes": {"push-v3": 4}}, "demos.max_attempts must be >= the "
                                                                       "demonstrations wanted (5), got 3"),
    (FlowPolicyConfig, {"n_exec": 5}, "policy.n_exec (5) must be <= policy.horizon (4)"),
    (TrainConfig, {"policy": FlowPolicyConfig(cameras=["corner"])}, "policy.cameras ['corner'] differ from env.cameras"),
])
def test_rules_between_fields_name_every_setting_involved(cls, kwargs, expected):
    with pytest.raises(SettingError, match="^" + re.escape(expected)):
        cls(**kwargs)


def test_values_are_normalised_to_their_declared_types():
    cfg = StepNFTConfig(lr=1, adam_betas=[0.5, 0.9], max_drift=None)
    assert type(cfg.lr) is float and cfg.adam_betas == (0.5, 0.9) and cfg.max_drift is None
    env = EnvConfig(tasks="reach-v3, push-v3", cameras=["corner,topview"], randomize="execution")
    assert env.tasks == ["reach-v3", "push-v3"] and env.cameras == ["corner", "topview"]
    assert env.randomize == ["object_position", "action_noise", "friction", "mass"]
    assert FlowPolicyConfig(cameras="corner").cameras == ["corner"]


def test_descriptions_and_flag_names():
    assert str(Range(gt=0)) == "> 0" and str(Range(ge=0, lt=1)) == "in [0, 1)" and str(Range(le=10)) == "<= 10"
    assert describe(typing.Annotated[float | None, Range(gt=0, le=2)]) == "a finite number in (0, 2] or None"
    err = SettingError("{sde_steps}=one needs {record_steps}=one", "algo")
    assert str(err) == "algo.sde_steps=one needs algo.record_steps=one"
    assert err.as_flags() == "--algo.sde-steps=one needs --algo.record-steps=one"
    assert SettingError("{env_step_budget} must be >= 1", got=0).as_flags() == "--env-step-budget must be >= 1, got 0"


def settings_classes() -> list[type]:
    """Every config class a run or a command builds."""
    return [TrainConfig, EnvConfig, DemoConfig, EvalConfig, RayConfig, SFTConfig, FlowPolicyConfig, DemosCommand,
            EvalCommand, *(config_class(name) for name in ALGORITHMS)]


@pytest.mark.parametrize("cls", settings_classes(), ids=lambda c: c.__name__)
def test_every_config_class_is_checked_and_its_defaults_are_valid(cls):
    assert issubclass(cls, Settings)
    cfg = cls()
    check_fields(cfg)  # every declared type is one the checker knows
    hints = typing.get_type_hints(cls, include_extras=True)
    for f in dataclasses.fields(cls):
        if typing.get_origin(hints[f.name]) is not typing.Annotated and hints[f.name] in (int, float):
            pytest.fail(f"{cls.__name__}.{f.name} declares no range")


def test_sections_are_named_where_train_config_holds_them():
    sections = {f.name: type(getattr(TrainConfig(), f.name)) for f in dataclasses.fields(TrainConfig)
                if dataclasses.is_dataclass(getattr(TrainConfig(), f.name))}
    assert tuple(sections) == CONFIG_SECTIONS
    for name, cls in sections.items():
        assert cls.section == name
    assert all(config_class(name).section == "algo" for name in ALGORITHMS)


def test_shared_algorithm_settings_are_declared_once():
    """noise_level, sde_steps and group_size are AlgoConfig's fields: an algorithm sets only its
    defaults (``defaults``), keeping the declared type, range and metadata."""
    base = {f.name: f for f in dataclasses.fields(AlgoConfig)}
    base_hints = typing.get_type_hints(AlgoConfig, include_extras=True)
    for name in ALGORITHMS:
        cls = config_class(name)
        hints = typing.get_type_hints(cls, include_extras=True)
        for key, f in base.items():
            own = {g.name: g for g in dataclasses.fields(cls)}[key]
            assert hints[key] == base_hints[key] and own.metadata == f.metadata, (name, key)
        own_fields = [k for k in cls.__dict__.get("__annotations__", {}) if k in base and k not in cls.defaults]
        assert own_fields == [], f"{cls.__name__} declares {own_fields} again"
    assert (StepNFTConfig().noise_level, PPOConfig().noise_level, GRPOConfig().noise_level) == (0.2, 0.5, 0.5)
    assert (StepNFTConfig().group_size, PPOConfig().group_size, GRPOConfig().group_size) == (1, 1, 4)
    assert [config_class(n)().name for n in ALGORITHMS] == list(ALGORITHMS)


@pytest.mark.parametrize("path", sorted(Path("configs").glob("*.yaml")), ids=lambda p: p.name)
def test_every_config_file_loads(path):
    cfg = load_config(path)
    assert isinstance(cfg, TrainConfig)


def test_a_shaped_reward_is_asked_of_the_simulator_only_where_its_own_is_sparse():
    from stepnft.envs import env_options

    assert "reward" not in env_options(EnvConfig(reward="shaped"))  # MetaWorld's own reward is shaped
    assert env_options(EnvConfig(name="libero", tasks=["libero_object"], reward="shaped"))["reward"] == "shaped"
    assert "reward" not in env_options(EnvConfig(name="libero", tasks=["libero_object"]))


def _numbers(hint) -> list[tuple[type, list[Range]]]:
    """``(int or float, its ranges)`` of every number a declared type holds (inside ``X | None``,
    lists, tuples and mappings too)."""
    ranges = []
    if typing.get_origin(hint) is typing.Annotated:
        ranges = [r for r in hint.__metadata__ if isinstance(r, Range)]
        hint = hint.__origin__
    if hint in (int, float):
        return [(hint, ranges)]
    found = []
    for arg in typing.get_args(hint):
        found += [(t, ranges + inner) for t, inner in _numbers(arg)]
    return found


def every_settings_class() -> list[type]:
    """Every subclass of Settings in stepnft's modules (LeRobot's when it is installed)."""
    import importlib
    import pkgutil

    import stepnft

    for module in pkgutil.walk_packages(stepnft.__path__, "stepnft."):
        try:
            importlib.import_module(module.name)
        except ImportError:  # an optional extra (LeRobot, LIBERO) that is not installed here
            pass

    def below(cls):
        for sub in cls.__subclasses__():
            yield sub
            yield from below(sub)

    return sorted({c for c in below(Settings) if dataclasses.is_dataclass(c)}, key=lambda c: c.__qualname__)


def test_every_number_of_every_settings_class_has_an_upper_bound():
    classes = every_settings_class()
    missing = []
    for cls in classes:
        hints = typing.get_type_hints(cls, include_extras=True)
        for f in dataclasses.fields(cls):
            for number, ranges in _numbers(hints[f.name]):
                if not any(r.le is not None or r.lt is not None for r in ranges):
                    missing.append(f"{cls.__module__}.{cls.__qualname__}.{f.name} ({number.__name__})")
    assert len(classes) >= 12 and not missing, "numbers without an upper bound:\n" + "\n".join(missing)


def test_huge_numbers_are_refused_by_their_bound_naming_the_setting():
    with pytest.raises(SettingError, match=r"^seed must be an integer in \[0, 2147483647\], got 1180591620717411303424$"):
        TrainConfig(seed=2**70)
    with pytest.raises(SettingError, match=r"^eval.episodes must be an integer in \[0, 16777216\], got 3000000000$"):
        EvalConfig(episodes=3_000_000_000)
    with pytest.raises(SettingError, match=r"^algo.lr must be a finite number in \(0, 1\], got 1e\+308$"):
        StepNFTConfig(lr=1e308)
    # Evaluation states stay below the training episodes' reset seeds.
    with pytest.raises(SettingError, match=r"eval.seed \+ eval.episodes .* at most 16777216"):
        EvalConfig(seed=16_777_000, episodes=1000, validation_seed=16_777_100)
    assert str(Range(ge=0, le=2**31 - 1)) == "in [0, 2147483647]" and str(Range(gt=0, le=1e-6)) == "in (0, 1e-06]"


def billion_laughs(levels: int = 9) -> str:
    """A YAML document of a few hundred bytes that stands for 9**levels strings."""
    rows = ["l0: &l0 [lol, lol, lol, lol, lol, lol, lol, lol, lol]"]
    rows += [f"l{i}: &l{i} [{', '.join([f'*l{i - 1}'] * 9)}]" for i in range(1, levels + 1)]
    return "\n".join(rows) + "\nenv:\n  tasks: *l%d\n" % levels


@pytest.mark.parametrize("text, message", [
    (billion_laughs(), "expands to more than 100000 values"),
    ("env: &a {tasks: *a}\n", "expands to more than 100000 values"),  # an alias inside its own anchor
    ("env: " + "[" * 50_000 + "]" * 50_000 + "\n", "nests too deeply"),
], ids=["billion-laughs", "recursive-alias", "deep"])
def test_yaml_that_expands_or_nests_without_bound_is_refused_in_one_line(tmp_path, text, message):
    path = tmp_path / "bad.yaml"
    path.write_text(text)
    with pytest.raises(ValueError) as caught:
        load_config(path)
    assert str(caught.value).startswith(f"config file {path} {message}") and "\n" not in str(caught.value)


def test_yaml_anchors_within_the_bound_still_load(tmp_path):
    path = tmp_path / "anchors.yaml"
    path.write_text("shared: &tasks [reach-v3, push-v3]\n".replace("shared: ", "env:\n  tasks: "))
    assert load_config(path).env.tasks == ["reach-v3", "push-v3"]
    assert read_yaml(billion_laughs(3)) is not None  # 9**3 = 729 values, used twice: under the bound


def test_a_settings_file_over_its_size_cap_is_refused_before_it_is_read(tmp_path, monkeypatch):
    path = tmp_path / "huge.yaml"
    path.write_text("seed: 1\n" + "#" * SETTINGS_FILE_BYTES_MAX)
    monkeypatch.setattr(Path, "read_text", lambda *a, **k: pytest.fail("read a file over the cap"))
    with pytest.raises(ValueError, match=rf"huge.yaml is {SETTINGS_FILE_BYTES_MAX + 8} bytes: settings files are at most"):
        load_config(path)
