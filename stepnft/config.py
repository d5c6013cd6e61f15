"""The run configuration: typed dataclasses, saved and loaded as YAML.

One schema serves every command: ``stepnft sft`` and ``train`` read a whole
:class:`TrainConfig`, ``demos`` and ``eval`` the sections they need; the CLI is generated from
these dataclasses (``stepnft.cli``). A run directory's ``config.yaml`` reproduces the run
(``stepnft train --config RUN/config.yaml``). Every field declares what it accepts (its type and
``Range``, ``stepnft.settings``) and is checked when its section is built, so Python, YAML files,
flags and a policy's config.json get the same checks; ``check()`` holds the rules between fields.
"""

from __future__ import annotations

import dataclasses
import importlib.util
import math
import re
import typing
from dataclasses import dataclass, field
from pathlib import Path
from typing import Annotated, ClassVar, Literal

import yaml

from stepnft.algos.base import AlgoConfig, config_class
from stepnft.algos.sft import SFTConfig
from stepnft.algos.stepnft import StepNFTConfig
from stepnft.devices import check_device_name
from stepnft.envs import DEFAULT_TASKS, SIMULATORS
from stepnft.envs.perturbations import FAMILY, expand
from stepnft.policies.base import policy_config_class
from stepnft.policies.configuration import PolicyConfig
from stepnft.policies.flow import FlowPolicyConfig
from stepnft.settings import (DEMO_EPISODES_MAX, EVAL_SEEDS_END, ITERATIONS_MAX, SEED_MAX, Check, Range, Settings,
                              read_settings_text)

DEVICE = Check(check_device_name, "cpu, cuda or cuda:N")
"""The devices a policy may compute on (``--device``)."""
PATH = Check(lambda path: bool(path.strip()), "a path (not empty)")
"""A file or folder a command reads or writes: "" would silently mean the working directory."""


