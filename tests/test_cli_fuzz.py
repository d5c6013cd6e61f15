"""Every flag of every command, fed bad values: one line on stderr, exit code 2, no traceback,
nothing written. The flags and the bad values are generated from the config dataclasses'
declared types and ranges (``stepnft.settings``), so a new flag is covered without a new line
here. Each case runs ``stepnft.cli.main`` in this process, in an empty working directory: the
checks come before any env is built, so a case takes milliseconds."""

from __future__ import annotations

import ctypes.util
import dataclasses
import os
import re
import subprocess
import sys
import typing
from types import UnionType
from typing import Literal, Union

import pytest

import stepnft.compare
import stepnft.data.demos
import stepnft.envs.base
from stepnft.algos.base import ALGORITHMS, AlgoConfig, config_class
from stepnft.cli import main
from stepnft.compare import CompareCommand
from stepnft.config import DemosCommand, EvalCommand, TrainConfig
from stepnft.policies.flow import FlowPolicy, FlowPolicyConfig
from stepnft.settings import SETTINGS_FILE_BYTES_MAX, Range


def flags(cls, prefix: str = "") -> list[tuple[str, object]]:
    """``(flag, declared type)`` of every field of config dataclass ``cls``, sections included."""
    hints = typing.get_type_hints(cls, include_extras=True)
    found = []
    for f in dataclasses.fields(cls):
        name = f"{prefix}{f.name}"
        if dataclasses.is_dataclass(hints[f.name]):
            found += flags(hints[f.name], name + ".")
        else:
            found.append(("--" + name.replace("_", "-"), hints[f.name]))
    return found


def _unwrap(hint) -> tuple[object, list[Range]]:
    """``(type, ranges)`` of a declared type, ``X | None`` as ``X`` ("None" is a good value)."""
    ranges = []
    if typing.get_origin(hint) is typing.Annotated:
        ranges = [r for r in hint.__metadata__ if isinstance(r, Range)]
        hint = hint.__origin__
    if typing.get_origin(hint) in (Union, UnionType):
        hint = next(a for a in typing.get_args(hint) if a is not type(None))
    return hint, ranges


def _out_of_range(ranges: list[Range], number: type) -> list[str]:
    values = []
    for r in ranges:
        values += [str(number(b)) for b in (r.gt, r.lt) if b is not None]
        values += [str(number(r.ge - 1))] if r.ge is not None else []
        values += [str(number(r.le + 1))] if r.le is not None else []
    return values


EXTREME = {int: [str(2**70), str(-(2**70))], float: ["1e308", "-1e308"]}
"""The "extreme value" row of every numeric flag: past every bound and every C integer (a seed of
2**70 once reached numpy as an OverflowError, 3e9 episodes a 22 GiB allocation)."""


def bad_values(hint) -> list[list[str]]:
    """Bad arguments for a flag of declared type ``hint``: the wrong type, non-finite, out of
    its range, empty, unicode."""
    hint, ranges = _unwrap(hint)
    origin, args = typing.get_origin(hint), typing.get_args(hint)
    if hint is bool:
        return [["maybe"]]  # a switch takes no value
    # (Python's int() and float() read some unicode digits, "٣" as 3: not those)
    if hint is int:
        return [[v] for v in ["1.5", "x", "五", "", *_out_of_range(ranges, int), *EXTREME[int]]]
    if hint is float:
        return [[v] for v in ["nan", "inf", "-inf", "∞", "", *_out_of_range(ranges, float), *EXTREME[float]]]
    if origin is Literal:
        return [["nope"], [""], ["é"]]
    if hint is str:
        return [[""]]
    if origin is list and args[0] is str:
        return [["é"]]
    if origin is list:
        return [["-1"], ["x"], ["1.5"], *([v] for v in EXTREME.get(args[0], []))]
    if origin is tuple:
        inner = bad_values(args[0])
        return [["0.5"], ["x", "y"]] + [[v[0], "0.5"] for v in inner if v and v[0]]
    if origin is dict:
        return [["reach-v3", "x"], ["reach-v3", "0"], ["nope-v3", "2"], ["reach-v3"]]
    raise AssertionError(f"no bad values for {hint!r}: add them here")


SHARED_ALGO_FLAGS = {flag for flag, _ in flags(AlgoConfig, "algo.")}
"""The flags every algorithm has (``AlgoConfig``'s): fed through ``TrainConfig``'s cases."""

