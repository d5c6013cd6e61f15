"""``stepnft`` command line: demos, sft, train, eval, demo-bandit.

Every command's flags are generated from the config dataclasses (``stepnft.config``): one
schema, the same checks for flags and YAML. ``sft``, ``train`` and ``demo-bandit`` read an
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
import sys
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
"""The sections of ``TrainConfig`` (kept here so ``stepnft --help`` needs no heavy import)."""

LEGACY_FLAGS = {
    "demos": {"--out": "--demos.path", "--tasks": "--env.tasks", "--episodes": "--demos.episodes",
              "--seed": "--demos.seed", "--action-noise": "--demos.action-noise",
              "--max-episode-steps": "--env.max-episode-steps"},
    "eval": {"--tasks": "--env.tasks", "--episodes": "--eval.episodes", "--seed": "--eval.seed",
             "--envs-per-task": "--env.envs-per-task", "--max-episode-steps": "--env.max-episode-steps"},
    "demo-bandit": {"--noise-level": "--algo.noise-level", "--target": "--algo.target", "--form": "--algo.form",
                    "--beta": "--algo.beta"},
}
"""Flags of earlier releases, still accepted: each is the same as the flag it maps to."""


class UsageError(Exception):
    """Bad input: reported as one line, exit code 2."""


def _parse(cls, argv: list[str], default, prog: str, description: str | None = None):
    """Parse ``argv`` over ``default`` into ``cls``; a bad value raises ValueError.

    tyro reports a ValueError raised while it builds a nested section (``--algo.lr -1``) in a
    box of its own, so sections are built unvalidated and their checks run after parsing.
    """
    import tyro

    errors = io.StringIO()
    try:
        with _validation_deferred(default), contextlib.redirect_stderr(errors):
            parsed = tyro.cli(cls, args=argv, default=default, prog=prog, description=description or _describe(cls))
    except SystemExit as stop:
        if stop.code not in (0, None):
            raise UsageError(f"{_first_message(errors.getvalue())}; see `{prog} --help`") from None
        raise
    _validate(parsed)
    return parsed


def _first_message(box: str) -> str:
    """The first paragraph of tyro's boxed error message, as one line."""
    lines = []
    for line in box.splitlines()[1:]:
        text = line.strip().strip("│╭╮╰╯").strip()
        if set(text) <= set("─ "):
            if lines:
                break
            continue
        lines.append(text)
    return " ".join(lines) or "invalid arguments"


def _section_classes(obj) -> set[type]:
    """The classes of ``obj`` and of its nested sections, and their bases."""
    found = {c for c in type(obj).__mro__ if dataclasses.is_dataclass(c)}
    for f in dataclasses.fields(obj):
        value = getattr(obj, f.name)
        if dataclasses.is_dataclass(value):
            found |= _section_classes(value)
    return found


@contextlib.contextmanager
def _validation_deferred(default):
    """Within the block, the config classes skip their ``__post_init__`` checks."""
    saved = {c: c.__dict__["__post_init__"] for c in _section_classes(default) if "__post_init__" in c.__dict__}
    for c in saved:
        c.__post_init__ = lambda self: None
    try:
        yield
    finally:
        for c, check in saved.items():
            c.__post_init__ = check


def _validate(obj) -> None:
    """Run the ``__post_init__`` checks of ``obj``'s sections, innermost first, then its own."""
    for f in dataclasses.fields(obj):
        value = getattr(obj, f.name)
        if dataclasses.is_dataclass(value):
            _validate(value)
    check = getattr(obj, "__post_init__", None)
    if check is not None:
        check()


def _describe(cls) -> str:
    doc = (cls.__doc__ or "").strip()
    if cls.__name__ == "TrainConfig":
        from stepnft.algos.base import ALGORITHMS

        doc += (f" --algo.name picks the algorithm ({', '.join(ALGORITHMS)}); the --algo.* flags listed are"
                " the chosen one's (`stepnft train --algo.name NAME --help`). Extra flags: --config FILE.yaml"
                " (defaults for every flag below; a run's config.yaml reproduces it), --resume RUN_DIR (continue"
                " the last checkpoint of a run; it takes no other flags than --ray.* and --device).")
    return doc