@dataclass
class EnvConfig(Settings):
    """Which simulator and tasks run, and how."""

    section: ClassVar[str] = "env"

    name: str = "metaworld"
    """Simulator: metaworld (MetaWorld v3, the default), bandit (a toy for tests), libero
    (LIBERO, the optional extra stepnft[libero]; docs/libero.md), maniskill (ManiSkill3, the
    optional extra stepnft[maniskill]; docs/maniskill.md), gym (any Gymnasium env: --env.id;
    docs/gym.md) or one an installed plugin registers (docs/extending.md)."""
    tasks: list[str] = field(default_factory=lambda: list(DEFAULT_TASKS))
    """Task names (space- or comma-separated); one multi-task policy serves all of them."""
    envs_per_task: Annotated[int, Range(ge=1, le=4096)] = 4
    """Parallel simulator instances per task: each plays its task's episodes back to back
    (more of them shorten the tail of an iteration whose allocation favours one task)."""
    max_episode_steps: Annotated[int, Range(ge=1, le=10**5)] = 200
    """Episode cap in env steps (MetaWorld allows at most 500)."""
    terminate_on_success: bool = True
    """End an episode at its first success (the episode then counts as a success)."""
    num_workers: Annotated[int, Range(ge=0, le=256)] = 0
    """Simulator processes stepping at once (0: all sub-envs in this process; 2 uses both
    cores of a 2-core machine)."""
    sim_backend: Literal["cpu", "gpu"] = "cpu"
    """cpu: one simulator instance per sub-env (stepped in this process or in num_workers
    processes). gpu (ManiSkill only, needs CUDA): each task's sub-envs are the scenes of one
    batched ManiSkill env on the GPU's physics (envs_per_task of them, e.g. 256; docs/maniskill.md)."""
    cameras: list[str] = field(default_factory=list)
    """Cameras rendered into the observation ``image`` once per policy call (MetaWorld: corner,
    corner2, corner3, corner4, topview, behindGripper, gripperPOV; empty: state only). Needs
    MUJOCO_GL=egl; the policy's --policy.cameras must match."""
    image_size: Annotated[int, Range(ge=8, le=480)] = 64
    """Side in pixels of the square camera images."""
    state_obs: Literal["full", "proprio", "interest"] = "full"
    """State observation: full (MetaWorld's 39 values, object and goal positions included) or
    proprio (hand xyz and gripper opening only: for camera policies; --policy.state-dim 4).
    LIBERO: full 64, proprio 8, interest 22 (the proprioception and the objects of interest' poses)."""
    reward: Literal["native", "shaped"] = "native"
    """native: the simulator's own reward (MetaWorld's and ManiSkill's are shaped; LIBERO's is
    sparse, 1 while the goal holds); shaped: a reward that measures progress, what π-StepNFT's
    labels: progress and PPO's reward: shaped read (MetaWorld, ManiSkill: their own; LIBERO: a
    reach-grasp-lift-place reward from the objects of interest, pick-and-place tasks only)."""
    id: list[str] = field(default_factory=list)
    """env.name gym: the Gymnasium env of each task, a registered id (FetchPush-v4) or
    module:Env-v0 (its module imported first, which registers it). Each task is named by its
    id's last part (PushT-v0): env.tasks then follows from env.id."""
    make_kwargs: dict[str, bool | Annotated[int, Range(ge=-10**9, le=10**9)] | Annotated[float, Range(ge=-1e9, le=1e9)]
                      | str] = field(default_factory=dict)
    """env.name gym: keyword arguments of gymnasium.make for every id (e.g. obs_type: state)."""
    state_keys: list[str] = field(default_factory=list)
    """env.name gym: the entries of a Dict observation that make the policy's state, flattened
    and concatenated in this order (nested ones as a/b); empty: a Box observation whole, or
    every vector entry of a Dict one. Camera images are the env.cameras entries (or render)."""
    success: str = "auto"
    """env.name gym: what success is: auto (info["is_success"], else info["success"]), another
    info key, or module:function called as function(obs, info) -> bool on the raw observation."""
    instructions: dict[str, str] = field(default_factory=dict)
    """env.name gym: the instruction of each task (by task name; default: the task's name)."""
    expert: str | None = None
    """env.name gym: module:factory of a scripted expert, factory(task, seed) returning a
    callable raw_obs -> action (in the env's units) that records the demonstrations; without
    one, --demos.path must hold a LeRobot dataset folder or HDF5 demonstrations."""
    randomize: list[str] = field(default_factory=list)
    """Perturbations randomised in every training episode, from their training ranges (never
    the held-out ones the suites use): suite names (vision, semantic, execution) or single
    perturbations (table_color, floor_color, object_color, lighting, camera_pose, paraphrase,
    distractor, object_position, action_noise, friction, mass); see docs/ood.md."""

    def check(self) -> None:
        if self.name not in SIMULATORS:
            raise self.fail(f"{{name}} must be one of {', '.join(SIMULATORS)}", self.name)
        self._check_gym()
        info = SIMULATORS[self.name]
        if self.max_episode_steps > info.max_episode_steps:
            raise self.fail(f"{{max_episode_steps}} must be in [1, {info.max_episode_steps}] for {self.name}",
                            self.max_episode_steps)
        if self.reward == "shaped" and info.reward == "sparse" and not info.shaped_option:
            raise self.fail(f"{{reward}} shaped: {self.name}'s reward is success only and it has no shaped option; "
                            "use native", self.reward)
        if self.sim_backend == "gpu" and self.name != "maniskill":
            raise self.fail(f"{{sim_backend}} gpu is ManiSkill's batched GPU physics; {self.name} runs on the CPU: use cpu",
                            self.sim_backend)
        if self.sim_backend == "gpu" and self.num_workers:
            raise self.fail("{sim_backend} gpu steps all scenes in this process: set {num_workers} 0", self.sim_backend)
        try:
            self.randomize = list(expand(self.randomize))
        except ValueError as err:
            raise self.fail(f"{{randomize}}: {err}") from None
        if not self.cameras and any(FAMILY[n] == "vision" for n in self.randomize):
            raise self.fail("{randomize} vision perturbations change only camera images: set {cameras} too")


    GYM_FIELDS: ClassVar[tuple[str, ...]] = ("id", "make_kwargs", "state_keys", "success", "instructions", "expert")

    def _check_gym(self) -> None:
        """``env.name: gym`` takes its tasks from ``env.id``; the other simulators take no gym settings."""
        if self.name != "gym":
            defaults = {f.name: f.default if f.default_factory is dataclasses.MISSING else f.default_factory()
                        for f in dataclasses.fields(self) if f.name in self.GYM_FIELDS}
            given = [n for n in self.GYM_FIELDS if getattr(self, n) != defaults[n]]
            if given:
                raise self.fail(f"{{{given[0]}}} is a setting of env.name gym (any Gymnasium env), not of {self.name}")
            return
        from stepnft.envs.gym import task_name

        if not self.id:
            raise self.fail("{name} gym needs the Gymnasium env: give {id} (a registered id or module:Env-v0)")
        names = [task_name(i) for i in self.id]
        if len(set(names)) != len(names):
            raise self.fail("{id} entries must have distinct names (the part after the last / or :)", self.id)
        if self.tasks not in (names, DEFAULT_TASKS):
            raise self.fail(f"{{tasks}} of env.name gym are named by {{id}}: leave {{tasks}} out (they are {names})",
                            self.tasks)
        self.tasks = names
        unknown = sorted(set(self.instructions) - set(names))
        if unknown:
            raise self.fail(f"{{instructions}} names {', '.join(unknown)}, not a task of {{id}} ({', '.join(names)})")
        for target in filter(None, (self.expert, self.success if ":" in self.success else None)):
            if not re.fullmatch(r"[\w.]+:[\w.]+", target):
                raise self.fail("{expert} and {success} take module:name", target)


