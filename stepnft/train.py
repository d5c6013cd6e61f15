"""The training loop: demonstrations -> few-shot SFT -> online RL -> evaluation, for any
registered algorithm, simulator and policy.

Each iteration: the collector plays episodes with the algorithm's acting policy (split over
tasks as ``task_allocation`` says) -> the algorithm updates -> its end-of-iteration step
(π-StepNFT: the EMA update). Every ``eval.every`` iterations the evaluated policy plays ODE
episodes from *validation* initial states; the best one so far is kept in ``best_policy/``.
The final ``policy/`` and ``best_policy/`` are evaluated on the *test* states. The run folder
gets ``config.yaml``, ``metrics.jsonl``, TensorBoard logs, checkpoints, ``learning_curve.png``
and ``summary.json`` (``stepnft.runs``).
"""

from __future__ import annotations

import dataclasses
import json
import shutil
import sys
import time
from contextlib import ExitStack, contextmanager
from pathlib import Path
from typing import Callable

import torch
from tqdm.auto import tqdm

from stepnft import distributed
from stepnft.algos.base import RunDiverged, make_algorithm
from stepnft.algos.sft import sft_stage
from stepnft.checkpoint import load_checkpoint, save_checkpoint
from stepnft.config import TrainConfig, load_config, save_config, to_dict
from stepnft.data.demos import check_task_episodes, load_or_generate_demos
from stepnft.devices import resolve_device
from stepnft.envs import env_options, make_vec_env, simulator_for
from stepnft.envs.base import RenderingError
from stepnft.evaluate import evaluate_policy, format_table, record_videos, tasks_below
from stepnft.policies.base import Policy, load_policy, load_policy_config, non_finite, non_finite_samples, probe_rows
from stepnft.rollout.allocation import TaskAllocator
from stepnft.rollout.collector import Collector
from stepnft.runs import (MetricLogger, check_free, check_resumable, clear_interrupted_start, mark_run,
                          plot_learning_curve, prepare_run_dir, run_kind, write_atomic, writer_lock)


def train(cfg: TrainConfig, resume: bool = False, log: Callable[[str], None] = print) -> dict:
    """Run (or resume) a training run; returns the summary also written to ``summary.json``.
    Under ``torchrun`` rank 0 runs it and the other processes share its updates (``_follow``)."""
    if distributed.init() and distributed.rank() > 0:
        return _follow(cfg)
    with ExitStack() as stack:
        stack.callback(distributed.close)
        run_dir, sim, tasks, collector = _start_run(cfg, stack, "train", resume)
        start = TrainingRun.resume if resume else TrainingRun.begin
        run = start(cfg, run_dir, sim, tasks, collector, log)
        if distributed.world_size() > 1:
            distributed.broadcast((run.policy, run.algo.state_dict(), run.algo.generator.get_state()))
        logger = MetricLogger(run_dir, resume_iteration=run.progress.iteration if resume else None)
        stack.callback(logger.close)
        if not resume:
            logger.log({"iteration": 0, "env_steps": 0, **_eval_record(run.progress.before, "test"),
                        **_eval_record(run.progress.validation, "validation")})
        bar = stack.enter_context(progress_bar(cfg, run.progress))
        while run.progress.iteration < cfg.iterations and not run.out_of_budget():
            record = run.iterate()
            last = run.progress.iteration == cfg.iterations or run.out_of_budget()
            if cfg.eval.every and (run.progress.iteration % cfg.eval.every == 0 or last):
                record |= run.validate()
            logger.log(record)
            bar.update(bar_position(cfg, run.progress) - bar.n)
            bar.set_postfix(rollout=f"{record['charts/rollout_success_rate']:.2f}",
                            best=f"{run.progress.best['validation'] or 0:.2f}@{run.progress.best['iteration']}",
                            refresh=False)
            if run.progress.iteration % cfg.checkpoint_every == 0 or last:
                run.save_checkpoint()
        bar.close()
        distributed.broadcast(None)  # the other processes are done
        # Leave the group together with them (they close on this message), not after the final
        # evaluation: a follower whose group outlived its peer's by minutes has aborted at exit.
        distributed.close(wait=True)
        return _finish(run, logger, sim, log)


