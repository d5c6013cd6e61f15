"""The data-parallel learner: with 2 processes (gloo) the gradient of a minibatch, a whole
update of every algorithm (π-StepNFT, PPO with its critic, GRPO) and a whole ``torchrun``
training run equal one process's."""

import json
import os
import subprocess
import sys

import pytest
import torch
import torch.distributed as dist
import torch.multiprocessing as mp

from stepnft import distributed
from stepnft.algos.base import make_algorithm
from stepnft.algos.grpo import GRPOConfig
from stepnft.algos.ppo import PPOConfig
from stepnft.algos.stepnft import StepNFTConfig
from stepnft.cli import main
from stepnft.config import EnvConfig
from stepnft.envs import make_vec_env
from stepnft.losses import stepnft_loss
from stepnft.policies.flow import FlowPolicy, FlowPolicyConfig
from stepnft.rollout.collector import Collector
from stepnft.runs import read_metrics

BANDIT_POLICY = FlowPolicyConfig(state_dim=2, action_dim=2, horizon=2, n_exec=2, lang_dim=0, hidden_dim=32,
                                 num_layers=2)
ALGOS = {  # odd minibatches: the two processes' shares differ in size
    "stepnft": StepNFTConfig(noise_level=0.3, minibatch_size=37, update_epochs=2),
    "ppo": PPOConfig(noise_level=0.3, minibatch_size=13, update_epochs=2),
    "grpo": GRPOConfig(noise_level=0.3, minibatch_size=13, update_epochs=2, group_size=2),
}


def new_policy() -> FlowPolicy:
    torch.manual_seed(0)
    return FlowPolicy(BANDIT_POLICY)


def bandit_batches() -> dict:
    """A batch per algorithm, collected as it asks (GRPO: groups of 2 from one initial state)."""
    venv = make_vec_env(EnvConfig(name="bandit", tasks=["bandit"], envs_per_task=50, max_episode_steps=2), 2, seed=0)
    batches = {}
    for name, cfg in ALGOS.items():
        spec = make_algorithm(cfg, new_policy(), 1, torch.Generator()).rollout
        batch = Collector(venv, seed=0).collect(new_policy(), 100, spec)
        batch.episode_success[::3] = True  # a random policy never succeeds; the updates need both outcomes
        batches[name] = batch
    venv.close()
    return batches


def minibatch_gradient(batch) -> dict[str, torch.Tensor]:
    """The gradient of one π-StepNFT minibatch loss, through the helpers the update uses."""
    policy, cfg = new_policy(), ALGOS["stepnft"]
    learner = distributed.data_parallel(policy)
    idx = torch.arange(3, 3 + cfg.minibatch_size)
    y = batch.step_success.float() * 2 - 1
    v = distributed.shard_forward(lambda part: learner(policy.processor(batch.steps_obs(part)), batch.x_t[part],
                                                       batch.t[part]), idx)
    loss, _ = stepnft_loss(v, batch.v_old[idx], batch.x_t[idx], batch.x_next[idx], batch.t[idx], batch.dt[idx],
                           cfg.noise_level, y[idx], mask=batch.mask[batch.call[idx]])
    loss.backward()
    return {name: p.grad.clone() for name, p in policy.named_parameters()}


def whole_update(name: str, batch) -> tuple[dict[str, torch.Tensor], dict[str, float]]:
    """Everything one iteration of algorithm ``name`` learns from ``batch``."""
    algo = make_algorithm(ALGOS[name], new_policy(), 3, torch.Generator().manual_seed(1))
    metrics = algo.update(batch) | algo.end_iteration(0)
    return {**algo.policy.state_dict(), **{f"algo.{k}": v for k, v in flat_tensors(algo.state_dict())}}, metrics


def flat_tensors(tree, prefix=""):
    if torch.is_tensor(tree):
        yield prefix, tree
    elif isinstance(tree, dict):
        for k, v in tree.items():
            yield from flat_tensors(v, f"{prefix}.{k}" if prefix else str(k))


def _rank(rank: int, world: int, init_file: str, batch_file: str, out_dir: str) -> None:
    torch.set_num_threads(1)
    dist.init_process_group("gloo", init_method=f"file://{init_file}", rank=rank, world_size=world)
    try:
        batches = torch.load(batch_file, weights_only=False)
        result = {"grad": minibatch_gradient(batches["stepnft"])}
        result |= {name: whole_update(name, batch) for name, batch in batches.items()}
        torch.save(result, f"{out_dir}/rank{rank}.pt")
    finally:
        dist.destroy_process_group()


