"""PPO and GRPO with Flow-SDE on hand-built batches: GAE, group normalisation, the likelihood of
a call (``stepnft.algos.likelihood``), the direction of an update, checkpoints, config checks; the
setup they share with π-StepNFT (minibatches of recorded steps, episode weighting), the shaped
reward and the critic's loss."""

import pytest
import torch

from stepnft.algos.base import make_algorithm
from stepnft.algos.grpo import GRPOConfig, episode_scores, group_advantages
from stepnft.algos.likelihood import (call_rewards, call_step_rows, call_weights, policy_gradient_update,
                                      shaped_rewards, steps_log_prob, success_rewards)
from stepnft.algos.ppo import PPOConfig, call_features, gae, value_loss
from stepnft.algos.stepnft import StepNFTConfig
from stepnft.batch import Batch
from stepnft.checkpoint import flatten_state, unflatten_state
from stepnft.policies.flow import FlowPolicy, FlowPolicyConfig
from stepnft.sampling import sde_step_log_prob


def make_batch(episode, success, task=None, seed=None, noise_level=0.3, record_all=False, gen_seed=0):
    """Calls in the given episode order (``episode`` [C]); an episode's last call is its ``done``."""
    g = torch.Generator().manual_seed(gen_seed)
    torch.manual_seed(gen_seed)
    policy = FlowPolicy(FlowPolicyConfig(state_dim=3, lang_dim=0, action_dim=2, horizon=2, n_exec=2, hidden_dim=32))
    episode = torch.as_tensor(episode)
    n_calls, n_episodes = len(episode), len(success)
    last = {int(e): i for i, e in enumerate(episode.tolist())}
    done = torch.tensor([last[int(e)] == i for i, e in enumerate(episode.tolist())])
    task = torch.zeros(n_episodes, dtype=torch.int64) if task is None else torch.as_tensor(task)
    obs = {"state": torch.randn(n_calls, 3, generator=g), "task": task[episode]}
    sample = policy.sample(policy.processor(obs), noise_level=noise_level, generator=g, keep_path=record_all)
    steps = sample.recorded_steps(every_step=record_all)
    batch = Batch(
        episode_success=torch.as_tensor(success, dtype=torch.bool), episode_task=task,
        episode_length=torch.bincount(episode, minlength=n_episodes) * 2,
        episode_seed=torch.full((n_episodes,), -1) if seed is None else torch.as_tensor(seed), obs=obs,
        actions=sample.actions, mask=torch.ones(n_calls, 2, dtype=torch.bool), reward=torch.zeros(n_calls),
        done=done, episode=episode, **steps)
    return policy, batch


def test_gae_on_a_hand_computed_sequence():
    # Two episodes interleaved as the collector writes them: ep 0 has calls 0, 2, 4 (succeeds),
    # ep 1 has calls 1, 3 (fails).
    episode = torch.tensor([0, 1, 0, 1, 0])
    done = torch.tensor([False, False, False, True, True])
    reward = torch.tensor([0.0, 0, 0, 0, 1])
    value = torch.tensor([0.5, 0.2, 0.6, 0.1, 0.8])
    adv, ret = gae(reward, value, done, episode, gamma=0.9, lam=0.8)
    # ep 0: A4 = 1 - 0.8 = 0.2; A2 = (0.9*0.8 - 0.6) + 0.72*0.2 = 0.264; A0 = (0.9*0.6 - 0.5) + 0.72*0.264
    # ep 1: A3 = -0.1; A1 = (0.9*0.1 - 0.2) + 0.72*(-0.1) = -0.182
    torch.testing.assert_close(adv, torch.tensor([0.04 + 0.72 * 0.264, -0.182, 0.264, -0.1, 0.2]))
    torch.testing.assert_close(ret, adv + value)
    # λ = 1, γ = 1: the advantage is the episode's return minus the value.
    adv, _ = gae(reward, value, done, episode, gamma=1.0, lam=1.0)
    torch.testing.assert_close(adv, torch.tensor([0.5, -0.2, 0.4, -0.1, 0.2]))


def test_sparse_success_reward_only_at_the_last_call_of_a_success():
    _, batch = make_batch([0, 1, 0, 1, 0], success=[True, False])
    assert success_rewards(batch).tolist() == [0, 0, 0, 0, 1]