def checkpoint_settings(cfg: TrainConfig) -> dict:
    """What a checkpoint records of the run's config: everything but where it runs
    (``TrainConfig.resumable``), its length (``lengthening``, which a resume may raise) and its folder."""
    skip = {"run_dir", *TrainConfig.resumable, *TrainConfig.lengthening}
    settings = {k: v for k, v in to_dict(cfg).items() if k not in skip}
    settings["algo"] = {k: v for k, v in settings["algo"].items() if k != "ema_horizon"}  # set from the length
    return settings


def check_config_matches(ckpt: dict, settings: dict, run_dir: Path, defaults: dict | None = None) -> None:
    """Refuse to resume when the folder's config.yaml no longer says what the checkpoint was
    written under (edited by hand): one line naming the changed settings and how to go on.
    ``defaults`` (:func:`checkpoint_settings` of a default config of the run's algorithm and policy
    type): a setting the checkpoint does not record (added to stepnft after it was written) is
    no change while it has its default value, so a newer stepnft resumes an older run."""
    recorded = ckpt.get("config")
    if recorded is None:  # written before checkpoints recorded their config: nothing to compare
        return

    def leaves(tree: dict, prefix: str = "") -> dict:
        out = {}
        for key, value in tree.items():
            out |= leaves(value, f"{prefix}{key}.") if isinstance(value, dict) else {f"{prefix}{key}": value}
        return out

    # What the checkpoint does not record, it was written under at its default.
    old = (leaves(json.loads(json.dumps(defaults))) if defaults else {}) | leaves(recorded)
    new = leaves(json.loads(json.dumps(settings)))
    changed = sorted(k for k in old.keys() | new.keys() if old.get(k) != new.get(k))
    if changed:
        shown = ", ".join(f"{k} {old.get(k)!r} -> {new.get(k)!r}" for k in changed[:4]) + (" ..." if len(changed) > 4 else "")
        raise ValueError(f"{run_dir}/config.yaml was edited after checkpoint {ckpt['path'].name} was written ({shown}): "
                         f"restore it to resume, or start a new run from the edited config with `stepnft train --config "
                         f"{run_dir}/config.yaml --run-dir NEW_DIR`")


