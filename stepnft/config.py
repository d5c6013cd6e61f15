"""The run configuration: typed dataclasses, saved and loaded as YAML.

One schema serves every command: ``stepnft sft`` and ``train`` read a whole
:class:`TrainConfig`, ``demos`` and ``eval`` the sections they need; the CLI is generated from
these dataclasses (``stepnft.cli``). A run directory's ``config.yaml`` reproduces the run
(``stepnft train --config RUN/config.yaml``). Every value is range-checked where its section
is built, so YAML files and flags get the same checks.
"""

from __future__ import annotations

import dataclasses
import importlib.util
import types
import typing
from dataclasses import dataclass, field
from pathlib import Path
from typing import Literal

import yaml

from stepnft.algos.base import AlgoConfig, config_class
from stepnft.algos.sft import SFTConfig
from stepnft.algos.stepnft import StepNFTConfig
from stepnft.devices import check_device_name
from stepnft.envs import DEFAULT_TASKS, SIMULATORS
from stepnft.envs.perturbations import FAMILY, expand
from stepnft.names import split_names
from stepnft.policies.flow import FlowPolicyConfig


@dataclass
class EnvConfig:
    """Which simulator and tasks run, and how."""

    name: str = "metaworld"
    """Simulator: metaworld (MetaWorld v3, the default), bandit (a toy for tests) or libero
    (LIBERO, the optional extra stepnft[libero]; docs/libero.md)."""
    tasks: list[str] = field(default_factory=lambda: list(DEFAULT_TASKS))
    """Task names (space- or comma-separated); one multi-task policy serves all of them."""
    envs_per_task: int = 4
    """Parallel simulator instances per task (each plays one episode per rollout wave)."""
    max_episode_steps: int = 200
    """Episode cap in env steps (MetaWorld allows at most 500)."""
    terminate_on_success: bool = True
    """End an episode at its first success (the episode then counts as a success)."""
    num_workers: int = 0
    """Simulator processes stepping at once (0: all sub-envs in this process; 2 uses both
    cores of a 2-core machine)."""
    cameras: list[str] = field(default_factory=list)
    """Cameras rendered into the observation ``image`` once per policy call (MetaWorld: corner,
    corner2, corner3, corner4, topview, behindGripper, gripperPOV; empty: state only). Needs
    MUJOCO_GL=egl; the policy's --policy.cameras must match."""
    image_size: int = 64
    """Side in pixels of the square camera images."""
    state_obs: Literal["full", "proprio"] = "full"
    """State observation: full (MetaWorld's 39 values, object and goal positions included) or
    proprio (hand xyz and gripper opening only: for camera policies; --policy.state-dim 4)."""
    randomize: list[str] = field(default_factory=list)
    """Perturbations randomised in every training episode, from their training ranges (never
    the held-out ones the suites use): suite names (vision, semantic, execution) or single
    perturbations (table_color, floor_color, object_color, lighting, camera_pose, paraphrase,
    distractor, object_position, action_noise, friction, mass); see docs/ood.md."""

    def __post_init__(self) -> None:
        if isinstance(self.tasks, str):
            self.tasks = [self.tasks]
        self.tasks = [t.strip() for item in self.tasks for t in item.split(",") if t.strip()]
        self.cameras = split_names(self.cameras)
        self.randomize = list(expand(split_names(self.randomize)))
        if self.cameras and not 8 <= self.image_size <= 480:
            raise ValueError(f"env.image_size must be in 8..480, got {self.image_size}")
        if self.state_obs not in ("full", "proprio"):
            raise ValueError(f"env.state_obs must be full or proprio, got {self.state_obs!r}")
        if not self.cameras and any(FAMILY[n] == "vision" for n in self.randomize):
            raise ValueError("env.randomize vision perturbations change only camera images: set --env.cameras too")
        if self.name not in SIMULATORS:
            raise ValueError(f"env.name={self.name!r} is unknown; choose one of: {', '.join(SIMULATORS)}")
        if self.envs_per_task < 1:
            raise ValueError(f"env.envs_per_task must be >= 1, got {self.envs_per_task}")
        cap = SIMULATORS[self.name].max_episode_steps
        if not 1 <= self.max_episode_steps <= cap:
            raise ValueError(f"env.max_episode_steps must be in 1..{cap}, got {self.max_episode_steps}")
        if self.num_workers < 0:
            raise ValueError(f"env.num_workers must be >= 0, got {self.num_workers}")