def _translate_legacy(argv: list[str], command: str) -> list[str]:
    table = LEGACY_FLAGS.get(command, {})
    out = []
    for arg in argv:
        flag, eq, value = arg.partition("=")
        out.append(table[flag] + eq + value if flag in table else arg)
    return out


def _algo_name(argv: list[str]) -> str | None:
    """The value of ``--algo.name`` in ``argv``, if given."""
    for i, arg in enumerate(argv):
        if arg.startswith("--algo.name="):
            return arg.split("=", 1)[1]
        if arg == "--algo.name" and i + 1 < len(argv):
            return argv[i + 1]
    return None


def _train_config_from_argv(argv: list[str], prog: str, allow_resume: bool, base=None):
    """Split off --config / --resume, then parse the rest over the YAML (or ``base``) defaults.
    Returns ``(TrainConfig, resume)``."""
    from stepnft.algos.base import config_class
    from stepnft.config import TrainConfig, load_config

    pre = argparse.ArgumentParser(add_help=False, allow_abbrev=False)
    pre.add_argument("--config")
    if allow_resume:
        pre.add_argument("--resume")
    known, rest = pre.parse_known_args(argv)
    resume = getattr(known, "resume", None)
    if resume and not any(a in ("-h", "--help") for a in rest):
        if (rest and not rest[0].startswith(("--ray.", "--device"))) or known.config:
            extra = " ".join(rest + (["--config", known.config] if known.config else []))
            raise UsageError(f"--resume continues a run with its own config.yaml and takes no other flags "
                             f"than --ray.* and --device; drop: {extra}")
        cfg_path = Path(resume) / "config.yaml"
        if not cfg_path.is_file():
            raise UsageError(f"cannot resume {resume}: no config.yaml there (is it a stepnft run directory?)")
        cfg = load_config(cfg_path)
        cfg.run_dir = resume  # the folder may have been moved or copied since it was written
        if rest:  # --ray.* and --device say where a run computes, not what: a run may resume elsewhere
            parsed = _parse(TrainConfig, rest, cfg, prog)
            if dataclasses.replace(parsed, ray=cfg.ray, device=cfg.device) != cfg:
                raise UsageError(f"--resume takes no other flags than --ray.* and --device; drop: {' '.join(rest)}")
            cfg = parsed
        return cfg, True
    base = load_config(known.config) if known.config else (base or TrainConfig())
    name = _algo_name(rest)
    if name is not None and name != base.algo.name:
        base = dataclasses.replace(base, algo=config_class(name)())  # that algorithm's defaults
    return _parse(TrainConfig, rest, base, prog), False


def _config_from_argv(argv: list[str], prog: str, allow_resume: bool):
    return _train_config_from_argv(argv, prog, allow_resume)


def cmd_demos(argv: list[str]) -> int:
    from stepnft.data.demos import generate_demos
    from stepnft.envs import get_simulator

    from stepnft.config import DemosCommand

    args = _parse(DemosCommand, _translate_legacy(argv, "demos"), DemosCommand(), "stepnft demos")
    sim = get_simulator(args.env.name)
    tasks = sim.validate_tasks(args.env.tasks)
    _writable_dir(args.demos.path, "--demos.path")
    path = generate_demos(tasks, args.demos.episodes, args.demos.path, seed=args.demos.seed,
                          action_noise=args.demos.action_noise, max_episode_steps=args.env.max_episode_steps,
                          simulator=sim, max_attempts=args.demos.max_attempts, cameras=args.env.cameras,
                          image_size=args.env.image_size)
    discarded = json.loads((path / "manifest.json").read_text())["generator"]["discarded"]
    print(f"wrote {args.demos.episodes} successful episodes x {len(tasks)} tasks to {path} "
          f"(failed expert attempts discarded: {sum(discarded.values())})")
    return 0


def cmd_sft(argv: list[str]) -> int:
    from stepnft.train import run_sft

    cfg, _ = _train_config_from_argv(argv, "stepnft sft", allow_resume=False)
    run_sft(cfg)
    return 0


def cmd_train(argv: list[str]) -> int:
    from stepnft.train import train

    cfg, resume = _train_config_from_argv(argv, "stepnft train", allow_resume=True)
    train(cfg, resume=resume)
    return 0


