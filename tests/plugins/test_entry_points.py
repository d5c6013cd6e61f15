"""Plugins found by entry point (stepnft.plugins): a package installed beside stepnft adds a
simulator, a policy type and an algorithm without editing stepnft, in every process.

The package here is made on disk as pip installs one (the module and its ``.dist-info`` with
``entry_points.txt``) and put on PYTHONPATH of a fresh ``stepnft`` process."""

import os
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest

MODULE = '''
import dataclasses
from dataclasses import dataclass
from typing import ClassVar

from stepnft.algos.stepnft import StepNFT, StepNFTConfig
from stepnft.algos.variants import Variant
from stepnft.envs import SimulatorInfo
from stepnft.envs.bandit import Bandit
from stepnft.policies.flow import FlowPolicy, FlowPolicyConfig

INFO = SimulatorInfo("myplug:MyBandit", 64, ("bandit",), "sparse")


class MyBandit(Bandit):
    name = "mybandit"


@dataclass
class MyPolicyConfig(FlowPolicyConfig):
    type: ClassVar[str] = "mypolicy"
    extra_layers: int = 0


class MyPolicy(FlowPolicy):
    type = "mypolicy"
    config_class = MyPolicyConfig

    def __init__(self, config):
        super().__init__(dataclasses.replace(FlowPolicyConfig(**{k: v for k, v in config.to_dict().items()
                                                                 if k != "extra_layers"}),
                                             num_layers=config.num_layers + config.extra_layers))
        self.config = config


@dataclass
class MyConfig(StepNFTConfig):
    defaults: ClassVar[dict] = {**StepNFTConfig.defaults, "name": "myalgo"}


class MyAlgo(StepNFT):
    config_class = MyConfig


FAST = Variant("myalgo", "myalgo with twice the learning rate", {"lr": 2e-4})
'''


def install(site: Path, entry_points: str, name: str = "myplug", module: str = MODULE) -> Path:
    """Write package ``name`` into ``site`` as an installed distribution with ``entry_points``."""
    site.mkdir(parents=True, exist_ok=True)
    (site / f"{name}.py").write_text(module)
    info = site / f"{name}-0.1.dist-info"
    info.mkdir()
    (info / "METADATA").write_text(f"Metadata-Version: 2.1\nName: {name}\nVersion: 0.1\n")
    (info / "entry_points.txt").write_text(textwrap.dedent(entry_points))
    return site


ENTRY_POINTS = """\
    [stepnft.simulators]
    mybandit = myplug:INFO
    [stepnft.policies]
    mypolicy = myplug:MyPolicy
    [stepnft.algorithms]
    myalgo = myplug:MyAlgo
    [stepnft.variants]
    myalgo-fast = myplug:FAST
    """


def run(site: Path, *argv, code: str | None = None) -> subprocess.CompletedProcess:
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(site), os.environ.get("PYTHONPATH", "")]),
           "MUJOCO_GL": os.environ.get("MUJOCO_GL", "egl")}
    cmd = [sys.executable, "-c", code] if code else [sys.executable, "-m", "stepnft.cli", *map(str, argv)]
    return subprocess.run(cmd, env=env, capture_output=True, text=True, timeout=600)


def test_a_plugin_package_registers_its_parts_under_the_old_registry_names(tmp_path):
    site = install(tmp_path / "site", ENTRY_POINTS)
    done = run(site, code="from stepnft.envs import SIMULATORS, get_simulator\n"
                          "from stepnft.policies.base import POLICY_TYPES, policy_class\n"
                          "from stepnft.algos.base import ALGORITHMS, config_class\n"
                          "assert SIMULATORS['mybandit'].target == 'myplug:MyBandit'\n"
                          "assert get_simulator('mybandit').name == 'mybandit'\n"
                          "assert POLICY_TYPES['mypolicy'] == 'myplug:MyPolicy' and policy_class('mypolicy').type == 'mypolicy'\n"
                          "assert config_class('myalgo')().name == 'myalgo'\n"
                          "assert list(SIMULATORS)[:4] == ['metaworld', 'bandit', 'libero', 'maniskill']\n"
                          "assert SIMULATORS.sources['mybandit'] == 'package myplug'\n"
                          "from stepnft.algos.variants import VARIANTS, variant_config, variant_names\n"
                          "from stepnft.algos.stepnft import StepNFTConfig\n"
                          "assert VARIANTS['myalgo-fast'].algo == 'myalgo' and 'myalgo' in variant_names()\n"
                          "fast = variant_config('myalgo-fast', StepNFTConfig())\n"
                          "assert fast.name == 'myalgo' and fast.lr == 2e-4\n"
                          "assert variant_config('myalgo', StepNFTConfig(lr=3e-4)).lr == 3e-4\n")
    assert done.returncode == 0, done.stderr[-2000:]