@dataclass
class DemoConfig:
    """Few-shot demonstrations from the simulator's scripted experts."""

    path: str = "demos/default"
    """Folder of demonstrations (generated there if missing)."""
    episodes: int = 5
    """Successful demonstrations per task (few-shot)."""
    task_episodes: dict[str, int] = field(default_factory=dict)
    """Per-task overrides of ``episodes`` (e.g. fewer on tasks SFT already saturates)."""
    max_attempts: int | None = None
    """Expert episodes tried per task before giving up (None: 5 x the demonstrations wanted);
    failed attempts are discarded and counted in the manifest."""
    action_noise: float = 0.0
    """Std of Gaussian noise added to the expert's actions."""
    successful_only: bool = True
    """Keep only the expert's successful episodes (False: keep every attempt, e.g. for a
    deliberately imperfect demonstrator)."""
    seed: int = 0
    """Seed of the demonstrations' initial states (disjoint from evaluation states)."""

    def __post_init__(self) -> None:
        if self.episodes < 1 or any(n < 1 for n in self.task_episodes.values()):
            raise ValueError(f"demos.episodes and demos.task_episodes must be >= 1, got {self.episodes}, {self.task_episodes}")
        if self.max_attempts is not None and self.max_attempts < max(self.episodes, *self.task_episodes.values()):
            raise ValueError(f"demos.max_attempts must be >= the demonstrations wanted, got {self.max_attempts}")
        if not 0 <= self.action_noise < float("inf"):
            raise ValueError(f"demos.action_noise must be a finite number >= 0, got {self.action_noise}")
        if self.seed < 0:
            raise ValueError(f"demos.seed must be >= 0, got {self.seed}")

    def count(self, task: str) -> int:
        """Demonstrations used for ``task``."""
        return self.task_episodes.get(task, self.episodes)


@dataclass
class EvalConfig:
    """Deterministic (ODE) evaluation on a fixed, seeded set of initial states."""

    episodes: int = 100
    """Episodes per task for the before/after figures (>= 100 for reported numbers)."""
    seed: int = 0
    """Test episode e of a task starts from initial state ``seed + e``: the same for every checkpoint."""
    every: int = 10
    """Iterations between validation evaluations during training (0: only before and after)."""
    during_episodes: int = 20
    """Episodes per task for the validation evaluations during training (cheap, noisier)."""
    validation_seed: int = 1_000_000
    """Validation episode e starts from initial state ``validation_seed + e``: disjoint from the
    test states, so choosing ``best_policy/`` on them does not bias the reported figures."""
    videos: int = 0
    """Episodes per task filmed after the final evaluation, into RUN/videos/*.mp4 and TensorBoard
    (camera policies: what the policy saw beside the scene); needs MUJOCO_GL=egl. 0: none."""

    def __post_init__(self) -> None:
        if self.episodes < 0 or self.every < 0 or self.during_episodes < 1 or self.seed < 0:
            raise ValueError(f"eval.episodes, eval.every and eval.seed must be >= 0 and eval.during_episodes >= 1, got "
                             f"{self.episodes}, {self.every}, {self.seed}, {self.during_episodes}")
        if self.validation_seed < self.seed + self.episodes:
            raise ValueError(f"eval.validation_seed ({self.validation_seed}) must be >= eval.seed + eval.episodes "
                             f"({self.seed + self.episodes}): validation and test states must not overlap")
        if self.videos < 0:
            raise ValueError(f"eval.videos must be >= 0, got {self.videos}")


@dataclass
class RayConfig:
    """Rollouts on Ray actors (``pip install "stepnft[ray]"``): each worker owns a share of the
    sub-envs and a copy of the acting policy; the same episodes as one process (docs/scaling.md)."""

    workers: int = 0
    """Ray rollout workers (0: collect in this process, the default); sub-env i plays on worker
    i mod N, and evaluation runs on them too. Each reserves max(1, env.num_workers) CPUs: with
    --env.num-workers 0 a worker is one core."""
    address: str | None = None
    """Ray cluster to join (``auto``, ``HOST:6379`` or ``ray://HOST:10001``); None: start a
    local Ray with the CPUs the workers reserve."""
    timeout_s: float = 600.0
    """Seconds a worker may take to start or to play one wave before it counts as hung: it is
    killed and restarted, its episodes of that wave dropped."""
    max_restarts: int = 3
    """Times each worker may be lost (crash, timeout, node loss) and restarted before the run
    stops with an error (then `stepnft train --resume RUN_DIR`)."""

    def __post_init__(self) -> None:
        if self.workers < 0 or not self.timeout_s > 0 or self.max_restarts < 0:
            raise ValueError(f"ray.workers and ray.max_restarts must be >= 0 and ray.timeout_s > 0, got "
                             f"{self.workers}, {self.max_restarts}, {self.timeout_s}")
        if self.address is not None and self.workers == 0:
            raise ValueError("ray.address needs rollout workers on the cluster: set --ray.workers N")
        if self.workers > 0 and importlib.util.find_spec("ray") is None:
            raise ValueError(f'ray.workers={self.workers} needs Ray, which is not installed: pip install "stepnft[ray]" '
                             "(or --ray.workers 0)")


