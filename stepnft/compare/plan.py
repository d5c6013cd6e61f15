"""What a comparison runs: the base run config with the command's overrides
(:func:`comparison_config`), one SFT job per seed and one RL job per variant and seed
(:func:`plan`), the suite evaluation of each of their policies (:func:`suite_job`), and the
record of the shared settings in ``OUT/compare.json`` that a rerun must match."""

from __future__ import annotations

import dataclasses
import json
import math
from dataclasses import dataclass
from pathlib import Path

from stepnft.algos.base import AlgoConfig
from stepnft.algos.variants import variant_config
from stepnft.compare.command import CompareCommand
from stepnft.config import TrainConfig, from_dict, load_config, to_dict
from stepnft.data.demos import check_task_episodes
from stepnft.envs import simulator_for
from stepnft.runs import check_folder, write_atomic

SFT = "sft"
"""The row of the SFT start in the report."""


@dataclass
class Job:
    """One subprocess: the SFT of a seed, a variant's RL run or the suites of a policy."""

    name: str
    """``sft_seedS``, ``VARIANT_seedS`` or ``suites_ROW_seedS``: its config, log and status key."""
    kind: str
    """``sft``, ``train`` or ``eval`` (the suites of a finished policy)."""
    run_dir: Path
    config: object
    """The TrainConfig it starts from (``eval``: its ``stepnft`` arguments)."""


def comparison_config(base: TrainConfig, cmd: CompareCommand) -> TrainConfig:
    """``base`` with the command's overrides set on the fields that declare them (``--tasks``:
    ``env.tasks``, ``--env-steps``: ``env_step_budget``, ``--eval-episodes``: ``eval.episodes``),
    so those sections check them; then what every run of a comparison shares: one torch thread
    and enough iterations that the budget ends every run (an episode costs at least one env
    step). The base config's ``init``, if any, is the policy every seed's SFT starts from (``stepnft
    sft --init``: e.g. a new SmolVLA folder); every RL run starts from its seed's SFT policy."""
    try:
        cfg = dataclasses.replace(
            base, env_step_budget=base.env_step_budget if cmd.env_steps is None else cmd.env_steps,
            env=dataclasses.replace(base.env, tasks=cmd.tasks) if cmd.tasks else base.env,
            eval=base.eval if cmd.eval_episodes is None else dataclasses.replace(base.eval, episodes=cmd.eval_episodes))
    except ValueError as err:
        raise ValueError(f"{err} (--tasks, --env-steps and --eval-episodes set env.tasks, env_step_budget and "
                         "eval.episodes)") from None
    sim = simulator_for(cfg.env)
    sim.validate_tasks(cfg.env.tasks)
    check_task_episodes(cfg.demos, sim)
    if cfg.env_step_budget is None:
        raise ValueError("a comparison needs one env-step budget: pass --env-steps N (or set env_step_budget in --config)")
    if cfg.eval.episodes < 1:
        raise ValueError("a comparison evaluates every run: --eval-episodes (eval.episodes) must be >= 1")
    iterations = max(cfg.iterations, math.ceil(cfg.env_step_budget / cfg.episodes_per_iteration))
    return dataclasses.replace(cfg, num_threads=1, iterations=iterations)


def plan(cmd: CompareCommand) -> tuple[list[Job], list[Job], Path]:
    """Check the settings and build the jobs: ``(SFT jobs, RL jobs, comparison folder)``."""
    loaded = load_config(cmd.config)
    base = comparison_config(loaded, cmd)
    # As given (relative to the working directory, as every run's --run-dir): the saved configs
    # then move with the folder.
    out = check_folder(cmd.out, "comparison", "--out")  # a new folder, or the comparison to resume
    defaults = comparison_settings(TrainConfig(algo=type(base.algo)()))
    check_same_settings(out / "compare.json", comparison_settings(base), defaults)
    overrides = cmd.variant_overrides()
    check_variant_settings(out / "compare.json", overrides, out / "runs", cmd.algos)
    sft_jobs, run_jobs = [], []
    for seed in cmd.seeds:
        sft_dir = out / "sft" / f"seed{seed}"
        demos = dataclasses.replace(base.demos, seed=seed, path=str(out / "demos" / f"seed{seed}"))
        sft_cfg = dataclasses.replace(base, seed=seed, run_dir=str(sft_dir), demos=demos)
        sft_jobs.append(Job(f"sft_seed{seed}", "sft", sft_dir, sft_cfg))
        for name in cmd.algos:
            algo = variant_config(name, base.algo)
            if getattr(algo, "ema_horizon", 0) is None:  # π-StepNFT's EMA schedule: the base config's iterations
                algo = dataclasses.replace(algo, ema_horizon=loaded.iterations)
            if name in overrides:  # --variant-set, checked as a config file's algo section is
                try:
                    algo = from_dict(AlgoConfig, to_dict(algo) | overrides[name], "algo.")
                except (ValueError, TypeError) as err:
                    raise ValueError(f"--variant-set {name}: {err}") from None
            run_dir = out / "runs" / name / f"seed{seed}"
            cfg = dataclasses.replace(sft_cfg, run_dir=str(run_dir), init=str(sft_dir / "policy"), algo=algo)
            run_jobs.append(Job(f"{name}_seed{seed}", "train", run_dir, cfg))
    return sft_jobs, run_jobs, out