COMMANDS = {
    # command: (its config dataclass, flags left out with the reason, every bad value or the first only)
    "demos": (DemosCommand, {"--env.cameras": "the scene names its cameras: checked when the first env is built, "
                                              "after the progress bar started (the folder is removed again)"}, True),
    "train": (TrainConfig, {"--algo.name": "a name, not a setting: an unknown one is a case of tests/test_cli.py"}, True),
    # the same parser as train's (stepnft.cli._config_from_argv): one bad value per flag
    "sft": (TrainConfig, {"--algo.name": "as for train"}, False),
    "demo-bandit": (TrainConfig, {"--algo.name": "as for train", "--run-dir": "'' is the demo's temporary folder",
                                  "--demos.path": "'' is the demo's temporary folder"}, False),
    "eval": (EvalCommand, {}, True),
    "compare": (CompareCommand, {}, True),
}


@pytest.fixture(scope="module")
def inputs(tmp_path_factory):
    """A tiny saved policy (for eval) and a comparison config, outside the working directory."""
    root = tmp_path_factory.mktemp("fuzz-inputs")
    FlowPolicy(FlowPolicyConfig(lang_dim=0, hidden_dim=8, num_layers=1)).save_pretrained(root / "policy")
    (root / "compare.yaml").write_text("env_step_budget: 100\nenv:\n  tasks: [reach-v3]\n")
    return root


def base_argv(command: str, flag: str, inputs) -> list[str]:
    """What makes the command valid but for the flag under test."""
    if command == "eval" and flag != "--policy":
        return ["--policy", str(inputs / "policy")]
    if command == "compare" and flag != "--config":
        return ["--config", str(inputs / "compare.yaml")]
    return []


class PastTheChecks(BaseException):
    """A command began its work (built an env, ran jobs): a bad value was not refused at start."""


@pytest.fixture(autouse=True)
def no_work(monkeypatch):
    """Every command's work starts by building an env (demonstrations: in ``_record_task``) or,
    for compare, by scheduling its jobs: stop there, so a missed check fails in milliseconds."""
    def stop(*args, **kwargs):
        raise PastTheChecks

    for target in (stepnft.envs.base.ChunkVecEnv, stepnft.envs.base.ShardedChunkVecEnv):
        monkeypatch.setattr(target, "__init__", stop)
    monkeypatch.setattr(stepnft.data.demos, "_record_task", stop)
    monkeypatch.setattr(stepnft.compare, "schedule", stop)


def failures(capsys, cwd, command: str, argv: list[str], flag: str, values: list[str]) -> list[str]:
    """What is wrong with how ``stepnft COMMAND argv`` ended (nothing: []); ``flag`` was given
    the bad ``values``."""
    try:
        code = main([command, *argv])
    except PastTheChecks:
        code = "none: the command got past its checks and began its work"
    out, err = capsys.readouterr()
    lines = err.strip().splitlines()
    wrong = []
    if code != 2:
        wrong.append(f"exit code {code}")
    if "Traceback" in err or len(lines) != 1 or not lines[0].startswith(f"stepnft {command}: error: "):
        wrong.append(f"stderr {err[-300:]!r}")
    elif not (flag in lines[0] or flag[2:].replace("-", "_") in lines[0] or any(repr(v) in lines[0] for v in values)):
        wrong.append(f"the message names neither {flag} nor the value: {lines[0]!r}")
    written = sorted(p.name for p in cwd.iterdir())
    if written:
        wrong.append(f"wrote {written}")
    return [f"stepnft {command} {' '.join(argv)}: {w}" for w in wrong]


@pytest.mark.parametrize("command", COMMANDS)
def test_bad_values_of_every_flag_are_one_line_exit_2_and_write_nothing(capsys, tmp_path, monkeypatch, inputs, command):
    cls, skipped, every_value = COMMANDS[command]
    monkeypatch.chdir(tmp_path)
    found, tried = [], 0
    for flag, hint in flags(cls):
        if flag in skipped:
            continue
        for values in bad_values(hint)[:None if every_value else 1]:
            argv = [*base_argv(command, flag, inputs), flag, *values]
            found += failures(capsys, tmp_path, command, argv, flag, values)
            tried += 1
    assert tried > 10 and not found, "\n".join(found)


@pytest.mark.parametrize("algo", ALGORITHMS)
def test_bad_values_of_every_algorithm_flag_are_one_line_exit_2_too(capsys, tmp_path, monkeypatch, algo):
    monkeypatch.chdir(tmp_path)
    found = []
    for flag, hint in flags(config_class(algo), "algo."):
        if flag not in SHARED_ALGO_FLAGS:
            for values in bad_values(hint):
                found += failures(capsys, tmp_path, "train", ["--algo.name", algo, flag, *values], flag, values)
    assert not found, "\n".join(found)


