"""The data-parallel learner: with 2 processes (gloo) the gradient of a minibatch, a whole
π-StepNFT update and a whole ``torchrun`` training run equal one process's."""

import json
import os
import subprocess
import sys

import pytest
import torch
import torch.distributed as dist
import torch.multiprocessing as mp

from stepnft import distributed
from stepnft.algos.base import RolloutSpec, make_optimizer
from stepnft.algos.stepnft import StepNFTConfig, stepnft_update
from stepnft.cli import main
from stepnft.envs import make_vec_env
from stepnft.config import EnvConfig
from stepnft.losses import stepnft_loss
from stepnft.policies.flow import FlowPolicy, FlowPolicyConfig
from stepnft.rollout.collector import Collector
from stepnft.runs import read_metrics

BANDIT_POLICY = FlowPolicyConfig(state_dim=2, action_dim=2, horizon=2, n_exec=2, lang_dim=0, hidden_dim=32,
                                 num_layers=2)
CFG = StepNFTConfig(noise_level=0.3, minibatch_size=37, update_epochs=2)  # 37: shares of 19 and 18


def new_policy() -> FlowPolicy:
    torch.manual_seed(0)
    return FlowPolicy(BANDIT_POLICY)


def bandit_batch():
    venv = make_vec_env(EnvConfig(name="bandit", tasks=["bandit"], envs_per_task=50, max_episode_steps=2), 2, seed=0)
    batch = Collector(venv, seed=0).collect(new_policy(), 100, RolloutSpec(0.3, record_steps="all"))
    venv.close()
    return batch


def minibatch_gradient(batch) -> dict[str, torch.Tensor]:
    """The gradient of one minibatch's π-StepNFT loss, through the helpers the update uses."""
    policy = new_policy()
    learner = distributed.data_parallel(policy)
    idx = torch.arange(3, 3 + CFG.minibatch_size)
    y = batch.step_success.float() * 2 - 1
    v = distributed.shard_forward(lambda part: learner(policy.processor(batch.steps_obs(part)), batch.x_t[part],
                                                       batch.t[part]), idx)
    loss, _ = stepnft_loss(v, batch.v_old[idx], batch.x_t[idx], batch.x_next[idx], batch.t[idx], batch.dt[idx],
                           CFG.noise_level, y[idx], mask=batch.mask[batch.call[idx]])
    distributed.backward(loss)
    return {name: p.grad.clone() for name, p in policy.named_parameters()}


def whole_update(batch) -> tuple[dict[str, torch.Tensor], dict[str, float]]:
    policy = new_policy()
    metrics = stepnft_update(policy, make_optimizer(policy.parameters(), CFG), batch, CFG,
                             torch.Generator().manual_seed(1))
    return policy.state_dict(), metrics


def _rank(rank: int, world: int, init_file: str, batch_file: str, out_dir: str) -> None:
    torch.set_num_threads(1)
    dist.init_process_group("gloo", init_method=f"file://{init_file}", rank=rank, world_size=world)
    try:
        batch = torch.load(batch_file, weights_only=False)
        torch.save({"grad": minibatch_gradient(batch), "update": whole_update(batch)}, f"{out_dir}/rank{rank}.pt")
    finally:
        dist.destroy_process_group()


@pytest.fixture(scope="module")
def two_processes(tmp_path_factory):
    """What each of 2 processes computed, and the batch they shared."""
    tmp = tmp_path_factory.mktemp("ddp")
    batch = bandit_batch()
    torch.save(batch, tmp / "batch.pt")
    mp.spawn(_rank, args=(2, str(tmp / "init"), str(tmp / "batch.pt"), str(tmp)), nprocs=2, join=True)
    return batch, [torch.load(tmp / f"rank{r}.pt", weights_only=False) for r in range(2)]


def test_two_processes_get_the_one_process_gradient(two_processes):
    batch, ranks = two_processes
    assert not dist.is_initialized() and distributed.world_size() == 1
    alone = minibatch_gradient(batch)
    for rank in ranks:
        for name, grad in alone.items():
            torch.testing.assert_close(rank["grad"][name], grad, rtol=1e-5, atol=1e-7)
    assert any(g.abs().sum() > 0 for g in alone.values())


def test_two_processes_take_the_one_process_update(two_processes):
    batch, ranks = two_processes
    weights, metrics = whole_update(batch)
    assert metrics["losses/update_steps"] == 2 * -(-batch.num_steps // CFG.minibatch_size)
    for rank in ranks:
        rank_weights, rank_metrics = rank["update"]
        for name, value in weights.items():
            torch.testing.assert_close(rank_weights[name], value, rtol=1e-4, atol=1e-6)
        assert rank_metrics.keys() == metrics.keys()
        assert all(rank_metrics[k] == pytest.approx(v, rel=1e-4, abs=1e-6) for k, v in metrics.items())
    assert not torch.equal(weights["net.0.weight"], new_policy().state_dict()["net.0.weight"])


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