@dataclass
class DemoConfig(Settings):
    """Few-shot demonstrations from the simulator's scripted experts."""

    section: ClassVar[str] = "demos"

    path: str = "demos/default"
    """Folder of demonstrations (generated there if missing)."""
    episodes: Annotated[int, Range(ge=1, le=DEMO_EPISODES_MAX)] = 5
    """Successful demonstrations per task (few-shot)."""
    task_episodes: dict[str, Annotated[int, Range(ge=1, le=DEMO_EPISODES_MAX)]] = field(default_factory=dict)
    """Per-task overrides of ``episodes`` (e.g. fewer on tasks SFT already saturates)."""
    max_attempts: Annotated[int | None, Range(ge=1, le=DEMO_EPISODES_MAX)] = None
    """Expert episodes tried per task before giving up (None: 5 x the demonstrations wanted);
    failed attempts are discarded and counted in the manifest."""
    action_noise: Annotated[float, Range(ge=0, le=10)] = 0.0
    """Std of Gaussian noise added to the expert's actions."""
    dart: bool = False
    """With ``action_noise``: execute the noisy action but record the expert's clean one for
    each state visited (DART): the demonstrations then show how to recover from the drift the
    noise causes, which a policy cloned from a few clean paths never sees."""
    successful_only: bool = True
    """Keep only the expert's successful episodes (False: keep every attempt, e.g. for a
    deliberately imperfect demonstrator)."""
    seed: Annotated[int, Range(ge=0, le=SEED_MAX)] = 0
    """Seed of the demonstrations' initial states (disjoint from evaluation states)."""

    def check(self) -> None:
        wanted = max([self.episodes, *self.task_episodes.values()])
        if self.max_attempts is not None and self.max_attempts < wanted:
            raise self.fail(f"{{max_attempts}} must be >= the demonstrations wanted ({wanted})", self.max_attempts)
        if self.dart and not self.action_noise > 0:
            raise self.fail("{dart} records the expert's clean actions on the states its noisy ones reach: give "
                            "{action_noise} > 0 too (e.g. 0.3)")

    def count(self, task: str) -> int:
        """Demonstrations used for ``task``."""
        return self.task_episodes.get(task, self.episodes)


