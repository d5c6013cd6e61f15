"""π-StepNFT (docs/algorithm.md §3–5): Flow-SDE rollouts from an EMA copy of the policy, one
forward pass per recorded denoising step, the step-wise contrastive ranking loss, then the EMA
update once per iteration. Reads top to bottom: config, sample weights, the update, the class
the training loop drives.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Annotated, Any, Literal

import torch
from torch import Tensor

from stepnft.algos.base import (AlgoConfig, Algorithm, MinibatchEpochs, NonFiniteGuard, RolloutSpec, call_progress,
                                call_step_rows, episode_weights, step_velocity)
from stepnft.batch import Batch
from stepnft.devices import to_device
from stepnft.distributed import data_parallel, shard_forward
from stepnft.ema import ema_decay, ema_state_dict, ema_update, load_ema_state_dict, make_ema_copy
from stepnft.losses import stepnft_loss
from stepnft.policies.base import Policy
from stepnft.settings import ITERATIONS_MAX, Range


@dataclass
class StepNFTConfig(AlgoConfig):
    """Hyperparameters of π-StepNFT (besides the shared ones of ``AlgoConfig``, whose defaults are
    π-StepNFT's). Defaults are the paper's reference values unless noted; configs/paper.yaml
    switches every beyond-paper option (docs/algorithm.md §10) off."""

    record_steps: Literal["one", "all"] = "all"
    """Transitions stored per policy call: ``one`` random denoising step (paper) or, beyond the
    paper, ``all`` K of them: K times the training signal for the same simulator steps.
    Default ``all``: measured better (docs/experiments.md)."""
    beta: Annotated[float, Range(gt=0, le=1000)] = 1.0
    """Trust factor β of the mirrored candidates ``v_old ± β Δc``."""
    beta_dpo: Annotated[float, Range(gt=0, le=1000)] = 1.0
    """Temperature of the ranking softplus."""
    max_drift: Annotated[float | None, Range(gt=0, le=1e6)] = 0.5
    """Cap on ``||v - v_old||`` per chunk position inside the loss (None: no clip)."""
    kl_beta: Annotated[float, Range(ge=0, le=1000)] = 1e-4
    """Weight of ``mean((v - v_old)^2)``."""
    target: Literal["next", "x0"] = "next"
    """``next``: step-wise target ``x_{t-dt}`` (paper); ``x0``: final-action ablation."""
    form: Literal["rank", "wmse", "pos", "neg"] = "rank"
    """``rank``: contrastive ranking (paper); ``wmse``: DiffusionNFT weighted-MSE ablation;
    ``pos`` / ``neg``: one branch of it alone (``r E_pos``: pull toward the steps of successes;
    ``(1 - r) E_neg``: push away from those of failures), the paper's branch ablations."""
    mean_correction: bool = True
    """Flow-SDE rollouts with the drift correction that keeps the flow's marginals (paper).
    False: the exploration ablation "SDE without mean correction": the same noise added to the
    plain Euler step, and the loss's step mean taken the same way."""
    ema_base: Annotated[float, Range(ge=0, le=1)] = 0.1
    """EMA decay at iteration 0."""
    ema_target: Annotated[float, Range(ge=0, le=1)] = 0.995
    """EMA decay at the end of the horizon."""
    ema_horizon: Annotated[int | None, Range(ge=1, le=ITERATIONS_MAX)] = None
    """Iterations over which the decay rises (None: the run's number of iterations)."""
    eval_ema: bool = False
    """Evaluate (and save as ``policy/``) the EMA rollout policy instead of the trained one
    (the reference evaluates the EMA policy)."""
    label_balance: Literal["none", "global", "task", "group"] = "global"
    """Beyond the paper: ``none`` (paper); ``global``: weight samples so successes and failures
    carry equal total weight (successful episodes are short, so positives are a minority of
    stored samples); ``task``: the same within each task (a zero-mean signal per task);
    ``group``: the same within each group of ``group_size`` episodes started from one initial
    state (outcomes then compare actions, not how hard the initial state was).
    Default ``global``: measured better than ``none`` and ``task`` (docs/experiments.md)."""
    drop_uniform_tasks: bool = False
    """Beyond the paper: give weight 0 to the samples of a task whose episodes in this iteration
    all succeeded or all failed (no contrast to learn from, only exploration noise; GRPO's
    zero-advantage groups)."""
    labels: Literal["episode", "progress"] = "episode"
    """Beyond the paper: ``episode`` (paper): every step of an episode carries its outcome ±1;
    ``progress``: each policy call's label mixes that outcome with how much the call moved the
    simulator's shaped reward (a per-call credit without a critic; ``call_progress``). Needs a
    simulator whose reward measures progress (MetaWorld's does); PPO and GRPO here use the
    sparse success only."""
    progress_mix: Annotated[float, Range(ge=0, le=1)] = 0.5
    """With ``labels: progress``: the share of the label from progress, in [0, 1]; a call's label
    is ``(1 - mix) * outcome + mix * tanh(progress / its task's std)``, in [-1, 1]."""
    progress_lambda: Annotated[float, Range(ge=0, lt=1)] = 0.8
    """With ``labels: progress``: how far ahead a call's progress looks, in [0, 1): the reward
    level after the call is ``(1 - λ) Σ_l λ^l r_{c+l}`` over the episode's following calls (the
    last level held after its end), compared with the level of the call before."""
    failed_task_labels: Literal["mixed", "progress"] = "mixed"
    """With ``labels: progress``, a task none of whose episodes succeeded in the iteration:
    ``mixed`` (the label above, which is <= 0 for every call of a failed episode: the update only
    pushes away from what the task's policy did) or ``progress``: its calls labelled by progress
    alone, ``tanh(progress / std)``, so the calls that moved it forward are pulled toward (the
    outcome, the same -1 for every call, ranks nothing). Tasks with a success keep ``mixed``."""
    drift_limit: Annotated[float | None, Range(gt=0, le=1e6)] = None
    """Beyond the paper: skip the rest of an iteration's updates once a minibatch's mean
    ``||v - v_old||`` exceeds this (like PPO's target-KL early stop): a guard against drifting
    past ``max_drift``, where the clipped loss no longer bounds the step size. None: off."""
    task_diagnostics: bool = False
    """Also log, every iteration and per task, what the update saw: ``labels/pos_frac/<task>``
    (share of its recorded steps labelled positive), ``labels/weight_share/<task>`` (its positives'
    share of its sample weight), ``losses/E_pos/<task>``, ``losses/E_neg/<task>`` and
    ``losses/delta_v_norm/<task>`` (the loss terms after the update, on up to 1024 of its steps,
    evenly spaced: no random draw, so the run is the same with it on). For diagnosing tasks that
    fall; one forward pass more per task and iteration."""

    def check(self) -> None:
        super().check()
        if self.sde_steps == "one" and self.record_steps == "all":
            raise self.fail("{sde_steps}=one needs {record_steps}=one: with one stochastic step per call the other "
                            "recorded steps are deterministic ODE steps with nothing to rank")
        if self.label_balance == "group" and self.group_size < 2:
            raise self.fail("{label_balance}=group needs {group_size} >= 2", self.group_size)

    def rollout_spec(self) -> RolloutSpec:
        return RolloutSpec(self.noise_level, self.sde_steps, self.record_steps, self.group_size,
                           self.mean_correction)


# --- sample weights ---------------------------------------------------------------------------
def label_weights(y: Tensor, group: Tensor | None = None, base: Tensor | None = None) -> Tensor:
    """Per-sample weights ``[B]`` giving successes and failures equal total weight within each
    group (``group`` [B] ints, e.g. task ids; None: one group), rescaling ``base`` weights
    (None: all 1). A group with one label only keeps its base weights."""
    group = torch.zeros_like(y, dtype=torch.long) if group is None else group
    pos = y > 0
    w = torch.ones_like(y, dtype=torch.float32) if base is None else base.float().clone()
    for g in group.unique():
        in_g = group == g
        total_pos, total_neg = w[pos & in_g].sum(), w[~pos & in_g].sum()
        if total_pos > 0 and total_neg > 0:
            total = total_pos + total_neg
            w[pos & in_g] *= 0.5 * total / total_pos
            w[~pos & in_g] *= 0.5 * total / total_neg
    return w


def informative_mask(y: Tensor, group: Tensor) -> Tensor:
    """``[B]`` bool: True for samples whose group holds both successes and failures."""
    keep = torch.zeros_like(y, dtype=torch.bool)
    for g in group.unique():
        in_g = group == g
        labels = y[in_g] > 0
        if labels.any() and not labels.all():
            keep |= in_g
    return keep


def episode_groups(batch: Batch) -> Tensor:
    """``[E]`` group id of every episode: episodes of one task from one initial state share it."""
    keys = torch.stack([batch.episode_task, batch.episode_seed], dim=1)
    return keys.unique(dim=0, return_inverse=True)[1]


def step_labels(batch: Batch, cfg: StepNFTConfig) -> Tensor:
    """``[N]`` labels of the recorded steps: the episode's outcome ±1 (``labels: episode``), or
    mixed with the call's progress normalised within its task (``labels: progress``; a task
    whose reward did not move in this batch keeps the outcome alone; with ``failed_task_labels:
    progress`` a task without a success in the batch takes the progress alone)."""
    outcome = batch.episode_success[batch.episode].float() * 2 - 1  # [C]
    if cfg.labels == "episode":
        return outcome[batch.call]
    progress = call_progress(batch, cfg.progress_lambda)
    task = batch.obs["task"]
    scaled = outcome.clone()  # a task whose reward never moved keeps its outcome
    for g in task.unique():
        in_g = task == g
        std = progress[in_g].std(unbiased=False)
        if std > 1e-6:
            scaled[in_g] = torch.tanh(progress[in_g] / std)
    label = (1 - cfg.progress_mix) * outcome + cfg.progress_mix * scaled
    if cfg.failed_task_labels == "progress":
        for g in task.unique():
            in_g = task == g
            if not bool((outcome[in_g] > 0).any()) and not torch.equal(scaled[in_g], outcome[in_g]):
                label[in_g] = scaled[in_g]  # no success to rank against: progress alone
    return label[batch.call]


def sample_weights(batch: Batch, y: Tensor, cfg: StepNFTConfig) -> Tensor | None:
    """``[N]`` weights of the recorded steps from the options above (None: uniform)."""
    weights = episode_weights(batch.step_episode) if cfg.episode_weighting else None
    if cfg.label_balance != "none":
        groups = {"global": None, "task": batch.step_task, "group": episode_groups(batch)[batch.step_episode]}
        weights = label_weights(y, groups[cfg.label_balance], weights)
    if cfg.drop_uniform_tasks:
        weights = torch.ones(len(y)) if weights is None else weights
        weights = weights * informative_mask(y, batch.step_task).float()
    return weights


# --- the update -------------------------------------------------------------------------------
def stepnft_update(
    policy: Policy,
    optimizer: torch.optim.Optimizer,
    batch: Batch,
    cfg: StepNFTConfig,
    generator: torch.Generator | None = None,
    guard: NonFiniteGuard | None = None,
) -> dict[str, float]:
    """Run ``cfg.update_epochs`` epochs of minibatch π-StepNFT steps over ``batch``'s recorded
    steps; labels ``y = ±1`` are the outcome of each step's episode (terminal-binary), or with
    ``labels: progress`` per call (``step_labels``). Steps with a non-finite loss or gradient
    are skipped (``guard``). Returns metrics averaged over minibatch steps, under stable names.
    Under ``torchrun`` the processes share each minibatch (``stepnft.distributed``): the same
    steps as one process."""
    guard = guard or NonFiniteGuard(cfg)
    learner = data_parallel(policy)
    y = step_labels(batch, cfg)
    weights = sample_weights(batch, y, cfg)
    epochs = MinibatchEpochs(cfg, guard)
    if policy.shares_prefix_in_update:  # whole calls: a call's recorded steps then share one prefix encoding
        rows = call_step_rows(batch)
        minibatches = (rows[calls].flatten() for calls in epochs.minibatches(batch.num_calls, generator, rows.shape[1]))
    else:  # random steps (the MLP's path, kept bit for bit)
        minibatches = epochs.minibatches(batch.num_steps, generator)
    for idx in minibatches:
        w = None if weights is None else weights[idx]
        if w is not None and not bool(w.sum() > 0):
            epochs.skip()  # nothing to learn here; an Adam step on zero gradients would still move
            continue
        v = shard_forward(lambda part: step_velocity(learner, policy, batch, part), idx)
        calls = batch.call[idx]
        v_old, x_t, x_next, t, dt, label, mask, actions, w = to_device(
            (batch.v_old[idx], batch.x_t[idx], batch.x_next[idx], batch.t[idx], batch.dt[idx], y[idx],
             batch.mask[calls], batch.actions[calls], w), v.device)
        loss, metrics = stepnft_loss(
            v, v_old, x_t, x_next, t, dt, cfg.noise_level, label, beta=cfg.beta, beta_dpo=cfg.beta_dpo,
            max_drift=cfg.max_drift, kl_beta=cfg.kl_beta, mask=mask, target=cfg.target, form=cfg.form,
            actions=actions, weight=w, mean_correction=cfg.mean_correction,
        )
        if math.isfinite(metrics["loss"]):
            epochs.measure(metrics)
        # The drift guard looks before it steps: no update is taken from a policy already too
        # far from v_old, so the drift stays near the limit however large the learning rate.
        if epochs.stop_if(cfg.drift_limit is not None and metrics["delta_v_norm"] > cfg.drift_limit):
            break
        epochs.step(loss, list(policy.parameters()), optimizer)
    means = epochs.means()
    means.setdefault("grad_norm", 0.0)  # logged every iteration, 0 when no step was taken
    out = {"charts/pos_sample_frac": means.pop("pos_frac", float("nan"))}
    out |= {f"losses/{k}": v for k, v in means.items()} | epochs.counts("drift_stopped")
    return out | (task_diagnostics(learner, policy, batch, y, weights, cfg) if cfg.task_diagnostics else {})


@torch.no_grad()
def task_diagnostics(learner, policy: Policy, batch: Batch, y: Tensor, weights: Tensor | None, cfg: StepNFTConfig,
                     max_steps: int = 1024) -> dict[str, list[float | None]]:
    """Per-task labels and loss terms (``StepNFTConfig.task_diagnostics``), under ``per_task/NAME``:
    each a list with one entry per task of the run (None for a task with no steps this
    iteration), which the training loop logs as ``NAME/<task>``."""
    num_tasks = int(batch.episode_task.max()) + 1 if batch.num_steps else 0
    names = ("labels/pos_frac", "labels/weight_share", "losses/E_pos", "losses/E_neg", "losses/delta_v_norm")
    out: dict[str, list[float | None]] = {name: [None] * num_tasks for name in names}
    w_all = torch.ones(len(y)) if weights is None else weights
    for k in range(num_tasks):
        rows = (batch.step_task == k).nonzero().flatten()
        if len(rows) == 0:
            continue
        pos = y[rows] > 0
        out["labels/pos_frac"][k] = float(pos.float().mean())
        w = w_all[rows]
        out["labels/weight_share"][k] = float(w[pos].sum() / w.sum()) if w.sum() > 0 else None
        rows = rows[torch.linspace(0, len(rows) - 1, min(max_steps, len(rows))).long()]
        v = step_velocity(learner, policy, batch, rows)
        calls = batch.call[rows]
        v_old, x_t, x_next, t, dt, label, mask, actions = to_device(
            (batch.v_old[rows], batch.x_t[rows], batch.x_next[rows], batch.t[rows], batch.dt[rows], y[rows],
             batch.mask[calls], batch.actions[calls]), v.device)
        _, metrics = stepnft_loss(v, v_old, x_t, x_next, t, dt, cfg.noise_level, label, beta=cfg.beta,
                                  beta_dpo=cfg.beta_dpo, max_drift=cfg.max_drift, kl_beta=cfg.kl_beta, mask=mask,
                                  target=cfg.target, form=cfg.form, actions=actions,
                                  mean_correction=cfg.mean_correction)
        for name in ("E_pos", "E_neg", "delta_v_norm"):
            out[f"losses/{name}"][k] = metrics[name]
    return {f"per_task/{name}": values for name, values in out.items()}


# --- the algorithm ----------------------------------------------------------------------------
class StepNFT(Algorithm):
    """π-StepNFT: the EMA copy acts (Flow-SDE), the policy learns, the EMA follows."""

    name = "stepnft"
    config_class = StepNFTConfig

    def __init__(self, policy: Policy, cfg: StepNFTConfig, iterations: int, generator: torch.Generator):
        super().__init__(policy, cfg, iterations, generator)
        self.ema = make_ema_copy(policy)
        self.ema_horizon = cfg.ema_horizon or iterations

    def acting_policy(self) -> Policy:
        return self.ema.eval()

    def eval_policy(self) -> Policy:
        return self.ema if self.cfg.eval_ema else self.policy

    def update(self, batch: Batch) -> dict[str, float]:
        self.policy.train()
        return stepnft_update(self.policy, self.optimizer, batch, self.cfg, self.generator, self.guard)

    def end_iteration(self, iteration: int) -> dict[str, float]:
        decay = ema_decay(iteration, self.ema_horizon, self.cfg.ema_base, self.cfg.ema_target)
        ema_update(self.ema, self.policy, decay)
        return {"charts/ema_decay": decay}

    def state_dict(self) -> dict[str, Any]:
        # The EMA copy's own tensors only: the frozen modules it shares are saved with the policy.
        return super().state_dict() | {"ema": ema_state_dict(self.ema, self.policy)}

    def load_state_dict(self, state: dict[str, Any]) -> None:
        super().load_state_dict(state)
        load_ema_state_dict(self.ema, self.policy, state["ema"])
