"""The run configuration: typed dataclasses, saved and loaded as YAML.

One schema serves ``stepnft sft``, ``train`` and ``eval``; a run directory's ``config.yaml``
reproduces the run (``stepnft train --config RUN/config.yaml``). CLI flags override YAML.
"""

from __future__ import annotations

import dataclasses
import types
import typing
from dataclasses import dataclass, field
from pathlib import Path

import yaml

from stepnft.algos.sft import SFTConfig
from stepnft.envs import DEFAULT_TASKS
from stepnft.algos.stepnft import StepNFTConfig
from stepnft.policies.flow import FlowPolicyConfig



@dataclass
class EnvConfig:
    """Which MetaWorld v3 tasks run, and how."""

    tasks: list[str] = field(default_factory=lambda: list(DEFAULT_TASKS))
    """MetaWorld v3 task names; one multi-task policy serves all of them."""
    envs_per_task: int = 4
    """Parallel simulator instances per task (each plays one episode per rollout wave)."""
    max_episode_steps: int = 200
    """Episode cap in env steps (MetaWorld allows at most 500)."""
    terminate_on_success: bool = True
    """End an episode at its first success (the episode then counts as a success)."""
    num_workers: int = 0
    """Simulator processes stepping at once (0: all sub-envs in this process; 2 uses both
    cores of a 2-core machine, one process per sub-env)."""

    def __post_init__(self) -> None:
        if isinstance(self.tasks, str):
            self.tasks = [t.strip() for t in self.tasks.split(",") if t.strip()]
        if self.envs_per_task < 1:
            raise ValueError(f"env.envs_per_task must be >= 1, got {self.envs_per_task}")
        if not 1 <= self.max_episode_steps <= 500:
            raise ValueError(f"env.max_episode_steps must be in 1..500, got {self.max_episode_steps}")


@dataclass
class DemoConfig:
    """Few-shot demonstrations from MetaWorld's scripted experts."""

    path: str = "demos/default"
    """Folder of demonstrations (generated there if missing)."""
    episodes: int = 5
    """Demonstrations per task (few-shot)."""
    task_episodes: dict[str, int] = field(default_factory=dict)
    """Per-task overrides of ``episodes`` (e.g. fewer on tasks SFT already saturates)."""
    action_noise: float = 0.0
    """Std of Gaussian noise added to the expert's actions."""
    seed: int = 0
    """Seed of the demonstrations' initial states (disjoint from evaluation states)."""

    def __post_init__(self) -> None:
        if self.episodes < 1 or any(n < 1 for n in self.task_episodes.values()):
            raise ValueError(f"demos.episodes and demos.task_episodes must be >= 1, got {self.episodes}, {self.task_episodes}")

    def count(self, task: str) -> int:
        """Demonstrations used for ``task``."""
        return self.task_episodes.get(task, self.episodes)


@dataclass
class EvalConfig:
    """Deterministic (ODE) evaluation on a fixed, seeded set of initial states."""

    episodes: int = 100
    """Episodes per task for the before/after figures (>= 100 for reported numbers)."""
    seed: int = 0
    """Episode e of a task starts from initial state ``seed + e``: the same for every checkpoint."""
    every: int = 10
    """Iterations between evaluations during training (0: only before and after)."""
    during_episodes: int = 20
    """Episodes per task for the evaluations during training (cheap, noisier)."""
    use_ema: bool = False
    """Evaluate the EMA rollout policy instead of the trained one."""