class TrainingRun:
    """The parts of a training run (policy, algorithm, collector, task allocator) and its
    progress; :meth:`state_dict` names everything a checkpoint holds besides the policy."""

    def __init__(self, cfg: TrainConfig, run_dir: Path, policy: Policy, collector: Collector, tasks: list[str]):
        self.cfg, self.run_dir, self.policy, self.collector, self.tasks = cfg, run_dir, policy, collector, tasks
        policy.set_precision(cfg.precision).set_gradient_checkpointing(cfg.gradient_checkpointing)
        policy.processor.bind_instructions(collector.venv.instruction_variants, run_dir / "lang_cache")
        self.algo = make_algorithm(cfg.algo, policy, cfg.iterations, torch.Generator().manual_seed(cfg.seed))
        self.allocator = TaskAllocator(len(tasks), cfg.task_allocation, cfg.allocation_floor)
        self.progress = Progress()
        self.probe: dict | None = None
        """A few raw observations of the last batch: every policy saved must sample finite actions on them."""

    # --- start ------------------------------------------------------------------------------
    @classmethod
    def begin(cls, cfg: TrainConfig, run_dir: Path, sim, tasks: list[str], collector: Collector, log) -> "TrainingRun":
        """A new run: the ``--init`` policy or few-shot SFT, evaluated on the test states (and
        the validation states, as the first ``best_policy/``)."""
        clock = Progress()  # SFT comes before the run's parts exist
        policy = _init_policy(cfg) if cfg.init else None
        mark_run(run_dir, "train")
        save_config(cfg, run_dir / "config.yaml")
        if policy is None:
            with clock.timed("demos"):
                episodes = load_or_generate_demos(cfg.demos, cfg.env, sim, log)
            with clock.timed("sft"):
                policy = sft_stage(cfg.env, cfg.demos, cfg.policy, cfg.sft, seed=cfg.seed, simulator=sim,
                                   device=cfg.device, cache_dir=run_dir / "lang_cache", log=log, episodes=episodes,
                                   precision=cfg.precision, gradient_checkpointing=cfg.gradient_checkpointing)
        policy.save_pretrained(run_dir / "sft_policy")
        run = cls(cfg, run_dir, policy, collector, tasks)
        run.progress.time_s = clock.time_s
        with run.progress.timed("test_eval"):
            run.progress.before = run.evaluate(policy, cfg.eval.episodes, cfg.eval.seed)
        log("before RL:\n" + format_table(None, run.progress.before))
        run.allocator.success[:] = [run.progress.before["tasks"][t]["success"] for t in tasks]
        if cfg.eval.every:
            with run.progress.timed("validation"):
                run.progress.validation = run.evaluate(policy, cfg.eval.during_episodes, cfg.eval.validation_seed)
            run.progress.best["validation"] = run.progress.validation["average"]
        policy.save_pretrained(run_dir / "best_policy")
        return run

    @classmethod
    def resume(cls, cfg: TrainConfig, run_dir: Path, sim, tasks: list[str], collector: Collector,
               log) -> "TrainingRun":
        """The run at its last checkpoint, exactly as it was."""
        ckpt = load_checkpoint(run_dir)
        defaults = dataclasses.replace(TrainConfig(), algo=type(cfg.algo)(), policy=type(cfg.policy)())
        check_config_matches(ckpt, checkpoint_settings(cfg), run_dir, checkpoint_settings(defaults))
        run = cls(cfg, run_dir, ckpt["policy"].to(cfg.device), collector, tasks)
        run.load_state_dict(ckpt["state"])
        log(f"resuming {run_dir} from iteration {run.progress.iteration} ({run.progress.env_steps} env steps)")
        saved = load_config(run_dir / "config.yaml")
        longer = {name: getattr(cfg, name) for name in TrainConfig.lengthening}
        if any(getattr(saved, name) != value for name, value in longer.items()):
            # Lengthened: the folder's config.yaml then describes the whole run, as a new run's does.
            save_config(dataclasses.replace(saved, **longer, algo=cfg.algo), run_dir / "config.yaml")
            log(f"lengthened to {cfg.iterations} iterations (env_step_budget {cfg.env_step_budget})")
        return run

    # --- checkpoints ------------------------------------------------------------------------
    def state_dict(self) -> dict:
        return {"progress": dataclasses.asdict(self.progress), "algorithm": self.algo.state_dict(),
                "algorithm_generator": self.algo.generator.get_state(), "collector": self.collector.state_dict(),
                "allocator": self.allocator.state_dict(), "torch_rng": torch.get_rng_state()}

    def load_state_dict(self, state: dict) -> None:
        self.progress = Progress(**state["progress"])
        self.algo.load_state_dict(state["algorithm"])
        self.algo.generator.set_state(state["algorithm_generator"])
        self.collector.load_state_dict(state["collector"])
        self.allocator.load_state_dict(state["allocator"])
        torch.set_rng_state(state["torch_rng"])

    def save_checkpoint(self) -> None:
        for policy in dict.fromkeys([self.policy, self.algo.eval_policy()]):
            self.check_samples(policy)
        with self.progress.timed("checkpoints"):
            save_checkpoint(self.run_dir, self.progress.iteration, self.policy, self.state_dict(),
                            config=checkpoint_settings(self.cfg))

    def check_samples(self, policy: Policy) -> None:
        """Stop the run (RunDiverged) if ``policy`` samples non-finite actions on :attr:`probe`:
        finite weights may still overflow, and such a policy is never saved."""
        bad = non_finite_samples(policy, self.probe, self.cfg.algo.noise_level) if self.probe is not None else []
        if bad:
            raise RunDiverged(f"the policy samples non-finite actions ({', '.join(bad)}) after iteration "
                              f"{self.progress.iteration} (algo.lr={self.cfg.algo.lr:g} too large?): it is not saved; "
                              "the last checkpoint is intact")

    # --- the loop -----------------------------------------------------------------------------
    def out_of_budget(self) -> bool:
        return self.cfg.env_step_budget is not None and self.progress.env_steps >= self.cfg.env_step_budget

    def iterate(self) -> dict:
        """One iteration: collect -> update -> end of iteration; returns its metrics."""
        cfg, algo, progress = self.cfg, self.algo, self.progress
        t0 = time.perf_counter()
        with progress.timed("rollouts"):
            task_episodes = self.allocator.allocate(cfg.episodes_per_iteration, algo.rollout.group_size)
            batch = self.collector.collect(algo.acting_policy(), cfg.episodes_per_iteration, algo.rollout, task_episodes)
            self.probe = probe_rows(batch.obs)
        distributed.broadcast((batch, progress.iteration, torch.get_rng_state()))
        t1 = time.perf_counter()
        with progress.timed("updates"):
            metrics = algo.update(batch)
            if non_finite(self.policy.state_dict()):  # the update guard should make this impossible
                raise RunDiverged(f"the policy's weights became non-finite in iteration {progress.iteration + 1} "
                                  f"(algo.lr={cfg.algo.lr:g} too large?); the last checkpoint is intact")
            metrics |= algo.end_iteration(progress.iteration)
            self.allocator.update(batch)
        t2 = time.perf_counter()
        progress.iteration += 1
        progress.env_steps += batch.env_steps
        self.check_samples(algo.acting_policy())  # before it plays NaN actions in the next iteration
        return {"iteration": progress.iteration, "env_steps": progress.env_steps, **_rollout_record(batch, self.tasks),
                "charts/SPS": batch.env_steps / max(t1 - t0, 1e-9), "charts/samples": batch.num_steps,
                "time/rollout_s": t1 - t0, "time/update_s": t2 - t1, **_per_task(metrics, self.tasks),
                **self.collector.pop_metrics()}

    def validate(self) -> dict:
        """The evaluated policy on the validation states; kept as ``best_policy/`` if best so far."""
        current = self.algo.eval_policy()
        self.check_samples(current)
        with self.progress.timed("validation"):
            result = self.evaluate(current, self.cfg.eval.during_episodes, self.cfg.eval.validation_seed)
        if result["average"] > self.progress.best["validation"]:
            self.progress.best = {"iteration": self.progress.iteration, "validation": result["average"]}
            current.save_pretrained(self.run_dir / "best_policy")
        return _eval_record(result, "validation")

    def evaluate(self, policy: Policy, episodes: int, seed: int) -> dict:
        """``evaluate_policy`` on the run's envs, with a progress bar."""
        with tqdm(total=len(self.tasks) * episodes, desc=f"eval {episodes}/task", leave=False) as bar:
            def progress(done, total):
                bar.total, bar.n = total, done
                bar.refresh()
            return evaluate_policy(policy, self.collector, episodes, seed, progress=progress)