@dataclass
class TrainConfig:
    """A run: demonstrations -> few-shot SFT -> online RL (π-StepNFT by default) -> evaluation."""

    run_dir: str = "runs/stepnft"
    """Output folder: config.yaml, metrics.jsonl, TensorBoard logs, checkpoints, curves, summary."""
    seed: int = 0
    """Seeds every source of randomness (torch, sampler noise, simulator)."""
    iterations: int = 60
    """RL iterations: collect rollouts -> update -> end-of-iteration step (e.g. the EMA update)."""
    episodes_per_iteration: int = 20
    """Episodes collected per iteration (with ``task_allocation: equal``, rounded up to whole
    waves of all parallel envs)."""
    task_allocation: Literal["equal", "informative"] = "equal"
    """How an iteration's episodes are split over tasks: ``equal``, or ``informative`` (more to
    tasks whose rollout success is far from 0 and 1; see stepnft.rollout.allocation)."""
    allocation_floor: float = 0.3
    """With ``informative``: the share of episodes split equally, so every task stays in play."""
    env_step_budget: int | None = None
    """Stop once this many rollout env steps were spent (None: run all iterations); the
    same budget for every algorithm makes comparisons fair."""
    init: str | None = None
    """Saved policy folder to start from; None: run few-shot SFT on the demonstrations first.
    ``stepnft sft --init``: the policy SFT fine-tunes (any type, e.g. a LeRobot SmolVLA folder,
    whose sizes then replace the --policy.* ones; docs/lerobot.md)."""
    checkpoint_every: int = 10
    """Iterations between checkpoints (the last one is always written)."""
    num_threads: int = 1
    """torch CPU threads (the policy is small: one thread is fastest, and leaves a core to the simulator)."""
    device: str = "cpu"
    """Where the policy, its EMA copy, PPO's critic and the optimizer state live and compute: cpu,
    cuda or cuda:N (docs/gpu.md). Simulators, observation processing, rollout batches, checkpoints
    and all random generators stay on the CPU, so a CUDA run draws the same noise as a CPU run.
    A resumed run may change it (``--resume RUN --device cuda``)."""
    env: EnvConfig = field(default_factory=EnvConfig)
    demos: DemoConfig = field(default_factory=DemoConfig)
    policy: FlowPolicyConfig = field(default_factory=FlowPolicyConfig)
    sft: SFTConfig = field(default_factory=SFTConfig)
    algo: AlgoConfig = field(default_factory=StepNFTConfig)
    eval: EvalConfig = field(default_factory=EvalConfig)
    ray: RayConfig = field(default_factory=RayConfig)

    def __post_init__(self) -> None:
        checks = {
            "iterations": self.iterations >= 0,
            "episodes_per_iteration": self.episodes_per_iteration >= 1,
            "checkpoint_every": self.checkpoint_every >= 1,
            "num_threads": self.num_threads >= 1,
            "env_step_budget": self.env_step_budget is None or self.env_step_budget >= 1,
            "allocation_floor": 0 <= self.allocation_floor <= 1,
            "task_allocation": self.task_allocation in ("equal", "informative"),
            "device": check_device_name(self.device),
        }
        bad = [k for k, ok in checks.items() if not ok]
        if bad:
            raise ValueError(f"{bad[0]}={getattr(self, bad[0])!r} is invalid: iterations must be >= 0, "
                             "episodes_per_iteration, checkpoint_every, num_threads and env_step_budget >= 1, "
                             "allocation_floor in [0, 1], device cpu, cuda or cuda:N")
        # An --init policy brings its own cameras (checked when the run starts).
        if self.init is None and self.policy.cameras != self.env.cameras:
            raise ValueError(f"policy.cameras {self.policy.cameras} differ from env.cameras {self.env.cameras}: "
                             "give both the same list (e.g. --config configs/image.yaml)")