@dataclass
class EvalConfig(Settings):
    """Deterministic (ODE) evaluation on a fixed, seeded set of initial states."""

    section: ClassVar[str] = "eval"

    episodes: Annotated[int, Range(ge=0, le=EVAL_SEEDS_END)] = 100
    """Episodes per task for the before/after figures (>= 100 for reported numbers)."""
    seed: Annotated[int, Range(ge=0, lt=EVAL_SEEDS_END)] = 0
    """Test episode e of a task starts from initial state ``seed + e``: the same for every checkpoint."""
    every: Annotated[int, Range(ge=0, le=ITERATIONS_MAX)] = 10
    """Iterations between validation evaluations during training (0: only before and after)."""
    during_episodes: Annotated[int, Range(ge=1, le=EVAL_SEEDS_END)] = 20
    """Episodes per task for the validation evaluations during training (cheap, noisier)."""
    validation_seed: Annotated[int, Range(ge=0, lt=EVAL_SEEDS_END)] = 1_000_000
    """Validation episode e starts from initial state ``validation_seed + e``: disjoint from the
    test states, so choosing ``best_policy/`` on them does not bias the reported figures."""
    videos: Annotated[int, Range(ge=0, le=1000)] = 0
    """Episodes per task filmed after the final evaluation, into RUN/videos/*.mp4 and TensorBoard
    (camera policies: what the policy saw beside the scene); needs MUJOCO_GL=egl. 0: none."""

    def check(self) -> None:
        if self.seed + self.episodes > EVAL_SEEDS_END or self.validation_seed + self.during_episodes > EVAL_SEEDS_END:
            raise self.fail(f"{{seed}} + {{episodes}} and {{validation_seed}} + {{during_episodes}} must be at most "
                            f"{EVAL_SEEDS_END} (evaluation states stay below the training episodes' seeds), got "
                            f"{self.seed + self.episodes} and {self.validation_seed + self.during_episodes}")
        if self.validation_seed < self.seed + self.episodes:
            raise self.fail(f"{{validation_seed}} ({self.validation_seed}) must be >= {{seed}} + {{episodes}} "
                            f"({self.seed + self.episodes}): validation and test states must not overlap")


@dataclass
class RayConfig(Settings):
    """Rollouts on Ray actors (``pip install "stepnft[ray]"``): each worker owns a share of the
    sub-envs and a copy of the acting policy; the same episodes as one process (docs/scaling.md)."""

    section: ClassVar[str] = "ray"

    workers: Annotated[int, Range(ge=0, le=4096)] = 0
    """Ray rollout workers (0: collect in this process, the default); sub-env i plays on worker
    i mod N, and evaluation runs on them too. Each reserves max(1, env.num_workers) CPUs: with
    --env.num-workers 0 a worker is one core."""
    address: Annotated[str | None, Check(lambda address: bool(address.strip()), "a cluster address")] = None
    """Ray cluster to join (``auto``, ``HOST:6379`` or ``ray://HOST:10001``); None: start a
    local Ray with the CPUs the workers reserve."""
    timeout_s: Annotated[float, Range(gt=0, le=7 * 86400)] = 600.0
    """Seconds a worker may take to start or to play its part of an iteration before it counts
    as hung: it is killed and restarted, its episodes of that part dropped."""
    max_restarts: Annotated[int, Range(ge=0, le=1000)] = 3
    """Times each worker may be lost (crash, timeout, node loss) and restarted before the run
    stops with an error (then `stepnft train --resume RUN_DIR`)."""

    def check(self) -> None:
        if self.address is not None and self.workers == 0:
            raise self.fail("{address} needs rollout workers on the cluster: set {workers} N")
        if self.workers > 0 and importlib.util.find_spec("ray") is None:
            raise self.fail(f'{{workers}}={self.workers} needs Ray, which is not installed: pip install "stepnft[ray]" '
                            "(or {workers}=0)")