def test_a_run_trains_on_a_plugin_simulator_with_a_plugin_algorithm(tmp_path):
    from stepnft.config import save_config
    from stepnft.demo_bandit import bandit_config

    save_config(bandit_config(), tmp_path / "bandit.yaml")
    site = install(tmp_path / "site", ENTRY_POINTS)
    done = run(site, "train", "--config", tmp_path / "bandit.yaml", "--env.name", "mybandit", "--algo.name", "myalgo",
               "--run-dir", tmp_path / "run", "--demos.path", tmp_path / "demos", "--iterations", 2,
               "--episodes-per-iteration", 64, "--env.envs-per-task", 64, "--demos.episodes", 64, "--sft.steps", 20,
               "--eval.episodes", 16, "--eval.during-episodes", 16, "--algo.minibatch-size", 64)
    assert done.returncode == 0, done.stderr[-3000:]
    config = (tmp_path / "run" / "config.yaml").read_text()
    assert "name: mybandit" in config and "name: myalgo" in config
    assert (tmp_path / "run" / "policy" / "model.safetensors").is_file()


def test_a_run_builds_a_plugin_policy_type_from_scratch(tmp_path):
    """--policy.type: a registered type's config gives the --policy.* flags; no --init folder."""
    import json

    from stepnft.config import save_config
    from stepnft.demo_bandit import bandit_config

    save_config(bandit_config(), tmp_path / "bandit.yaml")
    site = install(tmp_path / "site", ENTRY_POINTS)
    done = run(site, "train", "--config", tmp_path / "bandit.yaml", "--policy.type", "mypolicy",
               "--policy.extra-layers", 2, "--run-dir", tmp_path / "run", "--demos.path", tmp_path / "demos",
               "--iterations", 2, "--episodes-per-iteration", 64, "--env.envs-per-task", 64, "--demos.episodes", 64,
               "--sft.steps", 20, "--eval.episodes", 16, "--eval.during-episodes", 16, "--algo.minibatch-size", 64)
    assert done.returncode == 0, done.stderr[-3000:]
    assert "type: mypolicy" in (tmp_path / "run" / "config.yaml").read_text()
    saved = json.loads((tmp_path / "run" / "policy" / "config.json").read_text())
    assert saved["type"] == "mypolicy" and saved["extra_layers"] == 2
    # The run's config.yaml reproduces it, and the saved policy loads by its type.
    again = run(site, "train", "--resume", tmp_path / "run", "--iterations", 3)
    assert again.returncode == 0, again.stderr[-3000:]
    evaluated = run(site, "eval", "--policy", tmp_path / "run" / "policy", "--env.name", "mybandit",
                    "--env.tasks", "bandit", "--env.max-episode-steps", 16, "--eval.episodes", 8)
    assert evaluated.returncode == 0, evaluated.stderr[-3000:]


@pytest.mark.parametrize("entry, message", [
    ("[stepnft.simulators]\nbandit = myplug:INFO\n",
     "stepnft.simulators plugin 'bandit' of package myplug is already registered by stepnft: rename it"),
    ("[stepnft.simulators]\nbroken = myplug:MISSING\n",
     "stepnft.simulators plugin 'broken' of package myplug fails to load (AttributeError"),
    ("[stepnft.simulators]\nwrong = myplug:MyBandit\n",
     "must name a stepnft.envs.SimulatorInfo (whose target is the simulator class), not the class MyBandit"),
    ("[stepnft.algorithms]\nghost = nowhere.at_all:Algo\n",
     "'ghost' (package myplug) cannot be imported from nowhere.at_all:Algo"),
    ("[stepnft.variants]\nwrongv = myplug:MyAlgo\n",
     "stepnft.variants plugin 'wrongv' of package myplug: its entry point must name a stepnft.algos.variants.Variant, "
     "not the class MyAlgo"),
])
def test_a_broken_or_conflicting_plugin_is_one_line_naming_its_package(tmp_path, entry, message):
    site = install(tmp_path / "site", entry)
    argv = (["train", "--algo.name", "ghost", "--run-dir", tmp_path / "run"] if "ghost" in entry else
            ["compare", "--algos", "stepnft,ppo", "--out", tmp_path / "run"] if "wrongv" in entry else
            ["train", "--run-dir", tmp_path / "run"])
    done = run(site, *argv)
    assert done.returncode == 2 and "Traceback" not in done.stderr, done.stderr[-2000:]
    lines = done.stderr.strip().splitlines()
    assert len(lines) == 1 and message in lines[0], lines
    assert not (tmp_path / "run").exists()


def test_two_plugins_claiming_one_name_name_both_packages(tmp_path):
    site = install(tmp_path / "site", "[stepnft.policies]\nsame = myplug:MyPolicy\n")
    install(site, "[stepnft.policies]\nsame = otherplug:Policy\n", name="otherplug", module="")
    done = run(site, code="from stepnft.policies.base import POLICY_TYPES\n'x' in POLICY_TYPES\n")
    assert "plugin 'same' of package otherplug is already registered by package myplug" in done.stderr