@dataclass
class DemosCommand:
    """Generate scripted-expert demonstrations: expert episodes until N successes per task."""

    env: EnvConfig = field(default_factory=EnvConfig)
    demos: DemoConfig = field(default_factory=DemoConfig)


@dataclass
class EvalCommand:
    """Evaluate a saved policy on a fixed, seeded set of initial states (ODE sampling)."""

    policy: str = "runs/stepnft/policy"
    """Policy folder (config.json + model.safetensors), e.g. RUN/policy or RUN/sft_policy."""
    out: str | None = None
    """Also write the results as JSON to this file."""
    video_dir: str | None = None
    """Also record ODE episodes as ``DIR/<task>_ep<e>_<success|fail>.mp4`` (needs offscreen
    rendering: MUJOCO_GL=egl)."""
    video_episodes: int = 1
    """Episodes recorded per task with --video-dir (episode e starts from eval state seed + e)."""
    suite: list[str] = field(default_factory=lambda: ["ind"])
    """Evaluation suites: ind (the training distribution), vision, semantic, execution (held-out
    perturbations, docs/ood.md); several give a table with the OOD average. The env's cameras
    and state observation follow the policy."""
    device: str = "cpu"
    """Where the policy samples: cpu, cuda or cuda:N (simulators and noise stay on the CPU)."""
    env: EnvConfig = field(default_factory=EnvConfig)
    eval: EvalConfig = field(default_factory=EvalConfig)

    def __post_init__(self) -> None:
        if self.video_episodes < 1:
            raise ValueError(f"video_episodes must be >= 1, got {self.video_episodes}")
        if not check_device_name(self.device):
            raise ValueError(f"device={self.device!r} is invalid: use cpu, cuda or cuda:N")



def to_dict(cfg) -> dict:
    """Plain nested dict of a config (tuples as lists, so it is safe YAML)."""
    def plain(value):
        if isinstance(value, dict):
            return {k: plain(v) for k, v in value.items()}
        if isinstance(value, (list, tuple)):
            return [plain(v) for v in value]
        return value

    return plain(dataclasses.asdict(cfg))


def _matches(value, hint) -> bool:
    """Whether a YAML value fits a field's type hint (ints pass for floats; a comma-separated
    string passes for a list of names)."""
    origin, args = typing.get_origin(hint), typing.get_args(hint)
    if origin in (typing.Union, types.UnionType):
        return any(_matches(value, a) for a in args)
    if origin is typing.Literal:
        return value in args
    if origin is list:
        return isinstance(value, str) or (isinstance(value, list) and all(_matches(v, args[0]) for v in value))
    if origin is tuple:
        return isinstance(value, (list, tuple)) and len(value) == len(args) and all(map(_matches, value, args))
    if origin is dict:
        return isinstance(value, dict) and all(_matches(k, args[0]) and _matches(v, args[1]) for k, v in value.items())
    if hint is type(None):
        return value is None
    if hint is float:
        return isinstance(value, (int, float)) and not isinstance(value, bool)
    if hint is int:
        return isinstance(value, int) and not isinstance(value, bool)
    return isinstance(value, hint)


def _describe_hint(hint) -> str:
    if typing.get_origin(hint) is typing.Literal:
        return " or ".join(repr(a) for a in typing.get_args(hint))
    return hint.__name__ if isinstance(hint, type) else str(hint).replace("typing.", "")


def from_dict(cls, data: dict, where: str = ""):
    """Build dataclass ``cls`` from a nested dict. An unknown key or a value of the wrong type
    is a ValueError naming it, raised before any section's own checks run. An ``algo`` section
    is built as the config class of its ``name``."""
    if not isinstance(data, dict):
        raise ValueError(f"config section {where or 'root'} must be a mapping, got {type(data).__name__}")
    if cls is AlgoConfig:
        cls = config_class(data.get("name", StepNFTConfig.name))
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
            raise ValueError(f"{where}{key}={value!r} has the wrong type, expected {_describe_hint(hint)}")
        elif hint is float:
            value = float(value)
        kwargs[key] = value
    return cls(**kwargs)


def save_config(cfg, path: str | Path) -> None:
    from stepnft.runs import write_atomic

    write_atomic(path, yaml.safe_dump(to_dict(cfg), sort_keys=False))


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
