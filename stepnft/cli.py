"""``stepnft`` command line: demos, sft, train, eval, demo-bandit.

Every command's flags are generated from the config dataclasses (``stepnft.config``): tyro
reads them into plain values, then the config is built, and checked, once from them, as a YAML
file is (``stepnft.settings``). ``sft``, ``train`` and ``demo-bandit`` read an
optional ``--config FILE.yaml`` first; every other flag overrides a field of it
(``--algo.lr 1e-4``, ``--env.tasks reach-v3 push-v3``). ``--algo.name`` picks the algorithm,
and the ``--algo.*`` flags are then that algorithm's. Bad input ends with one line on stderr
and exit code 2.
"""

from __future__ import annotations

import argparse
import contextlib
import io
import dataclasses
import json
import re
import signal
import sys
import threading
import typing
from pathlib import Path

COMMANDS = {
    "demos": "generate scripted-expert demonstrations (until N successful episodes per task)",
    "sft": "few-shot flow-matching behaviour cloning on demonstrations, then evaluation",
    "train": "online RL (π-StepNFT by default) from an SFT policy (runs SFT first if --init is not given)",
    "eval": "deterministic (ODE) evaluation of a policy on fixed initial states, with 95 % CIs",
    "demo-bandit": "the core demo: π-StepNFT on a contextual bandit, success per iteration",
    "compare": "algorithms and ablations (PPO, GRPO, ...) from the same SFT start on one env-step budget",
}

CONFIG_SECTIONS = ("env", "demos", "policy", "sft", "algo", "eval", "ray")
"""The sections of ``TrainConfig`` (kept here so ``stepnft --help`` needs no heavy import; a
test checks them against ``TrainConfig``)."""

RENAMED_FLAGS = {
    "demos": {"--out": "--demos.path", "--tasks": "--env.tasks", "--episodes": "--demos.episodes",
              "--seed": "--demos.seed", "--action-noise": "--demos.action-noise",
              "--max-episode-steps": "--env.max-episode-steps"},
    "eval": {"--tasks": "--env.tasks", "--episodes": "--eval.episodes", "--seed": "--eval.seed",
             "--envs-per-task": "--env.envs-per-task", "--max-episode-steps": "--env.max-episode-steps"},
    "demo-bandit": {"--noise-level": "--algo.noise-level", "--target": "--algo.target", "--form": "--algo.form",
                    "--beta": "--algo.beta"},
}
"""Flags of earlier releases, no longer accepted: an error names the flag that replaced each."""


INTERRUPTED = {
    "train": "interrupted; `stepnft train --resume RUN_DIR` continues from the last checkpoint (a run stopped "
             "before its first checkpoint left nothing)",
    "sft": "interrupted; the run folder was removed (an SFT run that did not finish leaves nothing): rerun the command",
    "eval": "interrupted; --out was not written (it holds its earlier results, if any)",
    "demos": "interrupted before the recording began: nothing was written",
    "demo-bandit": "interrupted",
}
"""What an interrupted command left, said when it stops (``demos`` and ``compare`` say it themselves)."""


_WRITERS = contextlib.ExitStack()
"""Locks a command holds until it returns (``stepnft.runs.writer_lock``)."""


class UsageError(Exception):
    """Bad input: reported as one line, exit code 2."""


