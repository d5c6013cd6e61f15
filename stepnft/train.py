"""The training loop: demonstrations -> few-shot SFT -> online RL -> evaluation, for any
registered algorithm, simulator and policy.

Each iteration: the collector plays episodes with the algorithm's acting policy -> the
algorithm updates -> its end-of-iteration step (π-StepNFT: the EMA update). The run folder gets
``config.yaml``, ``metrics.jsonl``, TensorBoard logs, checkpoints, ``learning_curve.png`` and
``summary.json`` (``stepnft.runs``).
"""

from __future__ import annotations

import json
import time
from contextlib import ExitStack
from pathlib import Path
from typing import Callable

import torch
from tqdm.auto import tqdm

from stepnft import distributed
from stepnft.algos.base import make_algorithm
from stepnft.algos.sft import sft_from_demos
from stepnft.checkpoint import load_checkpoint, save_checkpoint
from stepnft.config import TrainConfig, save_config
from stepnft.envs import get_simulator, make_vec_env
from stepnft.evaluate import evaluate_policy, format_table
from stepnft.policies.base import Policy, load_policy
from stepnft.rollout.collector import Collector
from stepnft.runs import MetricLogger, plot_learning_curve, prepare_run_dir, refuse_existing_run, write_atomic


def train(cfg: TrainConfig, resume: bool = False, log: Callable[[str], None] = print) -> dict:
    """Run (or resume) a training run; returns the summary also written to ``summary.json``.
    Under ``torchrun`` rank 0 runs it and the other processes share its updates (``_follow``)."""
    if distributed.init() and distributed.rank() > 0:
        return _follow(cfg)
    with ExitStack() as stack:
        stack.callback(distributed.close)
        run_dir, sim, tasks, collector = _start_run(cfg, stack, resume)
        evaluate = _evaluator(collector, cfg.eval.seed)
        if resume:
            ckpt = load_checkpoint(run_dir)
            policy, state = ckpt["policy"], ckpt["state"]
        else:
            save_config(cfg, run_dir / "config.yaml")
            policy = _initial_policy(cfg, sim, tasks, run_dir, log)
            policy.save_pretrained(run_dir / "sft_policy")
        policy.processor.bind_instructions(collector.venv.instructions, run_dir / "lang_cache")
        algo = make_algorithm(cfg.algo, policy, cfg.iterations, torch.Generator().manual_seed(cfg.seed))
        if resume:
            algo.load_state_dict(state["algorithm"])
            algo.generator.set_state(state["algorithm_generator"])
            collector.load_state_dict(state["collector"])
            torch.set_rng_state(state["torch_rng"])
            start, env_steps, before = state["iteration"], state["env_steps"], state["before"]
            log(f"resuming {run_dir} from iteration {start} ({env_steps} env steps)")
        else:
            start, env_steps = 0, 0
            before = evaluate(policy, cfg.eval.episodes)
            log("before RL:\n" + format_table(None, before))
        if distributed.world_size() > 1:
            distributed.broadcast((policy, algo.state_dict(), algo.generator.get_state()))
        logger = MetricLogger(run_dir, resume_iteration=start if resume else None)
        stack.callback(logger.close)
        if not resume:
            logger.log({"iteration": 0, "env_steps": 0, **_eval_record(before)})

        t_start, last_eval, iteration = time.perf_counter(), before["average"] if not resume else None, start
        out_of_budget = lambda: cfg.env_step_budget is not None and env_steps >= cfg.env_step_budget  # noqa: E731
        bar = stack.enter_context(tqdm(range(start, cfg.iterations), desc=cfg.algo.name, initial=start,
                                       total=cfg.iterations))
        for it in bar:
            if out_of_budget():  # a resumed run that had already spent its budget
                break
            t0 = time.perf_counter()
            batch = collector.collect(algo.acting_policy(), cfg.episodes_per_iteration, algo.rollout)
            env_steps += batch.env_steps
            distributed.broadcast((batch, it))
            t1 = time.perf_counter()
            metrics = algo.update(batch)
            metrics |= algo.end_iteration(it)
            t2 = time.perf_counter()
            iteration = it + 1
            record = {"iteration": iteration, "env_steps": env_steps,
                      "charts/rollout_success_rate": float(batch.episode_success.double().mean()),
                      "charts/SPS": batch.env_steps / max(t1 - t0, 1e-9), "charts/samples": batch.num_steps,
                      "time/rollout_s": t1 - t0, "time/update_s": t2 - t1, **metrics, **collector.pop_metrics()}
            last = iteration == cfg.iterations or out_of_budget()
            if cfg.eval.every and iteration % cfg.eval.every == 0 and not last:
                record |= _eval_record(evaluate(algo.eval_policy(), cfg.eval.during_episodes))
                last_eval = record["charts/success_rate"]
            logger.log(record)
            bar.set_postfix(rollout=f"{record['charts/rollout_success_rate']:.2f}",
                            eval="-" if last_eval is None else f"{last_eval:.2f}", refresh=False)
            if iteration % cfg.checkpoint_every == 0 or last:
                save_checkpoint(run_dir, iteration, policy, {
                    "env_steps": env_steps, "before": before, "algorithm": algo.state_dict(),
                    "algorithm_generator": algo.generator.get_state(),
                    "collector": collector.state_dict(), "torch_rng": torch.get_rng_state()})
            if last:
                break
        bar.close()
        distributed.broadcast(None)  # the other processes are done

        final = algo.eval_policy()
        after = evaluate(final, cfg.eval.episodes)
        final.save_pretrained(run_dir / "policy")
        logger.log({"iteration": iteration, "env_steps": env_steps, "final": True, **_eval_record(after)})
        plot_learning_curve(run_dir)
        summary = {
            "tasks": {t: {"before": before["tasks"][t], "after": after["tasks"][t]} for t in tasks},
            "average": {"before": before["average"], "after": after["average"]},
            "eval_episodes_per_task": cfg.eval.episodes, "env_steps": env_steps, "algorithm": cfg.algo.name,
            "wall_clock_s_this_session": time.perf_counter() - t_start, "seed": cfg.seed, "iterations": iteration,
        }
        write_atomic(run_dir / "summary.json", json.dumps(summary, indent=2))
        log("before -> after:\n" + format_table(before, after))
        return summary


