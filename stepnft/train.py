"""The main job: demonstrations -> few-shot SFT -> online π-StepNFT -> evaluation.

Each iteration: Flow-SDE rollouts from the EMA policy (one recorded denoising step per policy
call, terminal-binary labels) -> ``update_epochs`` of π-StepNFT minibatch steps -> EMA update
(SPEC §3–5). The run directory gets ``config.yaml``, ``metrics.jsonl``, TensorBoard logs
(``tb/``), checkpoints, ``learning_curve.png`` and ``summary.json``.
"""

from __future__ import annotations

import json
import math
import time
from pathlib import Path
from typing import Callable

import numpy as np
import torch
from tqdm.auto import tqdm

from stepnft.algos.sft import sft_train
from stepnft.algos.stepnft import stepnft_update
from stepnft.checkpoint import load_checkpoint, save_checkpoint, write_atomic
from stepnft.config import TrainConfig, save_config
from stepnft.data.demos import demos_to_chunks, generate_demos, load_demos
from stepnft.ema import ema_decay, ema_update, make_ema_copy
from stepnft.envs.instructions import instruction_for
from stepnft.envs.metaworld import get_rng_states, make_metaworld_vec_env, set_rng_states, validate_tasks
from stepnft.evaluate import evaluate_policy, format_table
from stepnft.policies.flow import FlowPolicy
from stepnft.policies.language import LanguageEncoder
from stepnft.rollout.collector import concat_transitions, run_wave


def prepare_run_dir(path: str | Path, must_exist: bool = False) -> Path:
    """Create ``path`` and check it is writable; ValueError with one line otherwise."""
    run_dir = Path(path)
    if must_exist and not run_dir.is_dir():
        raise ValueError(f"run directory {run_dir} does not exist: nothing to resume")
    try:
        run_dir.mkdir(parents=True, exist_ok=True)
        probe = run_dir / ".write-test"
        probe.write_text("ok")
        probe.unlink()
    except OSError as err:
        raise ValueError(f"cannot write to {run_dir} ({err.strerror}): choose another --run-dir") from err
    return run_dir


def language_table(cfg: TrainConfig, tasks: list[str], cache_dir: Path | None = None) -> torch.Tensor | None:
    """Instruction embeddings ``[T, L]`` per task (None when the policy takes no language)."""
    if cfg.policy.lang_dim == 0:
        return None
    table = LanguageEncoder(cfg.language_encoder, cache_dir=cache_dir).embed([instruction_for(t) for t in tasks])
    if table.shape[1] != cfg.policy.lang_dim:
        raise ValueError(f"language encoder gives {table.shape[1]}-d embeddings but policy.lang_dim is {cfg.policy.lang_dim}")
    return table


def sft_policy(cfg: TrainConfig, tasks: list[str], lang_table, log: Callable[[str], None]) -> FlowPolicy:
    """Few-shot SFT from the demonstrations (generated first if the folder has none)."""
    path = Path(cfg.demos.path)
    if not (path / "manifest.json").is_file():
        count = max(cfg.demos.count(t) for t in tasks)
        log(f"generating {count} demonstrations per task into {path}")
        generate_demos(tasks, count, path, seed=cfg.demos.seed, action_noise=cfg.demos.action_noise,
                       max_episode_steps=cfg.env.max_episode_steps)
    episodes = [e for e in load_demos(path) if e.task in tasks and e.success]
    per_task = {t: [e for e in episodes if e.task == t][: cfg.demos.count(t)] for t in tasks}
    short = [t for t, eps in per_task.items() if len(eps) < cfg.demos.count(t)]
    if short:
        raise ValueError(f"demonstrations in {path} have too few successful episodes of {short}: "
                         f"run `stepnft demos --tasks ... --episodes N --out {path}` with a larger N")
    data = demos_to_chunks([e for eps in per_task.values() for e in eps], tasks, cfg.policy.horizon)
    if lang_table is not None:
        data["lang"] = lang_table[data["task_id"]]
    policy = FlowPolicy(cfg.policy)
    policy.set_normalization(data["state"])
    gen = torch.Generator().manual_seed(cfg.seed)
    bar = tqdm(total=cfg.sft.steps, desc="SFT", leave=False, mininterval=1.0)
    losses = sft_train(policy, data, cfg.sft, gen, on_step=lambda s, l: (bar.update(1), bar.set_postfix(loss=f"{l:.3f}", refresh=False)))
    bar.close()
    log(f"SFT: {len(data['state'])} chunks from {sum(len(v) for v in per_task.values())} demos, "
        f"loss {np.mean(losses[:50]):.3f} -> {np.mean(losses[-50:]):.3f}")
    return policy