def _parse(cls, argv: list[str], default, prog: str, description: str | None = None):
    """Parse ``argv`` over ``default`` (an instance of config dataclass ``cls``): tyro turns the
    flags into plain values, then ``cls`` is built, and checked, once from them
    (``stepnft.config.from_dict``). A bad value is a UsageError naming its flag."""
    import tyro

    from stepnft.config import from_dict
    from stepnft.settings import SettingError

    errors = io.StringIO()
    try:
        with _flags_as_values(), contextlib.redirect_stderr(errors):
            values = tyro.cli(cls, args=argv, default=default, prog=prog, description=description or _describe(cls))
    except SystemExit as stop:
        if stop.code not in (0, None):
            message = (_renamed_flag(argv, prog) or _switch_given_a_value(argv, errors.getvalue())
                       or f"{_first_message(errors.getvalue())}; see `{prog} --help`")
            raise UsageError(message) from None
        raise
    policy = getattr(default, "policy", None)
    if isinstance(values.get("policy"), dict) and hasattr(policy, "type"):
        values["policy"] = {"type": policy.type, **values["policy"]}  # the class the flags were parsed for
    try:
        return from_dict(cls, values)
    except SettingError as err:
        raise UsageError(err.as_flags()) from None


@contextlib.contextmanager
def _flags_as_values():
    """Within the block, tyro parses every dataclass (nested sections too) into a dict of its
    field values instead of building it: the help, flags and defaults stay the dataclass's."""
    from tyro.constructors import ConstructorRegistry, StructConstructorSpec

    registry, inside = ConstructorRegistry(), []

    @registry.struct_rule
    def as_values(info):
        if inside or not dataclasses.is_dataclass(info.type):
            return None
        inside.append(info)  # while tyro's own dataclass rule describes the fields
        try:
            spec = ConstructorRegistry.get_struct_spec(info)
        finally:
            inside.pop()
        if not isinstance(spec, StructConstructorSpec):
            return spec
        fields = tuple(dataclasses.replace(f, helptext=_help_with_range(f.helptext, f.type)) for f in spec.fields)
        return dataclasses.replace(spec, instantiate=dict, fields=fields)

    with registry:
        yield


def _help_with_range(helptext, hint) -> str | None:
    """A flag's help with the range its setting declares (``--seed``: "an integer in [0,
    2147483647]"), so ``--help`` states every bound the check enforces."""
    from stepnft.settings import Range, describe

    text = helptext() if callable(helptext) else helptext
    rules = getattr(hint, "__metadata__", ())
    if not any(isinstance(rule, Range) for rule in rules):
        return text
    return f"{text or ''} Takes {describe(hint)}.".strip()


def _renamed_flag(argv: list[str], prog: str) -> str | None:
    """The error for a flag of an earlier release in ``argv``, if there is one."""
    renamed = RENAMED_FLAGS.get(prog.removeprefix("stepnft "), {})
    for flag in (arg.partition("=")[0] for arg in argv):
        if flag in renamed:
            return f"{flag} is now {renamed[flag]} (the flags of earlier releases were removed); see `{prog} --help`"
    return None


def _switch_given_a_value(argv: list[str], box: str) -> str | None:
    """The error for a value after a switch (``--env.terminate-on-success maybe``), if tyro
    refused one: switches take none."""
    unrecognised = re.search(r"Unrecognized options?: (\S+)", " ".join(box.split()))
    token = unrecognised[1] if unrecognised else None
    if token not in argv or argv.index(token) == 0 or not argv[argv.index(token) - 1].startswith("--"):
        return None
    switch = argv[argv.index(token) - 1]
    section, _, name = switch[2:].rpartition(".")
    off = f"--{section}.no-{name}" if section else f"--no-{name}"
    return f"{switch} is a switch and takes no value, got {token!r}: give {switch} to turn it on, {off} to turn it off"


def _first_message(box: str) -> str:
    """The first paragraph of tyro's boxed error message, as one line."""
    lines = []
    for line in box.splitlines()[1:]:
        text = line.strip().strip("│╭╮╰╯").strip()
        if set(text) <= set("─- "):
            if lines:
                break
            continue
        lines.append(text)
    return " ".join(lines) or "invalid arguments"