def run_sft(cfg: TrainConfig, log: Callable[[str], None] = print) -> dict:
    """``stepnft sft``: few-shot SFT on the demonstrations, saved to ``RUN/policy``, then evaluated."""
    if distributed.launched():
        raise ValueError("stepnft sft runs in one process: start it without torchrun")
    with ExitStack() as stack:
        run_dir, sim, tasks, collector = _start_run(cfg, stack)
        save_config(cfg, run_dir / "config.yaml")
        policy = sft_from_demos(cfg.policy, cfg.sft, cfg.demos, sim, tasks, cfg.env.max_episode_steps, cfg.seed,
                                run_dir / "lang_cache", log)
        policy.save_pretrained(run_dir / "policy")
        result = _evaluator(collector, cfg.eval.seed)(policy, cfg.eval.episodes)
        write_atomic(run_dir / "summary.json", json.dumps({"sft": result}, indent=2))
        log("SFT policy:\n" + format_table(None, result))
        return result


def _start_run(cfg: TrainConfig, stack: ExitStack, resume: bool = False):
    """What ``sft`` and ``train`` start with: checked tasks, a run folder that is free (or holds
    the run to resume), seeds and threads, and a collector over the vector env (closed with
    ``stack`` on every exit path). Returns ``(run_dir, simulator, tasks, collector)``."""
    sim = get_simulator(cfg.env.name)
    tasks = sim.validate_tasks(cfg.env.tasks)
    if cfg.policy.state_dim != sim.state_dim or cfg.policy.action_dim != sim.action_dim:
        raise ValueError(f"{sim.label} has {sim.state_dim}-d states and {sim.action_dim}-d actions: set "
                         f"--policy.state-dim {sim.state_dim} --policy.action-dim {sim.action_dim}")
    run_dir = prepare_run_dir(cfg.run_dir, must_exist=resume)
    if not resume:
        refuse_existing_run(run_dir)
    torch.set_num_threads(cfg.num_threads)
    torch.manual_seed(cfg.seed)
    if cfg.ray.workers > 0:
        from stepnft.rollout.ray_collector import RayCollector

        collector = RayCollector(cfg.env, cfg.policy.n_exec, cfg.seed, cfg.ray, num_threads=cfg.num_threads)
    else:
        collector = Collector(make_vec_env(cfg.env, cfg.policy.n_exec, cfg.seed), seed=cfg.seed)
    stack.callback(collector.close)
    return run_dir, sim, tasks, collector


def _follow(cfg: TrainConfig) -> dict:
    """A process of rank > 0 under ``torchrun``: takes rank 0's policy and algorithm state,
    then updates on every batch rank 0 sends, in step with it (``stepnft.distributed``)."""
    try:
        torch.set_num_threads(cfg.num_threads)
        policy, state, generator_state = distributed.broadcast()
        algo = make_algorithm(cfg.algo, policy, cfg.iterations, torch.Generator())
        algo.load_state_dict(state)
        algo.generator.set_state(generator_state)
        while (message := distributed.broadcast()) is not None:
            batch, it = message
            algo.update(batch)
            algo.end_iteration(it)
    finally:
        distributed.close()
    return {}


def _initial_policy(cfg: TrainConfig, sim, tasks: list[str], run_dir: Path, log) -> Policy:
    """The policy RL starts from: ``--init``, or few-shot SFT on the demonstrations."""
    if not cfg.init:
        return sft_from_demos(cfg.policy, cfg.sft, cfg.demos, sim, tasks, cfg.env.max_episode_steps, cfg.seed,
                              run_dir / "lang_cache", log)
    policy = load_policy(cfg.init)
    if policy.config != cfg.policy:
        # The envs and config.yaml were built for cfg.policy.
        raise ValueError(f"--init policy {cfg.init} was built with other policy settings than this run's: "
                         f"pass the same --policy.* flags it was trained with (see its config.json)")
    return policy


def _evaluator(collector: Collector, seed: int):
    """``evaluate(policy, episodes)`` on the run's envs and fixed states, with a progress bar."""
    def evaluate(policy: Policy, episodes: int) -> dict:
        with tqdm(total=1, desc=f"eval {episodes}/task", leave=False) as bar:
            def progress(done, total):
                bar.total, bar.n = total, done
                bar.refresh()
            return evaluate_policy(policy, collector, episodes, seed, progress=progress)
    return evaluate


def _eval_record(result: dict) -> dict:
    return {"charts/success_rate": result["average"], **{f"eval/{t}": r["success"] for t, r in result["tasks"].items()}}