class MetricLogger:
    """Writes each record to ``metrics.jsonl`` and TensorBoard under stable names."""

    def __init__(self, run_dir: Path, resume_iteration: int | None = None):
        from torch.utils.tensorboard import SummaryWriter

        self.path = run_dir / "metrics.jsonl"
        kept = []
        if resume_iteration is not None and self.path.is_file():
            # Drop records written after the checkpoint we resume from: they will be redone.
            kept = [json.loads(l) for l in self.path.read_text().splitlines() if l]
            kept = [r for r in kept if r.get("iteration", 0) <= resume_iteration and not r.get("final")]
        write_atomic(self.path, "".join(json.dumps(r) + "\n" for r in kept))
        # TensorBoard drops the events a killed run wrote past the checkpoint, as above.
        purge_step = max((int(r.get("env_steps", 0)) for r in kept), default=-1) + 1
        self.writer = SummaryWriter(str(run_dir / "tb"), purge_step=purge_step if kept else None)

    def log(self, record: dict) -> None:
        step = int(record.get("env_steps", 0))
        for key, value in record.items():
            if "/" in key and isinstance(value, (int, float)) and math.isfinite(value):
                self.writer.add_scalar(key, value, step)
        with self.path.open("a") as f:
            f.write(json.dumps(record) + "\n")
        self.writer.flush()

    def close(self) -> None:
        self.writer.close()