@pytest.fixture(scope="module")
def two_processes(tmp_path_factory):
    """What each of 2 processes computed, and the batches they shared."""
    tmp = tmp_path_factory.mktemp("ddp")
    batches = bandit_batches()
    torch.save(batches, tmp / "batches.pt")
    mp.spawn(_rank, args=(2, str(tmp / "init"), str(tmp / "batches.pt"), str(tmp)), nprocs=2, join=True)
    return batches, [torch.load(tmp / f"rank{r}.pt", weights_only=False) for r in range(2)]


def test_two_processes_get_the_one_process_gradient(two_processes):
    batches, ranks = two_processes
    assert not dist.is_initialized() and distributed.world_size() == 1
    alone = minibatch_gradient(batches["stepnft"])
    for rank in ranks:
        for name, grad in alone.items():
            torch.testing.assert_close(rank["grad"][name], grad, rtol=1e-5, atol=1e-7)
    assert any(g.abs().sum() > 0 for g in alone.values())


@pytest.mark.parametrize("name", list(ALGOS))
def test_two_processes_take_the_one_process_update(two_processes, name):
    batches, ranks = two_processes
    learned, metrics = whole_update(name, batches[name])
    assert metrics["losses/update_steps"] > 0 and metrics["losses/skipped_nonfinite"] == 0
    for rank in ranks:
        rank_learned, rank_metrics = rank[name]
        assert rank_learned.keys() == learned.keys() and rank_metrics.keys() == metrics.keys()
        for key, value in learned.items():
            torch.testing.assert_close(rank_learned[key], value, rtol=1e-4, atol=1e-6)
        for key, value in metrics.items():
            assert rank_metrics[key] == pytest.approx(value, rel=1e-4, abs=1e-6, nan_ok=True), key
    assert not torch.equal(learned["net.0.weight"], new_policy().state_dict()["net.0.weight"])


@pytest.mark.slow
def test_torchrun_training_equals_one_process(tmp_path):
    new_policy().save_pretrained(tmp_path / "init")
    args = ["--init", str(tmp_path / "init"), "--env.name", "bandit", "--env.tasks", "bandit",
            "--env.envs-per-task", "64", "--env.max-episode-steps", "2", "--policy.state-dim", "2",
            "--policy.action-dim", "2", "--policy.horizon", "2", "--policy.n-exec", "2", "--policy.lang-dim", "0",
            "--policy.hidden-dim", "32", "--policy.num-layers", "2", "--iterations", "3", "--checkpoint-every", "2",
            "--episodes-per-iteration", "64", "--eval.episodes", "64", "--eval.every", "0",
            "--algo.minibatch-size", "33", "--algo.noise-level", "0.3"]
    assert main(["train", "--run-dir", str(tmp_path / "one"), *args]) == 0
    env = os.environ | {"OMP_NUM_THREADS": "1"}
    out = subprocess.run([sys.executable, "-m", "torch.distributed.run", "--standalone", "--nproc-per-node", "2",
                          "-m", "stepnft.cli", "train", "--run-dir", str(tmp_path / "two"), *args],
                         capture_output=True, text=True, timeout=300, env=env)
    assert out.returncode == 0, out.stderr[-3000:]
    one, two = read_metrics(tmp_path / "one" / "metrics.jsonl"), read_metrics(tmp_path / "two" / "metrics.jsonl")
    assert [r["iteration"] for r in two] == [r["iteration"] for r in one] == [0, 1, 2, 3, 3]
    for mine, theirs in zip(one, two):
        assert mine["env_steps"] == theirs["env_steps"]
        for key in (k for k in mine if k.startswith("losses/")):
            assert theirs[key] == pytest.approx(mine[key], rel=1e-3, abs=1e-5), key
    weights = [FlowPolicy.from_pretrained(tmp_path / run / "policy").state_dict() for run in ("one", "two")]
    for name in weights[0]:
        torch.testing.assert_close(weights[1][name], weights[0][name], rtol=1e-3, atol=1e-5)
    # Rank 0 alone wrote the run: one set of checkpoints, one summary.
    assert sorted(p.name for p in (tmp_path / "two" / "checkpoints").iterdir()) == ["LATEST", "iter_000002", "iter_000003"]
    assert json.loads((tmp_path / "two" / "summary.json").read_text())["iterations"] == 3