@dataclasses.dataclass
class Progress:
    """How far a training run got (checkpointed): iterations, env steps, the start's test and
    validation results, the best validation so far, and wall-clock seconds per phase."""

    iteration: int = 0
    env_steps: int = 0
    before: dict | None = None
    validation: dict | None = None
    best: dict = dataclasses.field(default_factory=lambda: {"iteration": 0, "validation": None})
    time_s: dict = dataclasses.field(default_factory=dict)

    @contextmanager
    def timed(self, phase: str):
        """Add the block's wall-clock to ``time_s[phase]``."""
        start = time.perf_counter()
        try:
            yield
        finally:
            self.time_s[phase] = self.time_s.get(phase, 0.0) + time.perf_counter() - start


def progress_bar(cfg: TrainConfig, progress: Progress, **options) -> tqdm:
    """The run's progress bar: in env steps when the run ends on ``env_step_budget`` (its
    ``iterations`` is then only a cap, often far beyond what the budget allows, which made an
    iteration bar read 1 % and estimate days), else in iterations."""
    if cfg.env_step_budget is not None:
        return tqdm(total=cfg.env_step_budget, initial=bar_position(cfg, progress), desc=cfg.algo.name,
                    unit=" env steps", unit_scale=True, **options)
    return tqdm(total=cfg.iterations, initial=bar_position(cfg, progress), desc=cfg.algo.name, unit="it", **options)