def cmd_eval(argv: list[str]) -> int:
    from stepnft.envs import get_simulator
    from stepnft.envs.base import RenderingError
    from stepnft.policies.base import load_policy
    from stepnft.runs import write_atomic
    from stepnft.suites import (check_suites, evaluate_suite, evaluate_suites, format_suite, format_suites,
                                record_suite_videos)

    from stepnft.config import EvalCommand
    from stepnft.devices import resolve_device

    args = _parse(EvalCommand, _translate_legacy(argv, "eval"), EvalCommand(), "stepnft eval")
    device = resolve_device(args.device)
    sim = get_simulator(args.env.name)
    args.env.tasks = sim.validate_tasks(args.env.tasks)
    suites = check_suites(args.suite)
    policy = load_policy(args.policy).to(device)
    # Fail on an unwritable output before spending time on episodes.
    out = _writable_dir(Path(args.out).parent, "--out") / Path(args.out).name if args.out else None
    video_dir = _writable_dir(args.video_dir, "--video-dir") if args.video_dir else None
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


def _writable_dir(path: str | Path, flag: str) -> Path:
    """Create folder ``path`` if needed and check a file can be written there."""
    from stepnft.runs import prepare_run_dir

    try:
        return prepare_run_dir(path)
    except ValueError as err:
        reason = getattr(err.__cause__, "strerror", None) or err
        raise UsageError(f"cannot write to {path} ({reason}): choose another {flag}") from err


def cmd_demo_bandit(argv: list[str]) -> int:
    from stepnft.demo_bandit import bandit_config, run_bandit_demo

    cfg, _ = _train_config_from_argv(_translate_legacy(argv, "demo-bandit"), "stepnft demo-bandit",
                                     allow_resume=False, base=bandit_config())
    summary = run_bandit_demo(cfg)
    print(f"success {summary['average']['before']:.3f} (SFT) -> {summary['average']['after']:.3f} ({cfg.algo.name})")
    return 0


def cmd_compare(argv: list[str]) -> int:
    from stepnft.compare import CompareCommand, help_text, run_compare

    return run_compare(_parse(CompareCommand, argv, CompareCommand(), "stepnft compare", help_text()))


HANDLERS = {"demos": cmd_demos, "sft": cmd_sft, "train": cmd_train, "eval": cmd_eval, "demo-bandit": cmd_demo_bandit,
            "compare": cmd_compare}


def _usage() -> str:
    rows = "\n".join(f"  {name:<12} {text}" for name, text in COMMANDS.items())
    sections = ", ".join(f"--{name}.*" for name in CONFIG_SECTIONS)
    return (f"usage: stepnft COMMAND [flags]   (stepnft COMMAND --help lists every flag)\n\n"
            f"Online RL fine-tuning of flow-matching robot policies with π-StepNFT.\n\ncommands:\n{rows}\n\n"
            f"sft, train and demo-bandit read --config FILE.yaml, then flags by section: {sections}\n")


def main(argv: list[str] | None = None) -> int:
    from stepnft.algos.base import RunDiverged

    argv = sys.argv[1:] if argv is None else argv
    if not argv or argv[0] in ("-h", "--help"):
        print(_usage())
        return 0
    command, rest = argv[0], argv[1:]
    if command not in HANDLERS:
        print(f"stepnft: error: unknown command {command!r}; choose one of: {', '.join(HANDLERS)}", file=sys.stderr)
        return 2
    try:
        return HANDLERS[command](rest)
    except SystemExit as stop:  # tyro ends --help with code 0
        return stop.code if isinstance(stop.code, int) else 0 if stop.code is None else 2
    except (UsageError, ValueError, OSError) as err:
        message = str(err).splitlines()[0] if str(err) else type(err).__name__
        print(f"stepnft {command}: error: {message}", file=sys.stderr)
        return 2
    except RunDiverged as err:
        print(f"stepnft {command}: error: {err}", file=sys.stderr)
        return 1
    except KeyboardInterrupt:
        print(f"stepnft {command}: interrupted; `stepnft train --resume RUN_DIR` continues a training run", file=sys.stderr)
        return 130


if __name__ == "__main__":
    raise SystemExit(main())