def test_group_normalisation_on_a_hand_built_batch():
    # Groups by (task, seed): A = (0, 7) with outcomes 1, 0, 1, 1; B = (1, 7) all failures (same
    # seed, another task); C = (0, 9) with 1, 0. Episodes interleaved.
    task = [0, 1, 0, 0, 1, 0, 0, 0]
    seed = [7, 7, 9, 7, 7, 7, 9, 7]
    success = [1, 0, 1, 0, 0, 1, 0, 1]
    _, batch = make_batch(list(range(8)), success=success, task=task, seed=seed)
    adv = group_advantages(batch)
    # A: mean 0.75, sample std 0.5; C: mean 0.5, sample std sqrt(0.5); B: zero std -> 0.
    a_hi, a_lo, c = 0.25 / 0.5, -0.75 / 0.5, 0.5 / 0.5**0.5
    torch.testing.assert_close(adv, torch.tensor([a_hi, 0.0, c, a_lo, 0.0, a_hi, -c, a_hi]), atol=1e-5, rtol=1e-5)


def test_group_advantages_need_groups():
    _, batch = make_batch([0, 1], success=[1, 0])  # unseeded resets: no groups
    with pytest.raises(ValueError, match="group_size"):
        group_advantages(batch)
    _, batch = make_batch([0, 1], success=[1, 0], seed=[3, 4])
    with pytest.raises(ValueError, match="single episode"):
        group_advantages(batch)


@pytest.mark.parametrize("record_all", [False, True])
def test_call_log_prob_sums_its_steps_and_the_first_ratio_is_one(record_all):
    policy, batch = make_batch(list(range(64)), success=[i % 2 for i in range(64)], record_all=record_all)
    rows = call_step_rows(batch)
    assert rows.shape == (64, 4 if record_all else 1)
    assert torch.all(batch.call[rows] == torch.arange(64)[:, None])
    per_call = steps_log_prob(batch, rows.flatten(), batch.v_old[rows.flatten()], 0.3).view_as(rows).sum(1)
    direct = sum(sde_step_log_prob(batch.x_next[rows[:, k]], batch.x_t[rows[:, k]], batch.v_old[rows[:, k]],
                                   batch.t[rows[:, k]], batch.dt[rows[:, k]], 0.3) for k in range(rows.shape[1]))
    torch.testing.assert_close(per_call, direct)
    # The acting policy is the policy: before any step the ratio is 1, nothing is clipped.
    cfg = PPOConfig(noise_level=0.3, update_epochs=1, minibatch_size=64, lr=1e-12)
    optimizer = torch.optim.SGD(policy.parameters(), lr=0.0)
    metrics = policy_gradient_update(policy, optimizer, batch, torch.randn(64), cfg)
    assert metrics["losses/approx_kl"] < 1e-8 and metrics["losses/clipfrac"] == 0.0


def test_an_update_raises_the_likelihood_of_positive_advantages():
    policy, batch = make_batch(list(range(256)), success=[i % 2 for i in range(256)], record_all=True)
    advantages = torch.where(batch.episode_success, 1.0, -1.0)
    rows = call_step_rows(batch)

    def log_probs():
        with torch.no_grad():
            v = policy.velocity(policy.processor(batch.steps_obs(rows.flatten())), batch.x_t[rows.flatten()],
                                batch.t[rows.flatten()])
            return steps_log_prob(batch, rows.flatten(), v, 0.3).view_as(rows).sum(1)

    before = log_probs()
    cfg = PPOConfig(noise_level=0.3, lr=3e-4, update_epochs=2, minibatch_size=64)
    metrics = policy_gradient_update(policy, torch.optim.Adam(policy.parameters(), lr=3e-4), batch, advantages, cfg)
    change = log_probs() - before
    assert change[batch.episode_success].mean() > 0 > change[~batch.episode_success].mean()
    # 256 calls of 4 recorded steps in minibatches of 64 recorded steps (16 calls), 2 epochs: as
    # many optimizer steps as π-StepNFT takes on the same 1,024 recorded steps.
    assert metrics["losses/update_steps"] == 2 * 1024 // 64 and metrics["losses/approx_kl"] > 0


def test_target_kl_stops_the_updates():
    policy, batch = make_batch(list(range(256)), success=[i % 2 for i in range(256)])
    cfg = PPOConfig(noise_level=0.3, lr=1e-2, update_epochs=8, minibatch_size=32, target_kl=1e-3)
    metrics = policy_gradient_update(policy, torch.optim.Adam(policy.parameters(), lr=1e-2), batch,
                                     torch.where(batch.episode_success, 1.0, -1.0), cfg)
    assert metrics["losses/kl_stopped"] == 1.0 and metrics["losses/update_steps"] < 64