def bar_position(cfg: TrainConfig, progress: Progress) -> int:
    """Where :func:`progress_bar` stands: env steps (capped at the budget: the last iteration
    overshoots it) or iterations."""
    if cfg.env_step_budget is not None:
        return min(progress.env_steps, cfg.env_step_budget)
    return progress.iteration


def _finish(run: TrainingRun, logger: MetricLogger, sim, log) -> dict:
    """Test evaluation of ``policy/`` (and of ``best_policy/`` unless it is the start or the
    final policy), videos, curves and ``summary.json``."""
    cfg, run_dir, tasks, progress = run.cfg, run.run_dir, run.tasks, run.progress
    final = run.algo.eval_policy()
    run.check_samples(final)
    with progress.timed("test_eval"):
        after = run.evaluate(final, cfg.eval.episodes, cfg.eval.seed)
    final.save_pretrained(run_dir / "policy")
    best = progress.best
    if best["iteration"] == progress.iteration:  # the last validation was the best: the same weights
        best_after = after
        shutil.copytree(run_dir / "policy", run_dir / "best_policy", dirs_exist_ok=True)
    elif best["iteration"] == 0:  # nothing beat the start on validation: best_policy/ is the start
        best_after = progress.before
    else:
        best_policy = load_policy(run_dir / "best_policy").to(cfg.device)
        best_policy.processor.bind_instructions(run.collector.venv.instruction_variants, run_dir / "lang_cache")
        with progress.timed("test_eval"):
            best_after = run.evaluate(best_policy, cfg.eval.episodes, cfg.eval.seed)
    logger.log({"iteration": progress.iteration, "env_steps": progress.env_steps, "final": True,
                **_eval_record(after, "test")})
    if cfg.eval.videos:
        with progress.timed("videos"):
            _film(final, cfg, sim, tasks, run_dir, logger, progress.env_steps, log)
    plot_learning_curve(run_dir)
    before = progress.before
    summary = {
        "tasks": {t: {"before": before["tasks"][t], "after": after["tasks"][t], "best": best_after["tasks"][t]}
                  for t in tasks},
        "average": {"before": before["average"], "after": after["average"], "best": best_after["average"]},
        "below_start": tasks_below(before, after), "best_below_start": tasks_below(before, best_after),
        "best_iteration": best["iteration"], "best_validation": best["validation"],
        "eval_episodes_per_task": cfg.eval.episodes, "env_steps": progress.env_steps, "algorithm": cfg.algo.name,
        "time_s": progress.time_s, "wall_clock_s": sum(progress.time_s.values()), "seed": cfg.seed,
        "iterations": progress.iteration,
    }
    write_atomic(run_dir / "summary.json", json.dumps(summary, indent=2))
    log("before -> after (policy/):\n" + format_table(before, after))
    validation = "none" if best["validation"] is None else f"{best['validation']:.3f}"
    log(f"best_policy/ (iteration {best['iteration']}, validation {validation}): "
        f"test average {best_after['average']:.3f}")
    log("time: " + ", ".join(f"{phase} {seconds:.0f} s" for phase, seconds in progress.time_s.items()))
    for name, below in (("policy/", summary["below_start"]), ("best_policy/", summary["best_below_start"])):
        if below:
            log(f"warning: {name} ends below its SFT start beyond the 95 % interval of the difference on: "
                f"{', '.join(below)}")
    return summary


def run_sft(cfg: TrainConfig, log: Callable[[str], None] = print) -> dict:
    """``stepnft sft``: few-shot SFT on the demonstrations, saved to ``RUN/policy``, then evaluated."""
    if distributed.launched():
        raise ValueError("stepnft sft runs in one process: start it without torchrun")
    with ExitStack() as stack:
        run_dir, sim, tasks, collector = _start_run(cfg, stack, "sft")
        mark_run(run_dir, "sft")
        save_config(cfg, run_dir / "config.yaml")
        policy = sft_stage(cfg.env, cfg.demos, cfg.policy, cfg.sft, seed=cfg.seed, simulator=sim, init=cfg.init,
                           device=cfg.device, cache_dir=run_dir / "lang_cache", log=log, precision=cfg.precision,
                           gradient_checkpointing=cfg.gradient_checkpointing)
        policy.save_pretrained(run_dir / "policy")
        if cfg.eval.episodes == 0:  # e.g. `stepnft train --init RUN/policy` evaluates it next
            write_atomic(run_dir / "summary.json", json.dumps({"sft": None}, indent=2))
            log(f"SFT policy saved to {run_dir / 'policy'} (eval.episodes 0: not evaluated)")
            return {}
        policy.processor.bind_instructions(collector.venv.instruction_variants, run_dir / "lang_cache")
        result = evaluate_policy(policy, collector, cfg.eval.episodes, cfg.eval.seed)
        write_atomic(run_dir / "summary.json", json.dumps({"sft": result}, indent=2))
        log("SFT policy:\n" + format_table(None, result))
        return result