def _resumable_flags() -> str:
    """The flags ``--resume`` takes (``TrainConfig.resumable`` and ``lengthening``), e.g. ``--ray.*, --device and
    --gradient-checkpointing``."""
    from stepnft.config import TrainConfig

    sections = {k for k, hint in typing.get_type_hints(TrainConfig).items() if dataclasses.is_dataclass(hint)}
    flags = [f"--{k.replace('_', '-')}" + (".*" if k in sections else "")
             for k in TrainConfig.resumable + TrainConfig.lengthening]
    return " and ".join(flags) if len(flags) < 3 else ", ".join(flags[:-1]) + " and " + flags[-1]


def _describe(cls) -> str:
    doc = (cls.__doc__ or "").strip()
    if cls.__name__ == "TrainConfig":
        from stepnft.algos.base import ALGORITHMS

        doc += (f" --algo.name picks the algorithm ({', '.join(ALGORITHMS)}); the --algo.* flags listed are"
                " the chosen one's (`stepnft train --algo.name NAME --help`); --policy.type picks the policy built"
                " when there is no --init (flow by default, or a plugin's type: docs/extending.md), and the"
                " --policy.* flags are then that type's. Extra flags: --config FILE.yaml"
                " (defaults for every flag below; a run's config.yaml reproduces it), --resume RUN_DIR (continue"
                f" the last checkpoint of a run; it takes no other flags than {_resumable_flags()}: a larger"
                " --iterations or --env-step-budget lengthens a finished run).")
    return doc


def _option(argv: list[str], flag: str) -> str | None:
    """The value of option ``flag`` in ``argv`` (argparse: ``--flag V`` or ``--flag=V``), if given."""
    parser = argparse.ArgumentParser(add_help=False, allow_abbrev=False)
    parser.add_argument(flag, dest="value")
    return parser.parse_known_args(argv)[0].value


def _take_option(argv: list[str], flag: str) -> tuple[str | None, list[str]]:
    """The value of option ``flag`` in ``argv`` (``--flag V`` or ``--flag=V``; the last one given)
    and ``argv`` without it."""
    parser = argparse.ArgumentParser(add_help=False, allow_abbrev=False, exit_on_error=False)
    parser.add_argument(flag, dest="value")
    try:
        known, rest = parser.parse_known_args(argv)
    except argparse.ArgumentError:
        raise UsageError(f"{flag} needs a value") from None
    return known.value, rest


def _with_policy_type(base, type_name: str | None):
    """``base`` with a policy config of type ``type_name`` (``--policy.type``) when it names another
    type than ``base``'s: the settings both types declare keep ``base``'s values (the sizes a
    config file set for its simulator), the others take the new type's defaults. A UsageError
    with one line for a type that cannot be built."""
    from stepnft.policies.base import policy_config_class
    from stepnft.settings import SettingError

    if type_name is None or type_name == base.policy.type:
        return base
    try:
        cls = policy_config_class(type_name)
        names = {f.name for f in dataclasses.fields(cls)} & {f.name for f in dataclasses.fields(base.policy)}
        return dataclasses.replace(base, policy=cls(**{name: getattr(base.policy, name) for name in names}))
    except SettingError as err:
        raise UsageError(err.as_flags()) from None
    except ValueError as err:
        raise UsageError(f"--policy.type: {err}") from None


def _config_from_argv(argv: list[str], prog: str, allow_resume: bool, base=None):
    """``--config FILE`` (a YAML file) or ``--resume RUN`` (a run's config.yaml), ``--algo.name``
    (that algorithm's defaults) and ``--policy.type`` (that policy type's defaults) give the
    defaults the other flags are parsed over (else ``base`` or ``TrainConfig()``). Returns
    ``(TrainConfig, resumed)``."""
    from stepnft.algos.base import config_class
    from stepnft.config import TrainConfig, load_config
    from stepnft.settings import SettingError

    pre = argparse.ArgumentParser(add_help=False, allow_abbrev=False)
    pre.add_argument("--config")
    if allow_resume:
        pre.add_argument("--resume")
    known, rest = pre.parse_known_args(argv)
    if getattr(known, "resume", None):
        return _resumed_config(known.resume, known.config, rest, prog), True
    base = load_config(known.config) if known.config else (base or TrainConfig())
    name = _option(rest, "--algo.name")
    if name is not None and name != base.algo.name:
        try:
            base = dataclasses.replace(base, algo=config_class(name)())  # that algorithm's defaults
        except SettingError as err:
            raise UsageError(err.as_flags()) from None
    # policy.type is no field (it is the config's class), so it is taken here, not by the parser.
    type_name, rest = _take_option(rest, "--policy.type")
    return _parse(TrainConfig, rest, _with_policy_type(base, type_name), prog), False