@dataclass
class TrainConfig(Settings):
    """A run: demonstrations -> few-shot SFT -> online RL (π-StepNFT by default) -> evaluation."""

    resumable: ClassVar[tuple[str, ...]] = ("ray", "device", "gradient_checkpointing")
    """What a resumed run may change (``stepnft train --resume RUN --device cuda``): where it
    computes, never what it computes."""
    lengthening: ClassVar[tuple[str, ...]] = ("iterations", "env_step_budget")
    """What a resumed run may raise (``stepnft train --resume RUN --iterations 40``): a finished
    or interrupted run goes on to the new length; π-StepNFT's EMA schedule keeps the horizon the
    run started with, so the longer run is the one a new run with these values and that horizon
    gives."""

    run_dir: str = "runs/stepnft"
    """Output folder: config.yaml, metrics.jsonl, TensorBoard logs, checkpoints, curves, summary."""
    seed: Annotated[int, Range(ge=0, le=SEED_MAX)] = 0
    """Seeds every source of randomness (torch, sampler noise, simulator)."""
    iterations: Annotated[int, Range(ge=0, le=ITERATIONS_MAX)] = 60
    """RL iterations: collect rollouts -> update -> end-of-iteration step (e.g. the EMA update)."""
    episodes_per_iteration: Annotated[int, Range(ge=1, le=10**6)] = 20
    """Episodes collected per iteration (with ``task_allocation: equal``, split evenly over the
    tasks, each task's share rounded up to whole groups)."""
    task_allocation: Literal["equal", "informative"] = "equal"
    """How an iteration's episodes are split over tasks: ``equal``, or ``informative`` (more to
    tasks whose rollout success is far from 0 and 1; see stepnft.rollout.allocation)."""
    allocation_floor: Annotated[float, Range(ge=0, le=1)] = 0.3
    """With ``informative``: the share of episodes split equally, so every task stays in play."""
    env_step_budget: Annotated[int | None, Range(ge=1, le=10**12)] = None
    """Stop once this many rollout env steps were spent (None: run all iterations); the
    same budget for every algorithm makes comparisons fair."""
    init: Annotated[str | None, PATH] = None
    """Saved policy folder to start from; None: run few-shot SFT on the demonstrations first.
    ``stepnft sft --init``: the policy SFT fine-tunes (any type, e.g. a LeRobot SmolVLA folder,
    whose sizes then replace the --policy.* ones; docs/lerobot.md)."""
    checkpoint_every: Annotated[int, Range(ge=1, le=ITERATIONS_MAX)] = 10
    """Iterations between checkpoints (the last one is always written)."""
    num_threads: Annotated[int, Range(ge=1, le=1024)] = 1
    """torch CPU threads (the policy is small: one thread is fastest, and leaves a core to the simulator)."""
    device: Annotated[str, DEVICE] = "cpu"
    """Where the policy, its EMA copy, PPO's critic and the optimizer state live and compute: cpu,
    cuda or cuda:N (docs/gpu.md). Simulators, observation processing, rollout batches, checkpoints
    and all random generators stay on the CPU, so a CUDA run draws the same noise as a CPU run.
    A resumed run may change it (``--resume RUN --device cuda``)."""
    precision: Literal["fp32", "bf16"] = "fp32"
    """How the policy computes: fp32, or bf16 (frozen parameters, e.g. a VLA's backbone with
    train: expert, stored in bfloat16; forward passes under torch.autocast; trained parameters,
    optimizer state, sampler noise and losses in float32; docs/gpu.md). For GPUs with bfloat16;
    on a CPU it saves memory, rarely time."""
    gradient_checkpointing: bool = False
    """Recompute activations in the backward pass instead of keeping them (a LeRobot VLA: per
    transformer layer): less memory, about one more forward pass per update step, the same
    gradients. A resumed run may change it."""
    env: EnvConfig = field(default_factory=EnvConfig)
    demos: DemoConfig = field(default_factory=DemoConfig)
    policy: PolicyConfig = field(default_factory=FlowPolicyConfig)
    """The policy built from scratch when there is no ``init``: ``policy.type`` picks its config
    class (the flow MLP's, ``flow``, by default; a registered type of a plugin: docs/extending.md),
    whose fields are then the ``--policy.*`` settings."""
    sft: SFTConfig = field(default_factory=SFTConfig)
    algo: AlgoConfig = field(default_factory=StepNFTConfig)
    eval: EvalConfig = field(default_factory=EvalConfig)
    ray: RayConfig = field(default_factory=RayConfig)

    def check(self) -> None:
        # An --init policy brings its own cameras (checked when the run starts).
        cameras = list(getattr(self.policy, "cameras", []))  # a policy config without cameras sees none
        if self.init is None and cameras != list(self.env.cameras):
            raise self.fail(f"{{policy.cameras}} {cameras} differ from {{env.cameras}} {self.env.cameras}: "
                            "give both the same list (e.g. --config configs/image.yaml)")