def _start_run(cfg: TrainConfig, stack: ExitStack, kind: str, resume: bool = False):
    """What ``sft`` and ``train`` start with: checked tasks, a run folder that is free (or holds
    the training run to resume), seeds and threads, and a collector over the vector env (closed
    with ``stack`` on every exit path). A folder this call creates is removed again if the run
    fails before its first checkpoint (or, for SFT, before it finishes), and an empty one is
    emptied again, so a failed start leaves nothing behind. Returns ``(run_dir, simulator, tasks, collector)``."""
    resolve_device(cfg.device)  # before anything is created: no CUDA here is one line, exit code 2
    sim = simulator_for(cfg.env)
    tasks = sim.validate_tasks(cfg.env.tasks)
    check_task_episodes(cfg.demos, sim)
    state_dim = sim.state_dim_for(cfg.env.state_obs)
    # An --init policy of another type (e.g. a LeRobot SmolVLA) brings its own sizes.
    policy_cfg = load_policy_config(cfg.init) if cfg.init else cfg.policy
    if policy_cfg.state_dim != state_dim or policy_cfg.action_dim != sim.action_dim:
        if policy_cfg is not cfg.policy:
            raise ValueError(f"--init policy {cfg.init} takes {policy_cfg.state_dim}-d states and "
                             f"{policy_cfg.action_dim}-d actions, {sim.label} has {state_dim} (env.state_obs "
                             f"{cfg.env.state_obs}) and {sim.action_dim}")
        raise ValueError(f"{sim.label} has {state_dim}-d states (env.state_obs {cfg.env.state_obs}) and "
                         f"{sim.action_dim}-d actions: set --policy.state-dim {state_dim} --policy.action-dim {sim.action_dim}")
    if cfg.init and list(policy_cfg.cameras) != list(cfg.env.cameras):
        raise ValueError(f"--init policy {cfg.init} sees cameras {list(policy_cfg.cameras)}, env.cameras is "
                         f"{list(cfg.env.cameras)}: give the policy's cameras to --env.cameras (a LeRobot policy's "
                         "are the `cameras` of its config.json)")
    created = not Path(cfg.run_dir).exists()
    run_dir = prepare_run_dir(cfg.run_dir, must_exist=resume)
    stack.enter_context(writer_lock(run_dir))  # one writer: a second process on this folder is refused
    if not resume and clear_interrupted_start(run_dir, kind):
        print(f"{run_dir}: removed an earlier start that was interrupted before its first checkpoint "
              "(nothing to resume); starting anew", file=sys.stderr)
    if not resume and run_kind(run_dir) is None:  # a new or empty folder: this run's alone
        def remove_if_unfinished(exc_type, exc, tb):
            done = (run_dir / "checkpoints" / "LATEST").is_file() or (run_dir / "summary.json").is_file()
            if exc_type is not None and not done:
                for child in run_dir.iterdir():
                    shutil.rmtree(child) if child.is_dir() else child.unlink()
                if created:
                    run_dir.rmdir()
        stack.push(remove_if_unfinished)
    if resume:
        check_resumable(run_dir)
    else:
        check_free(run_dir)
    torch.set_num_threads(cfg.num_threads)
    torch.manual_seed(cfg.seed)
    if cfg.ray.workers > 0:
        from stepnft.rollout.ray_collector import RayCollector

        collector = RayCollector(cfg.env, policy_cfg.n_exec, cfg.seed, cfg.ray, num_threads=cfg.num_threads)
    else:
        collector = Collector(make_vec_env(cfg.env, policy_cfg.n_exec, cfg.seed), seed=cfg.seed)
    stack.callback(collector.close)
    return run_dir, sim, tasks, collector