def _number_type(hint) -> type | None:
    """int or float for a numeric flag (a list of numbers too), else None."""
    hint, _ = _unwrap(hint)
    if typing.get_origin(hint) is list:
        hint = typing.get_args(hint)[0]
    return hint if hint in (int, float) else None


@pytest.mark.parametrize("command", ["demos", "train", "eval", "compare"])
def test_extreme_values_are_refused_naming_the_flag_and_its_range(capsys, tmp_path, monkeypatch, inputs, command):
    """Not an OverflowError's words ("Overflow when unpacking long long") nor a MemoryError: one
    line that names the flag and the range it takes, exit 2, nothing written."""
    cls, skipped, _ = COMMANDS[command]
    monkeypatch.chdir(tmp_path)
    found, tried = [], 0
    for flag, hint in flags(cls):
        number = _number_type(hint)
        if flag in skipped or number is None:
            continue
        for value in EXTREME[number]:
            argv = [*base_argv(command, flag, inputs), flag, value]
            code = main([command, *argv])
            err = capsys.readouterr().err.strip()
            named = flag in err or flag[2:].replace("-", "_") in err
            if code != 2 or "\n" in err or not named or not re.search(r"in [\[(]|at most", err) or any(tmp_path.iterdir()):
                found.append(f"stepnft {command} {' '.join(argv)}: exit {code}, {err[-300:]!r}")
            tried += 1
    assert tried >= 8 and not found, "\n".join(found)


def bad_config_files(root) -> dict[str, object]:
    """Config files no command should read through: name -> path."""
    from test_settings import billion_laughs  # the same documents as the loader's own tests

    files = {"billion-laughs.yaml": billion_laughs(), "recursive.yaml": "env: &a {tasks: *a}\n",
             "deep.yaml": "env: " + "[" * 50_000 + "]" * 50_000 + "\n",
             "huge.yaml": "seed: 1\n" + "#" * SETTINGS_FILE_BYTES_MAX}
    for name, text in files.items():
        (root / name).write_text(text)
    (root / "latin1.yaml").write_bytes("seed: 1 # é\n".encode("latin-1"))
    return {name: root / name for name in [*files, "latin1.yaml"]}


@pytest.mark.parametrize("command", ["train", "sft", "demo-bandit", "compare", "resume"])
def test_config_files_that_expand_nest_or_weigh_too_much_are_one_line_exit_2(capsys, tmp_path, monkeypatch,
                                                                               tmp_path_factory, command):
    root = tmp_path_factory.mktemp("configs")
    monkeypatch.chdir(tmp_path)
    found = []
    for name, path in bad_config_files(root).items():
        if command == "resume":  # a run folder whose config.yaml is the bad file
            run = root / f"run-{name}"
            run.mkdir()
            (run / "config.yaml").write_bytes(path.read_bytes())
            argv = ["--resume", str(run)]
        else:
            argv = ["--config", str(path)]
        found += failures(capsys, tmp_path, "train" if command == "resume" else command, argv, "--config", [name])
    assert not found, "\n".join(found)


@pytest.fixture
def camera_commands(inputs, tmp_path_factory):
    """Commands that render (camera observations or videos), each refused or begun at its start."""
    root = tmp_path_factory.mktemp("rendering")
    (root / "camera.yaml").write_text("env_step_budget: 100\nenv:\n  tasks: [reach-v3]\n  cameras: [corner]\n"
                                      "policy:\n  cameras: [corner]\n")
    return {
        "eval --video-dir": ["eval", "--policy", str(inputs / "policy"), "--video-dir", "videos"],
        "train --env.cameras": ["train", "--env.cameras", "corner", "--policy.cameras", "corner"],
        "train --eval.videos": ["train", "--eval.videos", "1"],
        "sft --env.cameras": ["sft", "--env.cameras", "corner", "--policy.cameras", "corner"],
        "demos --env.cameras": ["demos", "--env.cameras", "corner"],
        "compare (camera config)": ["compare", "--config", str(root / "camera.yaml")],
    }


GL_CASES = {
    # name: (environment, whether OSMesa's library is found, what the line must say)
    "bogus": ({"MUJOCO_GL": "bogus", "PYOPENGL_PLATFORM": None}, True, "MUJOCO_GL='bogus' is not a GL platform stepnft renders with: choose one of egl, osmesa, glfw"),
    "osmesa without OSMesa": ({"MUJOCO_GL": "osmesa", "PYOPENGL_PLATFORM": None}, False, "MUJOCO_GL=osmesa needs libOSMesa, which is not installed: apt-get install libosmesa6"),
    "glfw without a display": ({"MUJOCO_GL": "glfw", "DISPLAY": None, "WAYLAND_DISPLAY": None, "PYOPENGL_PLATFORM": None},
                               True,
                               "MUJOCO_GL=glfw renders through a window and no display is set"),
    "PyOpenGL contradicts": ({"MUJOCO_GL": "egl", "PYOPENGL_PLATFORM": "osmesa"}, True,
                             "PYOPENGL_PLATFORM='osmesa' contradicts MUJOCO_GL='egl'"),
}