def test_ppo_state_round_trips_through_a_checkpoint_with_its_critic():
    policy, batch = make_batch([0, 1, 0, 1, 0, 2], success=[True, False, True])
    cfg = PPOConfig(noise_level=0.3, minibatch_size=4)
    algo = make_algorithm(cfg, policy, iterations=3, generator=torch.Generator().manual_seed(0))
    assert "critic" not in algo.state_dict()
    metrics = algo.update(batch)
    for name in ("losses/policy_loss", "losses/value_loss", "losses/approx_kl", "losses/clipfrac",
                 "losses/explained_variance", "charts/advantage_std"):
        assert name in metrics
    skeleton, tensors = flatten_state(algo.state_dict())
    fresh = make_algorithm(cfg, policy, iterations=3, generator=torch.Generator())
    fresh.load_state_dict(unflatten_state(skeleton, tensors))
    features = torch.randn(5, 3)
    torch.testing.assert_close(fresh.critic(features), algo.critic(features))
    assert fresh.critic_optimizer.state_dict()["state"].keys() == algo.critic_optimizer.state_dict()["state"].keys()


def test_rollout_specs_and_config_checks():
    assert PPOConfig(sde_steps="one").rollout_spec().record_steps == "one"
    spec = make_algorithm(GRPOConfig(group_size=4), make_batch([0], [True])[0], 1, torch.Generator()).rollout
    assert (spec.group_size, spec.stochastic_steps, spec.record_steps) == (4, "all", "all")
    assert make_algorithm(PPOConfig(), make_batch([0], [True])[0], 1, torch.Generator()).rollout.group_size == 1
    with pytest.raises(ValueError, match="algo.noise_level must be > 0 for PPO and GRPO"):
        PPOConfig(noise_level=0.0)  # no noise, no likelihood: the ODE ablation is π-StepNFT's
    with pytest.raises(ValueError, match="algo.group_size must be >= 2 for GRPO"):
        GRPOConfig(group_size=1)
    with pytest.raises(ValueError, match=r"algo.gae_lambda must be a finite number in \[0, 1\], got 1.5"):
        PPOConfig(gae_lambda=1.5)


def test_minibatches_without_advantage_are_skipped():
    """GRPO's uniform groups give 0 advantage: no step is taken (Adam's momentum would still move
    the policy), and the metric names stay."""
    policy, batch = make_batch(list(range(64)), success=[i % 2 for i in range(64)])
    before = [p.detach().clone() for p in policy.parameters()]
    optimizer = torch.optim.Adam(policy.parameters(), lr=1e-2)
    policy_gradient_update(policy, optimizer, batch, torch.ones(64), PPOConfig(minibatch_size=32, update_epochs=1))
    moved = [p.detach().clone() for p in policy.parameters()]
    metrics = policy_gradient_update(policy, optimizer, batch, torch.zeros(64), PPOConfig(minibatch_size=32))
    assert metrics["losses/skipped_empty"] == 4 and metrics["losses/update_steps"] == 0
    assert metrics["losses/approx_kl"] != metrics["losses/approx_kl"]  # NaN: nothing measured
    assert all(torch.equal(a, b) for a, b in zip(moved, policy.parameters()))
    assert not all(torch.equal(a, b) for a, b in zip(before, moved))


