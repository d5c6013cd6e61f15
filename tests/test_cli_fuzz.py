"""Every flag of every command, fed bad values: one line on stderr, exit code 2, no traceback,
nothing written. The flags and the bad values are generated from the config dataclasses'
declared types and ranges (``stepnft.settings``), so a new flag is covered without a new line
here. Each case runs ``stepnft.cli.main`` in this process, in an empty working directory: the
checks come before any env is built, so a case takes milliseconds."""

from __future__ import annotations

import dataclasses
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
from stepnft.settings import Range


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


def bad_values(hint) -> list[list[str]]:
    """Bad arguments for a flag of declared type ``hint``: the wrong type, non-finite, out of
    its range, empty, unicode."""
    hint, ranges = _unwrap(hint)
    origin, args = typing.get_origin(hint), typing.get_args(hint)
    if hint is bool:
        return [["maybe"]]  # a switch takes no value
    # (Python's int() and float() read some unicode digits, "٣" as 3: not those)
    if hint is int:
        return [[v] for v in ["1.5", "x", "五", "", *_out_of_range(ranges, int)]]
    if hint is float:
        return [[v] for v in ["nan", "inf", "-inf", "∞", "", *_out_of_range(ranges, float)]]
    if origin is Literal:
        return [["nope"], [""], ["é"]]
    if hint is str:
        return [[""]]
    if origin is list and args[0] is str:
        return [["é"]]
    if origin is list:
        return [["-1"], ["x"], ["1.5"]]
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