@pytest.mark.parametrize("case", GL_CASES)
def test_a_gl_platform_that_cannot_render_is_one_line_at_start_for_every_command_that_renders(
        capsys, tmp_path, monkeypatch, camera_commands, case):
    environment, osmesa_found, expected = GL_CASES[case]
    for name, value in environment.items():
        monkeypatch.delenv(name, raising=False) if value is None else monkeypatch.setenv(name, value)
    find_library = ctypes.util.find_library
    monkeypatch.setattr(ctypes.util, "find_library", lambda lib: None if lib == "OSMesa" and not osmesa_found
                        else "libOSMesa.so.8" if lib == "OSMesa" else find_library(lib))
    monkeypatch.chdir(tmp_path)
    found = []
    for name, argv in camera_commands.items():
        try:
            code = main(argv)
        except PastTheChecks:
            code = "none: it began its work"
        err = capsys.readouterr().err.strip()
        if code != 2 or "\n" in err or expected not in err or any(tmp_path.iterdir()):
            found.append(f"{name}: exit {code}, {err[-300:]!r}, wrote {sorted(p.name for p in tmp_path.iterdir())}")
    assert not found, "\n".join(found)


@pytest.mark.parametrize("value", [None, ""], ids=["unset", "empty"])
def test_an_unset_or_empty_gl_platform_renders_offscreen_with_egl(capsys, tmp_path, monkeypatch, inputs, value):
    monkeypatch.delenv("MUJOCO_GL", raising=False) if value is None else monkeypatch.setenv("MUJOCO_GL", value)
    monkeypatch.delenv("PYOPENGL_PLATFORM", raising=False)
    monkeypatch.chdir(tmp_path)
    with pytest.raises(PastTheChecks):  # past the check: it builds its env (where this test stops it)
        main(["eval", "--policy", str(inputs / "policy"), "--video-dir", "videos"])
    assert os.environ["MUJOCO_GL"] == "egl"


def test_a_platform_that_passes_the_names_but_cannot_draw_is_one_line_without_teardown_noise(tmp_path, inputs):
    """GLFW with a display that does not exist: the probe's frame fails; MuJoCo's half-built
    renderer must not print its teardown tracebacks, nor GLFW its warnings."""
    env = {**os.environ, "MUJOCO_GL": "glfw", "DISPLAY": ":987"}
    env.pop("PYOPENGL_PLATFORM", None)
    done = subprocess.run([sys.executable, "-m", "stepnft.cli", "eval", "--policy", str(inputs / "policy"),
                           "--env.tasks", "reach-v3", "--video-dir", str(tmp_path / "videos")],
                          env=env, capture_output=True, text=True, timeout=120)
    assert done.returncode == 2, done.stderr
    assert done.stderr.startswith("stepnft eval: error: MUJOCO_GL=glfw cannot render here (")
    assert len(done.stderr.strip().splitlines()) == 1, done.stderr
    assert not (tmp_path / "videos").exists()


def test_a_camera_renderer_that_fails_later_says_so_without_teardown_noise(tmp_path):
    """Past the start check (a renderer built elsewhere, a worker): RenderingError, and nothing
    of MuJoCo's teardown on stderr."""
    code = ("import metaworld, mujoco\n"
            "from stepnft.envs.base import RenderingError\n"
            "from stepnft.envs.metaworld.camera import CameraRenderer\n"
            "model = mujoco.MjModel.from_xml_string('<mujoco><worldbody><camera name=\"c\"/></worldbody></mujoco>')\n"
            "try:\n    CameraRenderer(model, ['c'], 16, 16)\nexcept RenderingError as err:\n    print('refused:', err)\n")
    env = {**os.environ, "MUJOCO_GL": "glfw", "DISPLAY": ":987"}
    done = subprocess.run([sys.executable, "-W", "ignore", "-c", code], env=env, capture_output=True, text=True,
                          timeout=120)
    assert done.returncode == 0 and done.stdout.startswith("refused: offscreen rendering failed"), done
    assert "Traceback" not in done.stderr and "Exception ignored" not in done.stderr, done.stderr