def test_every_algorithm_takes_the_same_optimizer_steps_on_the_same_recorded_steps():
    """One definition of the minibatch: ``minibatch_size`` recorded steps, for π-StepNFT (a sample
    is a recorded step) and PPO/GRPO (a sample is a call of K = 4 recorded steps)."""
    episode = [i % 40 for i in range(300)]
    steps = {}
    for cfg in (StepNFTConfig(noise_level=0.3, minibatch_size=128, update_epochs=2),
                PPOConfig(noise_level=0.3, minibatch_size=128, update_epochs=2),
                GRPOConfig(noise_level=0.3, minibatch_size=128, update_epochs=2, group_size=2)):
        policy, batch = make_batch(sorted(episode), success=[i % 3 == 0 for i in range(40)],
                                   seed=[i // 2 for i in range(40)], record_all=True)
        algo = make_algorithm(cfg, policy, iterations=1, generator=torch.Generator().manual_seed(0))
        steps[cfg.name] = algo.update(batch)["losses/update_steps"]
    assert steps == {"stepnft": 2 * 10, "ppo": 2 * 10, "grpo": 2 * 10}  # 1,200 recorded steps: 10 minibatches


@pytest.mark.parametrize("weighting, expected", [(False, -0.5), (True, 0.0)])
def test_episode_weighting_gives_every_episode_the_same_weight(weighting, expected):
    """Episode 0 (6 calls, advantage +1) against episode 1 (2 calls, -1): at ratio 1 the surrogate
    is ``-mean(w A)``: -0.5 by calls, 0 with every episode weighing the same."""
    policy, batch = make_batch([0, 0, 1, 0, 0, 1, 0, 0], success=[True, False])
    advantages = torch.where(batch.episode == 0, 1.0, -1.0)
    cfg = PPOConfig(noise_level=0.3, update_epochs=1, minibatch_size=64, episode_weighting=weighting)
    metrics = policy_gradient_update(policy, torch.optim.SGD(policy.parameters(), lr=0.0), batch, advantages, cfg)
    assert metrics["losses/policy_loss"] == pytest.approx(expected, abs=1e-6)
    weights = call_weights(batch, cfg)
    assert (weights is None) == (not weighting)
    if weighting:
        torch.testing.assert_close(weights, torch.tensor([2 / 3, 2 / 3, 2, 2 / 3, 2 / 3, 2, 2 / 3, 2 / 3]))


def test_shaped_rewards_are_potential_based_shaping_of_the_call_levels():
    # Episode 0 (calls 0, 2, 4; succeeds): levels 1, 3, 2 (reward per executed step, 2 steps a
    # call); episode 1 (calls 1, 3; fails): levels 5, 4. r_c = success_c + γ L_c - L_{c-1}, L_{-1} = L_0.
    _, batch = make_batch([0, 1, 0, 1, 0], success=[True, False])
    batch.reward = torch.tensor([2.0, 10.0, 6.0, 8.0, 4.0])
    torch.testing.assert_close(shaped_rewards(batch, gamma=0.5), torch.tensor([-0.5, -2.5, 0.5, -3.0, -1.0]))
    assert call_rewards(batch, PPOConfig()).tolist() == success_rewards(batch).tolist() == [0, 0, 0, 0, 1]
    # Undiscounted, an episode's sum telescopes: success + last level - first level (GRPO's score).
    torch.testing.assert_close(shaped_rewards(batch, gamma=1.0), torch.tensor([0.0, 0.0, 2.0, -1.0, 0.0]))
    grpo = GRPOConfig(reward="shaped")
    torch.testing.assert_close(episode_scores(batch, grpo), torch.tensor([1 + 2 - 1.0, 4 - 5.0]))
    assert episode_scores(batch, GRPOConfig()).tolist() == [1.0, 0.0]


def test_value_loss_squared_huber_and_clipped():
    value, old, returns = torch.tensor([0.0, 0.0, 1.0]), torch.tensor([0.0, 0.5, 0.9]), torch.tensor([3.0, 0.2, 1.0])
    squared = 0.5 * (value - returns) ** 2  # 4.5, 0.02, 0
    assert value_loss(value, old, returns, PPOConfig()).item() == pytest.approx(squared.mean().item())
    # Huber δ = 1: the first error (3) is linear, 1 * (3 - 0.5).
    huber = value_loss(value, old, returns, PPOConfig(huber_delta=1.0))
    assert huber.item() == pytest.approx((2.5 + 0.02 + 0.0) / 3)
    # Value clip 0.2 (RLinf's): the larger of the clipped and unclipped errors. The first prediction
    # moved 1.0 from its rollout value 0, clipped to 0.2 (error 2.8 > 2); the second moved -0.5,
    # clipped to 0.3 (error 0.1 < 0.2: the unclipped one counts); the third is within 0.2.
    moved = torch.tensor([1.0, 0.0, 1.0])
    clipped = value_loss(moved, old, returns, PPOConfig(value_clip=0.2))
    assert clipped.item() == pytest.approx((0.5 * 2.8**2 + 0.02 + 0.0) / 3)
    weighted = value_loss(value, old, returns, PPOConfig(), weights=torch.tensor([0.0, 3.0, 0.0]))
    assert weighted.item() == pytest.approx(0.02)


# --- the critic's features: policy.value_features, detached or shared ----------------------------
def camera_batch(calls=24, gen_seed=0):
    """A camera FlowPolicy (one 16 px view, no instruction) and a batch of its Flow-SDE calls,
    episodes of 3 calls, every other one successful."""
    g = torch.Generator().manual_seed(gen_seed)
    torch.manual_seed(gen_seed)
    policy = FlowPolicy(FlowPolicyConfig(state_dim=3, lang_dim=0, action_dim=2, horizon=2, n_exec=2, hidden_dim=32,
                                         cameras=["corner"], image_size=16, image_channels=4, image_features=8))
    episode = torch.arange(calls) // 3
    n_episodes = calls // 3
    obs = {"state": torch.randn(calls, 3, generator=g), "task": torch.zeros(calls, dtype=torch.int64),
           "image": torch.randint(0, 256, (calls, 1, 3, 16, 16), generator=g, dtype=torch.uint8)}
    sample = policy.sample(policy.prepare(obs), noise_level=0.5, generator=g)
    batch = Batch(
        episode_success=torch.arange(n_episodes) % 2 == 0, episode_task=torch.zeros(n_episodes, dtype=torch.int64),
        episode_length=torch.full((n_episodes,), 6), episode_seed=torch.full((n_episodes,), -1), obs=obs,
        actions=sample.actions, mask=torch.ones(calls, 2, dtype=torch.bool), reward=torch.zeros(calls),
        done=torch.arange(calls) % 3 == 2, episode=episode, **sample.recorded_steps(every_step=False))
    return policy, batch


def test_value_features_are_the_encoders_output_by_default():
    """The MLP's critic reads what it read before the seam: ``encode(obs)`` flattened, detached."""
    policy, batch = camera_batch()
    obs = policy.prepare(batch.obs)
    features = call_features(policy, batch)
    assert torch.equal(features, policy.encode(obs).flatten(1)) and not features.requires_grad
    assert policy.value_features(obs).requires_grad  # the caller decides whether to detach

    class CacheContext(FlowPolicy):
        def encode(self, obs):
            return {"kv": super().encode(obs)}

    with pytest.raises(NotImplementedError, match="needs its own value_features"):
        CacheContext(policy.config).value_features(obs)


@pytest.mark.parametrize("shared", [False, True])
def test_the_value_loss_alone_trains_the_encoder_only_when_the_critic_shares_it(shared):
    """One PPO step whose policy loss cannot reach the CNN (the velocity net ignores the image
    features: their input weights are 0, so their gradient is exactly 0): the CNN moves from the
    value loss alone with ``critic_shares_encoder``, and not at all without it."""
    policy, batch = camera_batch()
    image_cols = slice(3, 3 + policy.image_encoder.out_dim)  # the context is [state, image features]
    with torch.no_grad():
        policy.net[0].weight[:, image_cols] = 0.0
    cnn = {n: p.detach().clone() for n, p in policy.image_encoder.named_parameters()}
    cfg = PPOConfig(noise_level=0.5, update_epochs=1, minibatch_size=64, critic_shares_encoder=shared)
    algo = make_algorithm(cfg, policy, iterations=1, generator=torch.Generator().manual_seed(0))
    metrics = algo.update(batch)
    assert metrics["losses/update_steps"] == 1 and metrics["losses/value_loss"] > 0
    moved = [n for n, p in policy.image_encoder.named_parameters() if not torch.equal(p, cnn[n])]
    assert bool(moved) == shared, moved
    # The wiring: a shared head is a second group of the policy's optimizer, at the critic's rate.
    assert (algo.critic_optimizer is None) == shared
    assert len(algo.optimizer.param_groups) == (2 if shared else 1)
    if shared:
        assert algo.optimizer.param_groups[1]["lr"] == cfg.critic_lr
        assert algo.optimizer.param_groups[1]["params"] == list(algo.critic.parameters())


def test_a_shared_critic_resumes_exactly_from_a_checkpoint():
    policy, batch = camera_batch()
    cfg = PPOConfig(noise_level=0.5, update_epochs=1, minibatch_size=16, critic_shares_encoder=True)
    algo = make_algorithm(cfg, policy, iterations=2, generator=torch.Generator().manual_seed(0))
    algo.update(batch)
    state = algo.state_dict()
    assert "critic" in state and "critic_optimizer" not in state  # its Adam state is in the policy's optimizer
    skeleton, tensors = flatten_state(state)
    copy = FlowPolicy(policy.config)
    copy.load_state_dict(policy.state_dict())
    fresh = make_algorithm(cfg, copy, iterations=2, generator=torch.Generator())
    # (cloned: on the CPU the flattened tensors are the optimizer's own, which the next step changes in place)
    fresh.load_state_dict(unflatten_state(skeleton, {k: v.clone() for k, v in tensors.items()}))
    for a in (algo, fresh):
        a.generator.manual_seed(5)
        a.update(batch)
    for a, b in ((policy, copy), (algo.critic, fresh.critic)):
        for (name, x), y in zip(a.state_dict().items(), b.state_dict().values()):
            assert torch.equal(x, y), name
    with pytest.raises(ValueError, match="algo.value_coef"):
        PPOConfig(value_coef=0.0)