@dataclass
class DemosCommand(Settings):
    """Generate scripted-expert demonstrations: expert episodes until N successes per task."""

    env: EnvConfig = field(default_factory=EnvConfig)
    demos: DemoConfig = field(default_factory=DemoConfig)


@dataclass
class EvalCommand(Settings):
    """Evaluate a saved policy on a fixed, seeded set of initial states (ODE sampling)."""

    policy: Annotated[str, PATH] = "runs/stepnft/policy"
    """Policy folder (config.json + model.safetensors), e.g. RUN/policy or RUN/sft_policy."""
    out: Annotated[str | None, PATH] = None
    """Also write the results as JSON to this file."""
    video_dir: Annotated[str | None, PATH] = None
    """Also record ODE episodes as ``DIR/<task>_ep<e>_<success|fail>.mp4`` (needs offscreen
    rendering: MUJOCO_GL=egl)."""
    video_episodes: Annotated[int, Range(ge=1, le=1000)] = 1
    """Episodes recorded per task with --video-dir (episode e starts from eval state seed + e)."""
    suite: list[str] = field(default_factory=lambda: ["ind"])
    """Evaluation suites: ind (the training distribution), vision, semantic, execution (held-out
    perturbations, docs/ood.md); several give a table with the OOD average. The env's cameras
    and state observation follow the policy."""
    device: Annotated[str, DEVICE] = "cpu"
    """Where the policy samples: cpu, cuda or cuda:N (simulators and noise stay on the CPU)."""
    env: EnvConfig = field(default_factory=EnvConfig)
    eval: EvalConfig = field(default_factory=EvalConfig)


def to_dict(cfg) -> dict:
    """Plain nested dict of a config (tuples as lists, so it is safe YAML). A policy section of
    another type than ``flow`` starts with its ``type`` (a flow one leaves it out, so configs and
    checkpoints written before policy types were settings read the same)."""
    def plain(value):
        if isinstance(value, dict):
            return {k: plain(v) for k, v in value.items()}
        if isinstance(value, (list, tuple)):
            return [plain(v) for v in value]
        return value

    data = plain(dataclasses.asdict(cfg))
    policy = getattr(cfg, "policy", None)
    if isinstance(policy, PolicyConfig) and policy.type != FlowPolicyConfig.type:
        data["policy"] = {"type": policy.type, **data["policy"]}
    return data


def from_dict(cls, data: dict, where: str = ""):
    """Build config dataclass ``cls`` from a nested dict (a YAML file, or the values of parsed
    flags). An unknown key is a ValueError naming it; every value is checked where its section is
    built (``stepnft.settings``). An ``algo`` section is built as the config class of its ``name``,
    a ``policy`` section as that of its ``type`` (``flow`` when it has none)."""
    if not isinstance(data, dict):
        raise ValueError(f"config section {where or 'root'} must be a mapping, got {type(data).__name__}")
    if cls is AlgoConfig:
        cls = config_class(data.get("name", StepNFTConfig.name))
    if cls is PolicyConfig:
        data = dict(data)
        type_name = data.pop("type", FlowPolicyConfig.type)
        if not isinstance(type_name, str):
            raise ValueError(f"config key '{where}type' must be a policy type name, got {type_name!r}")
        try:
            cls = policy_config_class(type_name)
        except ValueError as err:
            raise ValueError(f"{where}type: {err}") from None
    hints = typing.get_type_hints(cls)
    names = {f.name for f in dataclasses.fields(cls)}
    kwargs = {}
    for key, value in data.items():
        if key not in names:
            raise ValueError(f"unknown config key '{where}{key}'; known keys: {', '.join(sorted(names))}")
        if dataclasses.is_dataclass(hints[key]):
            value = from_dict(hints[key], value or {}, f"{where}{key}.")
        kwargs[key] = value
    return cls(**kwargs)