def _follow(cfg: TrainConfig) -> dict:
    """A process of rank > 0 under ``torchrun``: takes rank 0's policy and algorithm state,
    then updates on every batch rank 0 sends, in step with it (``stepnft.distributed``)."""
    try:
        torch.set_num_threads(cfg.num_threads)
        policy, state, generator_state = distributed.broadcast()
        policy = policy.to(cfg.device)  # "cuda": this process's GPU (stepnft.distributed.init)
        policy.set_precision(cfg.precision).set_gradient_checkpointing(cfg.gradient_checkpointing)
        algo = make_algorithm(cfg.algo, policy, cfg.iterations, torch.Generator())
        algo.load_state_dict(state)
        algo.generator.set_state(generator_state)
        while (message := distributed.broadcast()) is not None:
            batch, it, torch_rng = message
            torch.set_rng_state(torch_rng)  # what the update draws (e.g. PPO's new critic) is rank 0's
            algo.update(batch)
            algo.end_iteration(it)
        distributed.close(wait=True)
    finally:
        distributed.close()
    return {}


def _init_policy(cfg: TrainConfig) -> Policy:
    """The ``--init`` policy, checked against the run's policy settings before anything is written."""
    policy = load_policy(cfg.init).to(cfg.device)
    if policy.type == cfg.policy.type and policy.config != cfg.policy:
        # The envs and config.yaml were built for cfg.policy.
        raise ValueError(f"--init policy {cfg.init} was built with other policy settings than this run's: "
                         f"pass the same --policy.* flags it was trained with (see its config.json)")
    return policy


def _film(policy: Policy, cfg: TrainConfig, sim, tasks: list[str], run_dir: Path, logger: MetricLogger,
          env_steps: int, log) -> None:
    """``eval.videos`` ODE episodes per task from the test states into ``RUN/videos`` and
    TensorBoard (a machine without offscreen rendering only loses the videos)."""
    try:
        paths = record_videos(policy, sim, tasks, run_dir / "videos", seed=cfg.eval.seed, episodes=cfg.eval.videos,
                              max_episode_steps=cfg.env.max_episode_steps, env_options=env_options(cfg.env),
                              on_video=lambda name, frames: logger.video(f"videos/{name}", frames, sim.control_hz,
                                                                         env_steps))
        log(f"wrote {len(paths)} videos to {run_dir / 'videos'}")
    except RenderingError as err:
        log(f"no videos: {err}")


def _eval_record(result: dict | None, states: str) -> dict:
    """Evaluation metrics: ``charts/success_rate`` + ``eval/<task>`` on test states,
    ``charts/validation_success_rate`` + ``validation/<task>`` on validation states."""
    if result is None:
        return {}
    if states == "test":
        return {"charts/success_rate": result["average"], **{f"eval/{t}": r["success"] for t, r in result["tasks"].items()}}
    return {"charts/validation_success_rate": result["average"],
            **{f"validation/{t}": r["success"] for t, r in result["tasks"].items()}}


def _per_task(metrics: dict, tasks: list[str]) -> dict:
    """An algorithm's metrics with each ``per_task/NAME`` (a list, one entry per task: π-StepNFT's
    ``algo.task_diagnostics``) logged as ``NAME/<task>``."""
    out = {}
    for name, value in metrics.items():
        if name.startswith("per_task/"):
            name = name.removeprefix("per_task/")
            out |= {f"{name}/{task}": value[k] if k < len(value) else None for k, task in enumerate(tasks)}
        else:
            out[name] = value
    return out


def _rollout_record(batch, tasks: list[str]) -> dict:
    record = {"charts/rollout_success_rate": float(batch.episode_success.double().mean())}
    for k, task in enumerate(tasks):
        mine = batch.episode_task == k
        record[f"rollout/{task}"] = float(batch.episode_success[mine].double().mean()) if mine.any() else None
        record[f"episodes/{task}"] = int(mine.sum())
    return record