def _resumed_config(run_dir: str, config: str | None, rest: list[str], prog: str):
    """The config of the run in ``run_dir`` (its config.yaml); the flags in ``rest`` may change
    only ``TrainConfig.resumable`` (where the run computes, not what)."""
    from stepnft.config import TrainConfig, load_config

    if config:
        raise UsageError(f"--resume continues a run with its own config.yaml; drop: --config {config}")
    cfg_path = Path(run_dir) / "config.yaml"
    if not cfg_path.is_file():
        raise UsageError(f"cannot resume {run_dir}: no config.yaml there (is it a stepnft run directory?)")
    # The folder may have been moved or copied since its config.yaml was written.
    cfg = dataclasses.replace(load_config(cfg_path), run_dir=run_dir)
    name = _option(rest, "--algo.name")
    type_name, rest = _take_option(rest, "--policy.type")
    same = name in (None, cfg.algo.name) and type_name in (None, cfg.policy.type)
    parsed = _parse(TrainConfig, rest, cfg, prog) if same else None
    skip = TrainConfig.resumable + TrainConfig.lengthening
    switched = (("--algo.name", name, cfg.algo.name), ("--policy.type", type_name, cfg.policy.type))
    changed = ([flag for flag, value, own in switched if value not in (None, own)]
               if parsed is None else _differences(cfg, parsed, skip=skip))
    if changed:
        raise UsageError(f"--resume continues a run with its own config.yaml and takes no other flags than "
                         f"{_resumable_flags()}; drop: {' '.join(changed)}")
    shorter = [f"--{name.replace('_', '-')}" for name in TrainConfig.lengthening
               if None not in (getattr(cfg, name), getattr(parsed, name)) and getattr(parsed, name) < getattr(cfg, name)]
    if shorter:
        raise UsageError(f"--resume can lengthen a run, not shorten it: {' and '.join(shorter)} below the run's own "
                         f"({cfg.iterations} iterations, env_step_budget {cfg.env_step_budget})")
    if parsed.iterations != cfg.iterations and getattr(parsed.algo, "ema_horizon", 0) is None:
        # The EMA schedule rose over the run's own length: keep it, so the decay is what it was.
        parsed = dataclasses.replace(parsed, algo=dataclasses.replace(parsed.algo, ema_horizon=cfg.iterations))
    return parsed


def _differences(before, after, prefix: str = "", skip: tuple[str, ...] = ()) -> list[str]:
    """The flags of the settings that differ between two configs (nested sections included),
    except the fields in ``skip``."""
    flags = []
    for f in dataclasses.fields(after):
        old, new = getattr(before, f.name), getattr(after, f.name)
        if f.name in skip:
            continue
        if dataclasses.is_dataclass(new) and type(old) is type(new):
            flags += _differences(old, new, f"{prefix}{f.name}.")
        elif old != new:
            flags.append("--" + f"{prefix}{f.name}".replace("_", "-"))
    return flags


def _named_folders(*flags: tuple[str, str]) -> None:
    """Folders a command writes into must be named: "" would be the working directory (only
    demo-bandit takes "", for a temporary folder)."""
    for flag, path in flags:
        if not path.strip():
            raise UsageError(f"{flag} must name a folder, got {path!r}")


