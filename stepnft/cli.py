"""``stepnft`` command line: demos, sft, train, eval, demo-bandit.

Config commands read an optional ``--config FILE.yaml`` first; every other flag overrides a
field of it (``--algo.lr 1e-4``, ``--env.tasks reach-v3 push-v3``). Bad input ends with one
line on stderr and exit code 2.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import sys
from dataclasses import dataclass, field
from pathlib import Path

COMMANDS = {
    "demos": "generate scripted-expert demonstrations for MetaWorld tasks",
    "sft": "few-shot flow-matching behaviour cloning on demonstrations, then evaluation",
    "train": "online π-StepNFT from an SFT policy (runs SFT first if --init is not given)",
    "eval": "deterministic (ODE) evaluation of a policy on fixed initial states, with 95 % CIs",
    "demo-bandit": "the core demo: π-StepNFT on a contextual bandit, success per iteration",
}


@dataclass
class DemosArgs:
    """Generate scripted-expert demonstrations (MetaWorld's ENV_POLICY_MAP experts)."""

    out: str = "demos/default"
    """Output folder (manifest.json + one .npz per episode)."""
    tasks: list[str] = field(default_factory=lambda: ["reach-v3", "push-v3", "pick-place-v3", "door-open-v3", "drawer-open-v3"])
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
    tasks: list[str] = field(default_factory=lambda: ["reach-v3", "push-v3", "pick-place-v3", "door-open-v3", "drawer-open-v3"])
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
    import tyro

    return tyro.cli(cls, args=args, default=default, prog=prog, description=_describe(cls))


def _describe(cls) -> str:
    doc = (cls.__doc__ or "").strip()
    if cls.__name__ == "TrainConfig":
        doc += (" Extra flags: --config FILE.yaml (defaults for every flag below; a run's config.yaml"
                " reproduces it), --resume RUN_DIR (continue the last checkpoint of a run; other flags are ignored).")
    return doc


def _config_from_argv(argv: list[str], prog: str, allow_resume: bool):
    """Split off --config / --resume, then let tyro parse the rest over the YAML defaults."""
    from stepnft.config import TrainConfig, load_config

    pre = argparse.ArgumentParser(add_help=False)
    pre.add_argument("--config")
    if allow_resume:
        pre.add_argument("--resume")
    known, rest = pre.parse_known_args(argv)
    resume = getattr(known, "resume", None)
    if resume:
        cfg_path = Path(resume) / "config.yaml"
        if not cfg_path.is_file():
            raise UsageError(f"cannot resume {resume}: no config.yaml there (is it a stepnft run directory?)")
        return load_config(cfg_path), True
    base = load_config(known.config) if known.config else TrainConfig()
    return _tyro(TrainConfig, rest, base, prog), False


def cmd_demos(argv: list[str]) -> int:
    from stepnft.data.demos import generate_demos
    from stepnft.envs.metaworld import validate_tasks

    args = _tyro(DemosArgs, argv, DemosArgs(), "stepnft demos")
    tasks = validate_tasks(args.tasks[0] if len(args.tasks) == 1 else args.tasks)
    from stepnft.train import prepare_run_dir

    prepare_run_dir(args.out)
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
    from stepnft.config import TrainConfig
    from stepnft.envs.metaworld import make_metaworld_vec_env, validate_tasks
    from stepnft.evaluate import evaluate_policy, format_table
    from stepnft.policies.flow import FlowPolicy
    from stepnft.train import language_table

    args = _tyro(EvalArgs, argv, EvalArgs(), "stepnft eval")
    tasks = validate_tasks(args.tasks[0] if len(args.tasks) == 1 else args.tasks)
    policy = FlowPolicy.from_pretrained(args.policy)
    cfg = TrainConfig(language_encoder=args.language_encoder, policy=policy.config)
    venv = make_metaworld_vec_env(tasks, args.envs_per_task, policy.config.n_exec, args.max_episode_steps, seed=args.seed, autoreset=False)
    result = evaluate_policy(policy, venv, language_table(cfg, tasks), args.episodes, args.seed)
    print(format_table(None, result))
    if args.out:
        Path(args.out).write_text(json.dumps(result, indent=2))
    return 0


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
    return (f"usage: stepnft COMMAND [flags]   (stepnft COMMAND --help lists every flag)\n\n"
            f"Online RL fine-tuning of flow-matching robot policies with π-StepNFT.\n\ncommands:\n{rows}\n")


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
    except (UsageError, ValueError, FileNotFoundError) as err:
        message = str(err).splitlines()[0] if str(err) else type(err).__name__
        print(f"stepnft {command}: error: {message}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print(f"stepnft {command}: interrupted; `stepnft train --resume RUN_DIR` continues a training run", file=sys.stderr)
        return 130


if __name__ == "__main__":
    raise SystemExit(main())