@dataclass
class TrainConfig:
    """A π-StepNFT run on MetaWorld: demonstrations -> few-shot SFT -> online RL -> evaluation."""

    run_dir: str = "runs/stepnft"
    """Output folder: config.yaml, metrics.jsonl, TensorBoard logs, checkpoints, curves, summary."""
    seed: int = 0
    """Seeds every source of randomness (torch, sampler noise, simulator)."""
    iterations: int = 60
    """RL iterations: collect rollouts -> update epochs -> EMA update."""
    episodes_per_iteration: int = 20
    """Episodes collected per iteration (rounded up to a multiple of the number of envs)."""
    env_step_budget: int | None = None
    """Stop once this many rollout env steps were spent (None: run all iterations); the
    same budget for every algorithm makes comparisons fair."""
    init: str | None = None
    """SFT policy folder to start from; None: run few-shot SFT on the demonstrations first."""
    language_encoder: str = "default"
    """Frozen sentence encoder: 'default' (packaged all-MiniLM-L6-v2) or a local folder."""
    checkpoint_every: int = 10
    """Iterations between checkpoints (the last one is always written)."""
    num_threads: int = 1
    """torch CPU threads (the policy is small: one thread is fastest, and leaves a core to the simulator)."""
    env: EnvConfig = field(default_factory=EnvConfig)
    demos: DemoConfig = field(default_factory=DemoConfig)
    policy: FlowPolicyConfig = field(default_factory=FlowPolicyConfig)
    sft: SFTConfig = field(default_factory=SFTConfig)
    algo: StepNFTConfig = field(default_factory=StepNFTConfig)
    eval: EvalConfig = field(default_factory=EvalConfig)

    def __post_init__(self) -> None:
        if self.iterations < 0:
            raise ValueError(f"iterations must be >= 0, got {self.iterations}")
        if self.episodes_per_iteration < 1:
            raise ValueError(f"episodes_per_iteration must be >= 1, got {self.episodes_per_iteration}")
        if self.checkpoint_every < 1:
            raise ValueError(f"checkpoint_every must be >= 1, got {self.checkpoint_every}")


def to_dict(cfg) -> dict:
    return dataclasses.asdict(cfg)


def _matches(value, hint) -> bool:
    """Whether a YAML value fits a field's type hint (ints pass for floats; a comma-separated
    string passes for a list of names)."""
    origin, args = typing.get_origin(hint), typing.get_args(hint)
    if origin in (typing.Union, types.UnionType):
        return any(_matches(value, a) for a in args)
    if origin is list:
        return isinstance(value, str) or (isinstance(value, list) and all(_matches(v, args[0]) for v in value))
    if origin is dict:
        return isinstance(value, dict) and all(_matches(k, args[0]) and _matches(v, args[1]) for k, v in value.items())
    if hint is type(None):
        return value is None
    if hint is float:
        return isinstance(value, (int, float)) and not isinstance(value, bool)
    if hint is int:
        return isinstance(value, int) and not isinstance(value, bool)
    return isinstance(value, hint)


def from_dict(cls, data: dict, where: str = ""):
    """Build dataclass ``cls`` from a nested dict. An unknown key or a value of the wrong type
    is a ValueError naming it, raised before any section's own checks run."""
    if not isinstance(data, dict):
        raise ValueError(f"config section {where or 'root'} must be a mapping, got {type(data).__name__}")
    hints = typing.get_type_hints(cls)
    names = {f.name for f in dataclasses.fields(cls)}
    kwargs = {}
    for key, value in data.items():
        if key not in names:
            raise ValueError(f"unknown config key '{where}{key}'; known keys: {', '.join(sorted(names))}")
        hint = hints[key]
        if dataclasses.is_dataclass(hint):
            value = from_dict(hint, value or {}, f"{where}{key}.")
        elif not _matches(value, hint):
            expected = hint.__name__ if isinstance(hint, type) else str(hint)
            raise ValueError(f"{where}{key}={value!r} has the wrong type, expected {expected}")
        elif hint is float:
            value = float(value)
        kwargs[key] = value
    return cls(**kwargs)


def save_config(cfg, path: str | Path) -> None:
    Path(path).write_text(yaml.safe_dump(to_dict(cfg), sort_keys=False))


def load_config(path: str | Path, cls=TrainConfig):
    """Read a YAML config; raise ValueError with one actionable line when it is bad."""
    path = Path(path)
    if not path.is_file():
        raise ValueError(f"config file {path} not found")
    try:
        data = yaml.safe_load(path.read_text()) or {}
    except yaml.YAMLError as err:
        raise ValueError(f"config file {path} is not valid YAML: {str(err).splitlines()[0]}") from err
    try:
        return from_dict(cls, data)
    except ValueError as err:
        raise ValueError(f"{path}: {err}") from err
