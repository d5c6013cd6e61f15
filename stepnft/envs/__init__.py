"""Simulators behind one interface (``stepnft.envs.base``).

This module stays import-light (no MuJoCo): the config and the CLI read the registry below to
check names and limits. ``get_simulator(name)`` imports a simulator's module on first use.
"""

from __future__ import annotations

import importlib
from dataclasses import dataclass

from stepnft.plugins import PluginRegistry


@dataclass(frozen=True)
class SimulatorInfo:
    """What the config needs to know about a simulator before importing it."""

    target: str
    """``module:Class`` of its :class:`stepnft.envs.base.Simulator`."""
    max_episode_steps: int
    """The longest episode the simulator allows."""
    default_tasks: tuple[str, ...]
    """Tasks used when a config names none."""
    reward: str = "shaped"
    """Its own reward (``env.reward: native``): ``shaped`` (it measures progress, as MetaWorld's
    and ManiSkill's ``normalized_dense`` do) or ``sparse`` (success only)."""
    shaped_option: bool = False
    """With a ``sparse`` reward: whether its envs offer a shaped one of stepnft's own
    (``env.reward: shaped`` passes ``reward="shaped"`` to them)."""
    opengl: bool = False
    """Whether its cameras and videos render through MuJoCo's OpenGL (``MUJOCO_GL``, checked when
    a command that renders starts: ``stepnft.envs.rendering``)."""


DEFAULT_TASKS = ["reach-v3", "push-v3", "pick-place-v3", "door-open-v3", "drawer-open-v3"]
"""The embedded default: five MetaWorld v3 tasks, one multi-task policy."""

def _check_info(value) -> str | None:
    if not isinstance(value, SimulatorInfo):
        what = f"the class {value.__name__}" if isinstance(value, type) else f"a {type(value).__name__}"
        return (f"its entry point must name a stepnft.envs.SimulatorInfo (whose target is the simulator class), "
                f"not {what}")
    if ":" not in value.target:
        return f"its SimulatorInfo.target {value.target!r} must be 'module:Class'"
    return None


SIMULATORS: dict[str, SimulatorInfo] = PluginRegistry("stepnft.simulators", {
    "metaworld": SimulatorInfo("stepnft.envs.metaworld:MetaWorld", 500, tuple(DEFAULT_TASKS), opengl=True),
    "bandit": SimulatorInfo("stepnft.envs.bandit:Bandit", 64, ("bandit",), "sparse"),
    "libero": SimulatorInfo("stepnft.envs.libero:LIBERO", 520, ("libero_spatial",), "sparse", True, opengl=True),
    "maniskill": SimulatorInfo("stepnft.envs.maniskill:ManiSkill", 500, ("PickCube-v1", "PushCube-v1")),
    "gym": SimulatorInfo("stepnft.envs.gym:GymSimulator", 10**5, ()),
}, load=True, check=_check_info)
"""Registered simulators by config name (``env.name``): stepnft's own and those of installed
packages (entry-point group ``stepnft.simulators``, ``stepnft.plugins``)."""


def get_simulator(name: str):
    """The :class:`~stepnft.envs.base.Simulator` registered as ``name``; one whose optional
    extra is not installed is a ValueError saying so."""
    if name not in SIMULATORS:
        raise ValueError(f"unknown simulator {name!r}; choose one of: {', '.join(SIMULATORS)}")
    info = SIMULATORS[name]
    if info.opengl:  # MuJoCo reads MUJOCO_GL when imported, and some values fail its import
        from stepnft.envs.rendering import check_gl_platform

        check_gl_platform(renders=False)
    module, cls = info.target.split(":")
    try:
        module = importlib.import_module(module)
    except ImportError as err:  # an optional extra (e.g. stepnft[libero]) that is not installed
        raise ValueError(str(err)) from err
    return getattr(module, cls)()


def simulator_for(env_cfg):
    """The simulator an :class:`~stepnft.config.EnvConfig` runs, set up by it
    (``Simulator.configured``: ``env.name: gym`` builds one env per task to read its sizes)."""
    return get_simulator(env_cfg.name).configured(env_cfg)


RENDERING_ENV_VARS = ("MUJOCO_GL", "PYOPENGL_PLATFORM")
"""Environment variables that choose how the simulators render offscreen (MuJoCo's GL backend);
processes started elsewhere (Ray workers) get the driver's."""


def make_vec_env(env_cfg, n_exec: int, seed: int, perturbations=None, sub_envs=None):
    """The vector env an :class:`~stepnft.config.EnvConfig` describes, acting in chunks of
    ``n_exec`` actions; sub-env streams seeded from ``seed``. ``perturbations``
    (:class:`~stepnft.envs.perturbations.Perturbations`) replaces the config's training
    randomisation (``env.randomize``), e.g. with a suite's held-out perturbations;
    ``sub_envs``: only those sub-envs (a remote worker's share, see ``Simulator.make_vec_env``)."""
    backend = {} if env_cfg.sim_backend == "cpu" else {"sim_backend": env_cfg.sim_backend}  # ManiSkill's GPU physics
    return simulator_for(env_cfg).make_vec_env(
        env_cfg.tasks, env_cfg.envs_per_task, n_exec, env_cfg.max_episode_steps,
        terminate_on_success=env_cfg.terminate_on_success, seed=seed, num_workers=env_cfg.num_workers,
        sub_envs=sub_envs, **backend, **env_options(env_cfg, perturbations))


def env_options(env_cfg, perturbations=None) -> dict:
    """The chunk-env options an ``EnvConfig`` sets beyond the defaults: ``cameras`` and
    ``image_size``, ``state_obs``, ``reward`` (a shaped reward where the simulator's own is sparse),
    ``perturbations`` (default: its ``randomize`` list, training ranges)."""
    from stepnft.envs.perturbations import Perturbations

    perturbations = Perturbations(tuple(env_cfg.randomize)) if perturbations is None else perturbations
    options: dict = {}
    if env_cfg.cameras:
        options |= {"cameras": list(env_cfg.cameras), "image_size": env_cfg.image_size}
    if env_cfg.state_obs != "full":
        options["state_obs"] = env_cfg.state_obs
    if env_cfg.reward == "shaped" and SIMULATORS[env_cfg.name].reward == "sparse":
        options["reward"] = "shaped"  # where the simulator's own reward is shaped already, it is that one
    if perturbations:
        options["perturbations"] = perturbations
    return options
