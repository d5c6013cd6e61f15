"""``stepnft`` command line: demos, sft, train, eval, demo-bandit.

Config commands read an optional ``--config FILE.yaml`` first; every other flag overrides a
field of it (``--algo.lr 1e-4``, ``--env.tasks reach-v3 push-v3``). Bad input ends with one
line on stderr and exit code 2.
"""

from __future__ import annotations

import argparse
import contextlib
import dataclasses
import json
import sys
import typing
from dataclasses import dataclass, field
from pathlib import Path

from stepnft.envs import DEFAULT_TASKS

COMMANDS = {
    "demos": "generate scripted-expert demonstrations for MetaWorld tasks",
    "sft": "few-shot flow-matching behaviour cloning on demonstrations, then evaluation",
    "train": "online π-StepNFT from an SFT policy (runs SFT first if --init is not given)",
    "eval": "deterministic (ODE) evaluation of a policy on fixed initial states, with 95 % CIs",
    "demo-bandit": "the core demo: π-StepNFT on a contextual bandit, success per iteration",
}

CONFIG_SECTIONS = ("env", "demos", "policy", "sft", "algo", "eval")
"""The sections of ``TrainConfig`` (kept here so ``stepnft --help`` needs no heavy import)."""


@dataclass
class DemosArgs:
    """Generate scripted-expert demonstrations (MetaWorld's ENV_POLICY_MAP experts)."""

    out: str = "demos/default"
    """Output folder (manifest.json + one .npz per episode)."""
    tasks: list[str] = field(default_factory=lambda: list(DEFAULT_TASKS))
    """MetaWorld v3 task names (space- or comma-separated)."""
    episodes: int = 5
    """Episodes per task."""
    seed: int = 0
    """Seed of the initial states (disjoint from evaluation states)."""
    action_noise: float = 0.0
    """Std of Gaussian noise added to the expert's actions."""
    max_episode_steps: int = 200
    """Episode cap in env steps."""


@dataclass
class EvalArgs:
    """Evaluate a saved policy on a fixed, seeded set of initial states (ODE sampling)."""

    policy: str = "runs/stepnft/policy"
    """Policy folder (config.json + model.safetensors), e.g. RUN/policy or RUN/sft_policy."""
    tasks: list[str] = field(default_factory=lambda: list(DEFAULT_TASKS))
    """MetaWorld v3 task names."""
    episodes: int = 100
    """Episodes per task (>= 100 for reported figures)."""
    seed: int = 0
    """Episode e starts from initial state seed + e (same set for every checkpoint)."""
    envs_per_task: int = 4
    """Parallel simulators per task."""
    max_episode_steps: int = 200
    """Episode cap in env steps."""
    language_encoder: str = "default"
    """Frozen sentence encoder ('default' or a local folder); must match training."""
    out: str | None = None
    """Also write the results as JSON to this file."""
    video_dir: str | None = None
    """Also record ODE episodes as ``DIR/<task>_ep<e>_<success|fail>.mp4`` (needs offscreen
    rendering: MUJOCO_GL=egl)."""
    video_episodes: int = 1
    """Episodes recorded per task with --video-dir (episode e starts from eval state seed + e)."""

    def __post_init__(self) -> None:
        if self.episodes < 0 or self.video_episodes < 1:
            raise ValueError(f"episodes must be >= 0 (0: no evaluation) and video_episodes >= 1, "
                             f"got {self.episodes} and {self.video_episodes}")


@dataclass
class BanditArgs:
    """π-StepNFT on a contextual bandit: SFT on biased demos, then RL; prints success per iteration."""

    seed: int = 0
    """Seed."""
    iterations: int = 30
    """RL iterations."""
    noise_level: float = 0.3
    """Flow-SDE noise level a (0: ODE rollouts, the exploration ablation)."""
    target: str = "next"
    """'next' (step-wise, paper) or 'x0' (final-action ablation)."""
    form: str = "rank"
    """'rank' (paper) or 'wmse' (weighted-MSE ablation)."""
    beta: float = 1.0
    """Trust factor of the mirrored candidates."""