def _check_rendering(env_cfg, renders: bool) -> None:
    """A command that renders (camera observations, videos) on a simulator that renders through
    MuJoCo's OpenGL checks ``MUJOCO_GL`` once, before any work (``stepnft.envs.rendering``)."""
    from stepnft.envs import SIMULATORS
    from stepnft.envs.rendering import check_gl_platform

    info = SIMULATORS.get(env_cfg.name)
    if renders and info is not None and info.opengl:
        check_gl_platform()


def _renders(cfg) -> bool:
    """Whether a run renders: camera observations, or videos of its final policy."""
    return bool(cfg.env.cameras) or cfg.eval.videos > 0


def cmd_demos(argv: list[str]) -> int:
    from stepnft.data.demos import check_task_episodes, generate_demos
    from stepnft.envs import simulator_for

    from stepnft.config import DemosCommand

    args = _parse(DemosCommand, argv, DemosCommand(), "stepnft demos")
    _named_folders(("--demos.path", args.demos.path))
    _check_rendering(args.env, bool(args.env.cameras))
    sim = simulator_for(args.env)
    tasks = sim.validate_tasks(args.env.tasks)
    check_task_episodes(args.demos, sim)
    episodes = max(args.demos.count(t) for t in tasks)
    # generate_demos checks the folder (new or empty) before it builds an env.
    path = generate_demos(tasks, episodes, args.demos.path, seed=args.demos.seed,
                          action_noise=args.demos.action_noise, dart=args.demos.dart,
                          max_episode_steps=args.env.max_episode_steps,
                          simulator=sim, max_attempts=args.demos.max_attempts, cameras=args.env.cameras,
                          image_size=args.env.image_size, successful_only=args.demos.successful_only)
    discarded = json.loads((path / "manifest.json").read_text())["generator"]["discarded"]
    print(f"wrote {episodes} {'successful ' * args.demos.successful_only}episodes x {len(tasks)} tasks to {path} "
          f"(failed expert attempts discarded: {sum(discarded.values())})")
    return 0


def cmd_sft(argv: list[str]) -> int:
    from stepnft.train import run_sft

    cfg, _ = _config_from_argv(argv, "stepnft sft", allow_resume=False)
    _named_folders(("--run-dir", cfg.run_dir), ("--demos.path", cfg.demos.path))
    _check_rendering(cfg.env, _renders(cfg))
    run_sft(cfg)
    return 0


def cmd_train(argv: list[str]) -> int:
    from stepnft.train import train

    cfg, resume = _config_from_argv(argv, "stepnft train", allow_resume=True)
    _named_folders(("--run-dir", cfg.run_dir), ("--demos.path", cfg.demos.path))
    _check_rendering(cfg.env, _renders(cfg))
    train(cfg, resume=resume)
    return 0


def cmd_eval(argv: list[str]) -> int:
    from stepnft.envs import simulator_for
    from stepnft.envs.base import RenderingError
    from stepnft.policies.base import load_policy
    from stepnft.runs import check_folder, write_atomic
    from stepnft.suites import (check_suites, evaluate_suite, evaluate_suites, format_suite, format_suites,
                                record_suite_videos)

    from stepnft.config import EvalCommand
    from stepnft.devices import resolve_device

    args = _parse(EvalCommand, argv, EvalCommand(), "stepnft eval")
    device = resolve_device(args.device)
    sim = simulator_for(args.env)
    args.env.tasks = sim.validate_tasks(args.env.tasks)
    suites = check_suites(args.suite)
    _check_rendering(args.env, bool(args.video_dir or args.env.cameras or _policy_cameras(args.policy)))
    # Fail on an output that cannot be written before spending time on the policy and episodes.
    out = _eval_out(args.out) if args.out else None
    video_dir = check_folder(args.video_dir, "videos", "--video-dir") if args.video_dir else None
    policy = load_policy(args.policy).to(device)
    _check_samples(policy, args.env, args.eval.seed, args.policy)
    if out:  # one writer of --out (the lock is a hidden file beside it)
        from stepnft.runs import writer_lock

        _WRITERS.enter_context(writer_lock(out.parent, f".{out.name}.lock"))
    if args.eval.episodes > 0:
        if len(suites) == 1:
            result = evaluate_suite(policy, args.env, suites[0], args.eval.episodes, args.eval.seed)
            print(format_suite(result))
        else:
            result = evaluate_suites(policy, args.env, suites, args.eval.episodes, args.eval.seed)
            print(format_suites(result))
        if out:
            write_atomic(out, json.dumps(result, indent=2))
    if video_dir:
        try:
            paths = [p for suite in suites
                     for p in record_suite_videos(policy, args.env, suite, video_dir / suite if len(suites) > 1 else video_dir,
                                                  seed=args.eval.seed, episodes=args.video_episodes)]
        except RenderingError as err:  # the machine, not the input: exit code 1
            print(f"stepnft eval: error: {err}", file=sys.stderr)
            return 1
        print(f"wrote {len(paths)} videos to {video_dir}")
    return 0