def suite_job(cmd: CompareCommand, job: Job, out: Path) -> Job:
    """The suite evaluation of ``job``'s final policy (``stepnft eval --suite ...``)."""
    row = SFT if job.kind == "sft" else job.name.rsplit("_seed", 1)[0]
    run_dir = out / "suites" / row / f"seed{job.config.seed}"
    argv = ["eval", "--policy", str(job.run_dir / "policy"), "--suite", *cmd.suites,
            "--eval.episodes", str(cmd.suite_episodes), "--eval.seed", str(job.config.eval.seed),
            "--out", str(run_dir / "suites.json"), *env_flags(job.config.env),
            *(["--device", job.config.device] if job.config.device != "cpu" else [])]
    return Job(f"suites_{row}_seed{job.config.seed}", "eval", run_dir, argv)


def env_flags(env) -> list[str]:
    """Command-line flags that rebuild ``env`` (fields left at their defaults are omitted)."""
    default = type(env)()
    flags = []
    for f in dataclasses.fields(env):
        value = getattr(env, f.name)
        if value == getattr(default, f.name):
            continue
        flag = "--env." + f.name.replace("_", "-")
        if isinstance(value, bool):
            flags.append(flag if value else "--env.no-" + f.name.replace("_", "-"))
        elif isinstance(value, (list, tuple)):
            flags += [flag, *map(str, value)] if value else []
        else:
            flags += [flag, str(value)]
    return flags


def comparison_settings(base: TrainConfig) -> dict:
    """What every run of the comparison shares (``OUT/compare.json``): the config without the
    per-run fields (run folder, seed, the demonstrations' folder and seed); ``init`` is the SFT
    start (the RL runs' own is their seed's SFT policy)."""
    settings = to_dict(base)
    for per_run in ("run_dir", "seed"):
        settings.pop(per_run)
    if settings.get("init") is None:  # as comparisons recorded it before init could be set
        settings.pop("init", None)
    settings["demos"] = {k: v for k, v in settings["demos"].items() if k not in ("path", "seed")}
    return settings


def check_variant_settings(path: Path, overrides: dict, runs: Path, algos: list[str]) -> None:
    """Record ``--variant-set`` of the compared ``algos`` in ``compare.json`` (``variant_set``),
    or check a rerun asks for the same: a variant's settings may change only while it has no run
    folder under ``runs``. Variants a rerun does not compare keep what was recorded for them."""
    recorded = json.loads(path.read_text())
    old = recorded.get("variant_set", {})
    new = {v: s for v, s in old.items() if v not in algos} | json.loads(json.dumps(overrides))
    changed = sorted(v for v in old.keys() | new.keys() if old.get(v) != new.get(v))
    started = [v for v in changed if (runs / v).exists()]
    if started:
        raise ValueError(f"{path.parent} ran {', '.join(started)} with other --variant-set settings "
                         f"({', '.join(f'{v}: {old.get(v, {})}' for v in started)}): rerun with those, or delete "
                         f"{', '.join(str(runs / v) for v in started)} to rerun it with the new ones")
    if changed:
        recorded.pop("variant_set", None)
        write_atomic(path, json.dumps(recorded | ({"variant_set": new} if new else {}), indent=2))


def _flat(tree: dict, prefix: str = "") -> dict:
    flat = {}
    for k, v in tree.items():
        flat |= _flat(v, f"{prefix}{k}.") if isinstance(v, dict) else {f"{prefix}{k}": v}
    return flat


def check_same_settings(path: Path, settings: dict, defaults: dict | None = None) -> None:
    """Record the comparison's settings, or check a rerun asks for the same ones. A setting the
    recorded file lacks (one added to the code since) counts as the same if the rerun leaves it
    at its default (``defaults``: the settings of a default config)."""
    settings = json.loads(json.dumps(settings))  # tuples as lists, as they come back from disk
    if not path.is_file():
        write_atomic(path, json.dumps(settings, indent=2))
        return
    recorded = json.loads(path.read_text())
    recorded.pop("variant_set", None)  # checked by check_variant_settings
    old, new = _flat(recorded), _flat(settings)
    default = _flat(json.loads(json.dumps(defaults))) if defaults else {}
    diff = sorted(k for k in old.keys() | new.keys() if old.get(k) != new.get(k)
                  and not (k not in old and k in default and new.get(k) == default[k]))
    if diff:
        raise ValueError(f"{path.parent} holds a comparison with other settings (differs in: {', '.join(diff)}): "
                         "rerun it with its own --config and flags (algorithms and seeds may be added), or choose "
                         "another --out")