def save_config(cfg, path: str | Path) -> None:
    from stepnft.runs import write_atomic

    write_atomic(path, yaml.safe_dump(to_dict(cfg), sort_keys=False))


class _Loader(yaml.SafeLoader):
    """YAML as PyYAML's safe loader reads it, but with YAML 1.2's numbers: ``3e-5`` is a float
    (YAML 1.1 wants ``3.0e-5`` and reads ``3e-5`` as a string, which a float setting refuses)."""


_Loader.add_implicit_resolver(
    "tag:yaml.org,2002:float",
    re.compile(r"^[-+]?(?:[0-9][0-9_]*)(?:\.[0-9_]*)?[eE][-+]?[0-9]+$"),
    list("-+0123456789"),
)


YAML_NODES_MAX = 100_000
"""The most values a YAML config may hold once its aliases are expanded (a run's config.yaml
holds about 200): anchors and aliases can make a small file stand for billions of values (the
"billion laughs"), which every later step would walk."""


def read_yaml(text: str):
    """Parse YAML ``text`` as config files are read (``3e-5`` is a number): ``yaml.YAMLError`` if it
    is no YAML, ValueError (one line, "expands to ...") if it expands beyond :data:`YAML_NODES_MAX`
    values or nests too deeply."""
    loader = _Loader(text)
    try:
        node = loader.get_single_node()
        if node is None:
            return None
        if _expanded_size(node) > YAML_NODES_MAX:
            raise ValueError(f"expands to more than {YAML_NODES_MAX} values (anchors and aliases used many times "
                             "over, or an alias inside its own anchor): write the values out")
        return loader.construct_document(node)
    except RecursionError:
        raise ValueError("nests too deeply to be a config (lists or mappings inside each other hundreds of times)") from None
    finally:
        loader.dispose()


def _expanded_size(root: yaml.Node) -> float:
    """Values under ``root`` with every alias expanded where it is used (inf for an alias inside
    its own anchor); each distinct node is visited once."""
    sizes: dict[int, float] = {}
    open_nodes: set[int] = set()

    def size(node: yaml.Node) -> float:
        if id(node) in sizes:
            return sizes[id(node)]
        if id(node) in open_nodes:
            return math.inf
        open_nodes.add(id(node))
        children = (node.value if isinstance(node, yaml.SequenceNode)
                    else [n for pair in node.value for n in pair] if isinstance(node, yaml.MappingNode) else [])
        total = 1 + sum(size(child) for child in children)
        open_nodes.discard(id(node))
        sizes[id(node)] = total
        return total

    return size(root)


def load_config(path: str | Path, cls=TrainConfig):
    """Read a YAML config; raise ValueError with one actionable line when it is bad."""
    path = Path(path)
    if path.is_dir():
        raise ValueError(f"config file {path} is a folder: give a YAML file (a run's config is RUN/config.yaml)")
    if not path.is_file():
        raise ValueError(f"config file {path} not found")
    text = read_settings_text(path)
    try:
        data = read_yaml(text) or {}
    except yaml.YAMLError as err:
        raise ValueError(f"config file {path} is not valid YAML: {str(err).splitlines()[0]}") from err
    except ValueError as err:
        raise ValueError(f"config file {path} {err}") from None
    try:
        return from_dict(cls, data)
    except ValueError as err:
        raise ValueError(f"{path}: {err}") from err