class UsageError(Exception):
    """Bad input: reported as one line, exit code 2."""


def _tyro(cls, args, default, prog):
    """Parse ``args`` over ``default`` into ``cls``; a bad value raises ValueError.

    tyro reports a ValueError raised while it builds a nested section (``--algo.lr -1``) in a
    box of its own, so sections are built unvalidated and their checks run after parsing.
    """
    import tyro

    with _validation_deferred(cls):
        parsed = tyro.cli(cls, args=args, default=default, prog=prog, description=_describe(cls))
    _validate(parsed)
    return parsed


def _section_classes(cls) -> set[type]:
    """``cls`` and the dataclasses of its nested sections."""
    found = {cls}
    for hint in typing.get_type_hints(cls).values():
        if dataclasses.is_dataclass(hint) and hint not in found:
            found |= _section_classes(hint)
    return found


@contextlib.contextmanager
def _validation_deferred(cls):
    """Within the block, ``cls`` and its sections skip their ``__post_init__`` checks."""
    saved = {c: c.__dict__["__post_init__"] for c in _section_classes(cls) if "__post_init__" in c.__dict__}
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
        doc += (" Extra flags: --config FILE.yaml (defaults for every flag below; a run's config.yaml"
                " reproduces it), --resume RUN_DIR (continue the last checkpoint of a run; it takes no other flags).")
    return doc


def _config_from_argv(argv: list[str], prog: str, allow_resume: bool):
    """Split off --config / --resume, then let tyro parse the rest over the YAML defaults."""
    from stepnft.config import TrainConfig, load_config

    pre = argparse.ArgumentParser(add_help=False, allow_abbrev=False)
    pre.add_argument("--config")
    if allow_resume:
        pre.add_argument("--resume")
    known, rest = pre.parse_known_args(argv)
    resume = getattr(known, "resume", None)
    if resume and not any(a in ("-h", "--help") for a in rest):
        if rest or known.config:
            extra = " ".join(rest + (["--config", known.config] if known.config else []))
            raise UsageError(f"--resume continues a run with its own config.yaml and takes no other flags; drop: {extra}")
        cfg_path = Path(resume) / "config.yaml"
        if not cfg_path.is_file():
            raise UsageError(f"cannot resume {resume}: no config.yaml there (is it a stepnft run directory?)")
        cfg = load_config(cfg_path)
        cfg.run_dir = resume  # the folder may have been moved or copied since it was written
        return cfg, True
    base = load_config(known.config) if known.config else TrainConfig()
    return _tyro(TrainConfig, rest, base, prog), False


def cmd_demos(argv: list[str]) -> int:
    from stepnft.data.demos import generate_demos
    from stepnft.envs.metaworld import validate_tasks

    args = _tyro(DemosArgs, argv, DemosArgs(), "stepnft demos")
    tasks = validate_tasks(args.tasks[0] if len(args.tasks) == 1 else args.tasks)
    _writable_dir(args.out, "--out")
    path = generate_demos(tasks, args.episodes, args.out, seed=args.seed, action_noise=args.action_noise,
                          max_episode_steps=args.max_episode_steps)
    print(f"wrote {args.episodes} episodes x {len(tasks)} tasks to {path}")
    return 0


def cmd_sft(argv: list[str]) -> int:
    from stepnft.train import run_sft

    cfg, _ = _config_from_argv(argv, "stepnft sft", allow_resume=False)
    run_sft(cfg)
    return 0


def cmd_train(argv: list[str]) -> int:
    from stepnft.train import train

    cfg, resume = _config_from_argv(argv, "stepnft train", allow_resume=True)
    train(cfg, resume=resume)
    return 0