def _policy_cameras(path: str) -> list[str]:
    """The cameras of the policy saved at ``path``; none when it cannot be read (that error comes
    later, where the policy is loaded)."""
    from stepnft.policies.base import load_policy_config

    try:
        return list(load_policy_config(path).cameras)
    except (ValueError, OSError):
        return []


def _eval_out(path: str) -> Path:
    """``eval --out``: a new file, or the results of an earlier evaluation (replaced); its folder
    is created and checked writable."""
    from stepnft.runs import prepare_run_dir

    out = Path(path)
    if out.is_dir():
        raise UsageError(f"--out {out} is a folder: give a file name, e.g. --out {out / 'eval.json'}")
    if out.exists() and not _holds_eval_results(out):
        raise UsageError(f"{out} exists and holds no stepnft eval results: choose another --out (a new file)")
    prepare_run_dir(out.parent, flag="--out")
    return out


def _holds_eval_results(path: Path) -> bool:
    try:
        data = json.loads(path.read_text())
    except (OSError, UnicodeDecodeError, ValueError):
        return False
    return isinstance(data, dict) and ("tasks" in data or "suites" in data)


def _check_samples(policy, env_cfg, seed: int, where: str) -> None:
    """Refuse a policy that samples non-finite actions in the first test state of the first
    task (a run that diverged could save one before saved policies were checked): evaluating it
    would feed NaN to the simulator."""
    import torch

    from stepnft.envs import make_vec_env
    from stepnft.policies.base import non_finite_samples
    from stepnft.suites import env_for_policy

    env_cfg = dataclasses.replace(env_for_policy(env_cfg, policy.config), tasks=env_cfg.tasks[:1], envs_per_task=1,
                                  num_workers=0)
    venv = make_vec_env(env_cfg, policy.config.n_exec, seed)
    try:
        obs, _ = venv.reset(seed=[seed])
        raw = {k: torch.as_tensor(v) for k, v in obs.items()} | {"task": torch.as_tensor(venv.task_ids)}
        with policy.processor.bound(venv.instruction_variants):
            bad = non_finite_samples(policy, raw)
    finally:
        venv.close()
    if bad:
        raise ValueError(f"the policy at {where} samples non-finite actions ({', '.join(bad)}) in the first test state: "
                         "it cannot be evaluated (a run that diverged saved it: train again with a smaller --algo.lr)")


def cmd_demo_bandit(argv: list[str]) -> int:
    from stepnft.demo_bandit import bandit_config, run_bandit_demo

    cfg, _ = _config_from_argv(argv, "stepnft demo-bandit", allow_resume=False, base=bandit_config())
    summary = run_bandit_demo(cfg)
    print(f"success {summary['average']['before']:.3f} (SFT) -> {summary['average']['after']:.3f} ({cfg.algo.name})")
    return 0