def plot_learning_curve(run_dir: Path) -> Path:
    """``learning_curve.png``: evaluation and rollout success against env steps."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    records = [json.loads(l) for l in (run_dir / "metrics.jsonl").read_text().splitlines() if l]
    fig, ax = plt.subplots(figsize=(7, 4))
    roll = [(r["env_steps"], r["charts/rollout_success_rate"]) for r in records if "charts/rollout_success_rate" in r]
    ev = [(r["env_steps"], r["charts/success_rate"]) for r in records if "charts/success_rate" in r]
    if roll:
        ax.plot(*zip(*roll), color="tab:gray", alpha=0.6, label="rollout (Flow-SDE, EMA policy)")
    if ev:
        ax.plot(*zip(*ev), "o-", color="tab:blue", label="evaluation (ODE, fixed states)")
    ax.set_xlabel("env steps")
    ax.set_ylabel("success rate")
    ax.set_ylim(-0.02, 1.02)
    ax.grid(alpha=0.3)
    ax.legend(loc="lower right")
    ax.set_title(f"stepnft: {run_dir.name}")
    fig.tight_layout()
    out = run_dir / "learning_curve.png"
    fig.savefig(out, dpi=100)
    plt.close(fig)
    return out


def _start_run(cfg: TrainConfig, resume: bool = False):
    """What ``sft`` and ``train`` both start with: checked tasks, a writable run folder, seeds
    and threads, the instruction table and the vector env (autoreset off: rollout waves and
    evaluations reset it themselves). Returns ``(tasks, run_dir, lang_table, venv)``."""
    tasks = validate_tasks(cfg.env.tasks)
    run_dir = prepare_run_dir(cfg.run_dir, must_exist=resume)
    torch.set_num_threads(cfg.num_threads)
    torch.manual_seed(cfg.seed)
    lang_table = language_table(cfg, tasks, cache_dir=run_dir / "lang_cache")
    venv = make_metaworld_vec_env(tasks, cfg.env.envs_per_task, cfg.policy.n_exec, cfg.env.max_episode_steps,
                                  cfg.env.terminate_on_success, seed=cfg.seed, autoreset=False,
                                  num_workers=cfg.env.num_workers)
    return tasks, run_dir, lang_table, venv


def train(cfg: TrainConfig, resume: bool = False, log: Callable[[str], None] = print) -> dict:
    """Run (or resume) a π-StepNFT run; returns the summary also written to ``summary.json``."""
    tasks, run_dir, lang_table, venv = _start_run(cfg, resume)
    make_opt = lambda p: torch.optim.AdamW(p.parameters(), lr=cfg.algo.lr, betas=(0.9, 0.95), weight_decay=cfg.algo.weight_decay)  # noqa: E731
    gen = torch.Generator().manual_seed(cfg.seed)
    waves_per_iter = math.ceil(cfg.episodes_per_iteration / venv.num_envs)
    horizon = cfg.algo.ema_horizon or cfg.iterations

    def evaluate(policy, episodes):
        bar = tqdm(total=1, desc=f"eval {episodes}/task", leave=False)
        def progress(done, total):
            bar.total = total
            bar.n = done
            bar.refresh()
        res = evaluate_policy(policy, venv, lang_table, episodes, cfg.eval.seed, progress=progress)
        bar.close()
        return res

    if resume:
        ckpt = load_checkpoint(run_dir, make_opt)
        policy, ema, optimizer, state = ckpt["policy"], ckpt["ema"], ckpt["optimizer"], ckpt["state"]
        gen.set_state(ckpt["rng"]["generator"])
        torch.set_rng_state(ckpt["rng"]["torch"])
        set_rng_states(venv, state["env_rng"])
        start_it, env_steps, before = state["iteration"], state["env_steps"], state["before"]
        log(f"resuming {run_dir} from iteration {start_it} ({env_steps} env steps)")
    else:
        if (run_dir / "checkpoints" / "LATEST").is_file():
            raise ValueError(f"{run_dir} already holds a run with checkpoints: continue it with "
                             f"`stepnft train --resume {run_dir}`, or choose another --run-dir")
        save_config(cfg, run_dir / "config.yaml")
        policy = FlowPolicy.from_pretrained(cfg.init) if cfg.init else sft_policy(cfg, tasks, lang_table, log)
        if policy.config != cfg.policy:
            # The envs, language table and config.yaml were built for cfg.policy.
            raise ValueError(f"--init policy {cfg.init} was built with other policy settings than this run's: "
                             f"pass the same --policy.* flags it was trained with (see its config.json)")
        policy.save_pretrained(run_dir / "sft_policy")
        ema = make_ema_copy(policy)
        optimizer = make_opt(policy)
        start_it, env_steps = 0, 0
        before = evaluate(policy, cfg.eval.episodes)
        log("before RL:\n" + format_table(None, before))
    logger = MetricLogger(run_dir, resume_iteration=start_it if resume else None)
    if not resume:
        logger.log({"iteration": 0, "env_steps": 0, "charts/success_rate": before["average"],
                    **{f"eval/{t}": r["success"] for t, r in before["tasks"].items()}})

    t_start = time.perf_counter()
    out_of_budget = lambda: cfg.env_step_budget is not None and env_steps >= cfg.env_step_budget  # noqa: E731
    iteration = start_it
    bar = tqdm(range(start_it, cfg.iterations), desc="π-StepNFT", initial=start_it, total=cfg.iterations)
    for it in bar:
        if out_of_budget():  # a resumed run that had already spent its budget
            break
        t0 = time.perf_counter()
        ema.eval()
        waves = [run_wave(ema, venv, lang_table, cfg.algo.noise_level, gen, record=True,
                          stochastic_steps=cfg.algo.sde_steps, record_steps=cfg.algo.record_steps) for _ in range(waves_per_iter)]
        batch = concat_transitions(waves)
        if lang_table is not None:
            batch["lang"] = lang_table[batch["task_id"]]
        del batch["env_index"]
        rollout_steps = int(sum(w.length.sum() for w in waves))
        env_steps += rollout_steps
        t1 = time.perf_counter()
        policy.train()
        metrics = stepnft_update(policy, optimizer, batch, cfg.algo, gen)
        decay = ema_decay(it, horizon, cfg.algo.ema_base, cfg.algo.ema_target)
        ema_update(ema, policy, decay)
        t2 = time.perf_counter()
        success = np.concatenate([w.success for w in waves])
        record = {
            "iteration": it + 1, "env_steps": env_steps,
            "charts/rollout_success_rate": float(success.mean()),
            "charts/pos_sample_frac": metrics.pop("pos_frac"),
            "charts/ema_decay": decay,
            "charts/SPS": rollout_steps / max(t1 - t0, 1e-9),
            "charts/samples": int(batch["y"].shape[0]),
            "time/rollout_s": t1 - t0, "time/update_s": t2 - t1,
            **{f"losses/{k}": v for k, v in metrics.items()},
        }
        iteration = it + 1
        last = iteration == cfg.iterations or out_of_budget()
        if cfg.eval.every and (it + 1) % cfg.eval.every == 0 and not last:
            ev = evaluate(ema if cfg.eval.use_ema else policy, cfg.eval.during_episodes)
            record["charts/success_rate"] = ev["average"]
            record.update({f"eval/{t}": r["success"] for t, r in ev["tasks"].items()})
        logger.log(record)
        bar.set_postfix(rollout=f"{record['charts/rollout_success_rate']:.2f}",
                        eval=f"{record.get('charts/success_rate', float('nan')):.2f}",
                        dv=f"{metrics['delta_v_norm']:.3f}", refresh=False)
        if (it + 1) % cfg.checkpoint_every == 0 or last:
            state = {"env_steps": env_steps, "before": before, "env_rng": get_rng_states(venv)}
            save_checkpoint(run_dir, it + 1, policy, ema, optimizer, state,
                            {"generator": gen.get_state(), "torch": torch.get_rng_state()})
        if last:
            break
    bar.close()

    final_policy = ema if cfg.eval.use_ema else policy
    after = evaluate(final_policy, cfg.eval.episodes)
    final_policy.save_pretrained(run_dir / "policy")
    logger.log({"iteration": iteration, "env_steps": env_steps, "charts/success_rate": after["average"], "final": True,
                **{f"eval/{t}": r["success"] for t, r in after["tasks"].items()}})
    logger.close()
    plot_learning_curve(run_dir)
    summary = {
        "tasks": {t: {"before": before["tasks"][t], "after": after["tasks"][t]} for t in tasks},
        "average": {"before": before["average"], "after": after["average"]},
        "eval_episodes_per_task": cfg.eval.episodes, "env_steps": env_steps,
        "wall_clock_s_this_session": time.perf_counter() - t_start, "seed": cfg.seed, "iterations": iteration,
    }
    write_atomic(run_dir / "summary.json", json.dumps(summary, indent=2))
    log("before -> after:\n" + format_table(before, after))
    venv.close()
    return summary


def run_sft(cfg: TrainConfig, log: Callable[[str], None] = print) -> dict:
    """``stepnft sft``: few-shot SFT on the demonstrations, saved to ``RUN/policy``, then evaluated."""
    tasks, run_dir, lang_table, venv = _start_run(cfg)
    save_config(cfg, run_dir / "config.yaml")
    policy = sft_policy(cfg, tasks, lang_table, log)
    policy.save_pretrained(run_dir / "policy")
    result = evaluate_policy(policy, venv, lang_table, cfg.eval.episodes, cfg.eval.seed)
    venv.close()
    write_atomic(run_dir / "summary.json", json.dumps({"sft": result}, indent=2))
    log("SFT policy:\n" + format_table(None, result))
    return result