def cmd_eval(argv: list[str]) -> int:
    from stepnft.checkpoint import write_atomic
    from stepnft.config import TrainConfig
    from stepnft.envs.metaworld import make_metaworld_vec_env, validate_tasks
    from stepnft.evaluate import RenderingError, evaluate_policy, format_table, record_videos
    from stepnft.policies.flow import FlowPolicy
    from stepnft.train import language_table

    args = _tyro(EvalArgs, argv, EvalArgs(), "stepnft eval")
    tasks = validate_tasks(args.tasks[0] if len(args.tasks) == 1 else args.tasks)
    policy = FlowPolicy.from_pretrained(args.policy)
    # Fail on an unwritable output before spending time on episodes.
    out = _writable_dir(Path(args.out).parent, "--out") / Path(args.out).name if args.out else None
    video_dir = _writable_dir(args.video_dir, "--video-dir") if args.video_dir else None
    cfg = TrainConfig(language_encoder=args.language_encoder, policy=policy.config)
    lang_table = language_table(cfg, tasks)
    if args.episodes > 0:
        venv = make_metaworld_vec_env(tasks, args.envs_per_task, policy.config.n_exec, args.max_episode_steps,
                                      seed=args.seed, autoreset=False)
        result = evaluate_policy(policy, venv, lang_table, args.episodes, args.seed)
        venv.close()
        print(format_table(None, result))
        if out:
            write_atomic(out, json.dumps(result, indent=2))
    if video_dir:
        try:
            paths = record_videos(policy, tasks, video_dir, lang_table, seed=args.seed, episodes=args.video_episodes,
                                  max_episode_steps=args.max_episode_steps)
        except RenderingError as err:  # the machine, not the input: exit code 1
            print(f"stepnft eval: error: {err}", file=sys.stderr)
            return 1
        print(f"wrote {len(paths)} videos to {video_dir}")
    return 0


def _writable_dir(path: str | Path, flag: str) -> Path:
    """Create folder ``path`` if needed and check a file can be written there."""
    from stepnft.train import prepare_run_dir

    try:
        return prepare_run_dir(path)
    except ValueError as err:
        reason = getattr(err.__cause__, "strerror", None) or err
        raise UsageError(f"cannot write to {path} ({reason}): choose another {flag}") from err


def cmd_demo_bandit(argv: list[str]) -> int:
    from stepnft.demo_bandit import BanditDemoConfig, run_bandit_demo, with_overrides

    args = _tyro(BanditArgs, argv, BanditArgs(), "stepnft demo-bandit")
    cfg = with_overrides(dataclasses.replace(BanditDemoConfig(), seed=args.seed, iterations=args.iterations),
                         noise_level=args.noise_level, target=args.target, form=args.form, beta=args.beta)
    history = run_bandit_demo(cfg)
    print(f"success {history[0]['success']:.3f} (SFT) -> {history[-1]['success']:.3f} (π-StepNFT)")
    return 0


HANDLERS = {"demos": cmd_demos, "sft": cmd_sft, "train": cmd_train, "eval": cmd_eval, "demo-bandit": cmd_demo_bandit}


def _usage() -> str:
    rows = "\n".join(f"  {name:<12} {text}" for name, text in COMMANDS.items())
    sections = ", ".join(f"--{name}.*" for name in CONFIG_SECTIONS)
    return (f"usage: stepnft COMMAND [flags]   (stepnft COMMAND --help lists every flag)\n\n"
            f"Online RL fine-tuning of flow-matching robot policies with π-StepNFT.\n\ncommands:\n{rows}\n\n"
            f"sft and train read --config FILE.yaml, then flags by section: {sections}\n")


def main(argv: list[str] | None = None) -> int:
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
    except SystemExit as stop:
        # tyro ends --help with code 0 and its own argument errors (after printing them) with 2.
        return stop.code if isinstance(stop.code, int) else 0 if stop.code is None else 2
    except (UsageError, ValueError, OSError) as err:
        message = str(err).splitlines()[0] if str(err) else type(err).__name__
        print(f"stepnft {command}: error: {message}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print(f"stepnft {command}: interrupted; `stepnft train --resume RUN_DIR` continues a training run", file=sys.stderr)
        return 130


if __name__ == "__main__":
    raise SystemExit(main())