def cmd_compare(argv: list[str]) -> int:
    from stepnft.compare import CompareCommand, help_text, run_compare
    from stepnft.config import load_config

    cmd = _parse(CompareCommand, argv, CompareCommand(), "stepnft compare", help_text())
    base = load_config(cmd.config)  # its runs render what it renders (--tasks and the rest change nothing of it)
    _check_rendering(base.env, _renders(base))
    return run_compare(cmd)


HANDLERS = {"demos": cmd_demos, "sft": cmd_sft, "train": cmd_train, "eval": cmd_eval, "demo-bandit": cmd_demo_bandit,
            "compare": cmd_compare}


def _usage() -> str:
    rows = "\n".join(f"  {name:<12} {text}" for name, text in COMMANDS.items())
    sections = ", ".join(f"--{name}.*" for name in CONFIG_SECTIONS)
    return (f"usage: stepnft COMMAND [flags]   (stepnft COMMAND --help lists every flag)\n\n"
            f"Online RL fine-tuning of flow-matching robot policies with π-StepNFT.\n\ncommands:\n{rows}\n\n"
            f"sft, train and demo-bandit read --config FILE.yaml, then flags by section: {sections}\n")


def _interrupted(err: BaseException) -> bool:
    """Whether ``err`` is a Ctrl-C (or SIGTERM) that other code turned into another exception:
    ctypes reports a KeyboardInterrupt raised inside a foreign function's argument conversion as
    ``ctypes.ArgumentError("argument 1: KeyboardInterrupt: ")`` (seen when a signal lands while
    MuJoCo's EGL bindings load); others chain it as the cause or context."""
    import ctypes

    seen: set[int] = set()
    while err is not None and id(err) not in seen:
        seen.add(id(err))
        if isinstance(err, KeyboardInterrupt) or (isinstance(err, ctypes.ArgumentError)
                                                  and "KeyboardInterrupt" in str(err)):
            return True
        err = err.__cause__ or err.__context__
    return False


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    if not argv or argv[0] in ("-h", "--help"):
        print(_usage())
        return 0
    command, rest = argv[0], argv[1:]
    if command not in HANDLERS:
        print(f"stepnft: error: unknown command {command!r}; choose one of: {', '.join(HANDLERS)}", file=sys.stderr)
        return 2
    # SIGTERM unwinds like Ctrl-C, so every command's cleanup runs (a run folder that cannot
    # resume is removed, a recording keeps its finished tasks).
    main_thread = threading.current_thread() is threading.main_thread()
    previous = signal.signal(signal.SIGTERM, signal.default_int_handler) if main_thread else None
    try:
        with _WRITERS:
            return HANDLERS[command](rest)
    except SystemExit as stop:  # tyro ends --help with code 0
        return stop.code if isinstance(stop.code, int) else 0 if stop.code is None else 2
    except (UsageError, ValueError, OSError) as err:
        message = str(err).splitlines()[0] if str(err) else type(err).__name__
        print(f"stepnft {command}: error: {message}", file=sys.stderr)
        return 2
    except KeyboardInterrupt as err:  # Ctrl-C, or SIGTERM (above): each command says what is left
        print(f"stepnft {command}: {str(err) or INTERRUPTED.get(command, 'interrupted')}", file=sys.stderr)
        return 130
    except Exception as err:
        if _interrupted(err):  # Ctrl-C inside a foreign call that wrapped it (ctypes, while MuJoCo loads)
            print(f"stepnft {command}: {INTERRUPTED.get(command, 'interrupted')}", file=sys.stderr)
            return 130
        algos = sys.modules.get("stepnft.algos.base")  # imported by the commands that train (with torch)
        if algos is None or not isinstance(err, algos.RunDiverged):
            raise
        print(f"stepnft {command}: error: {err}", file=sys.stderr)
        return 1
    finally:
        if main_thread:
            signal.signal(signal.SIGTERM, previous)


if __name__ == "__main__":
    raise SystemExit(main())
