"""The paper's ablations (Sec. 5.3, Figure 4), lab/ablations.py: every new gradient
against finite differences, each check shown to catch a wrong gradient; each switch's
behaviour; then each ablation end to end, `python -m lab.ablations` from the repository
root, killed halfway and resumed."""

from __future__ import annotations

import dataclasses
import json
import math

import numpy as np
import pytest
from gradcheck import assert_gradient_close, numerical_gradient
from helpers import (
    assert_one_line_error,
    interrupted_after,
    read_rows,
    release,
    run_module,
    run_script,
)
from hypothesis import assume, given
from hypothesis import strategies as st
from test_offpac_il import (
    OBJECTIVE_EPS,
    OBJECTIVE_TOL,
    TINY_RUN,
    away_from_kinks,
    random_triplets,
    small_learner,
    targets_and_continuation,
    tiny_config,
)
from threadpoolctl import threadpool_limits

import harness
import nets
import offpac_il
from lab import ablations
from lab.ablations import AblationConfig

# The dev profile (1000 examples per test) found small gradient elements (behind units
# on the leaky side of their ReLU) that missed 5e-5 relative error: ~4e-9 ones by ~1e-12
# absolute (the difference's rounding), a 9e-7 one by 1.3e-10 (its truncation error,
# O(eps^2) with the curvature of the whole loss). The checks below hold elements under
# 1e-5 to 5e-5 * 1e-5 = 5e-10 absolute instead; a wrong gradient is off by O(1) on the
# large elements (~1e-2 and more), as the wrong-gradient tests show.
OBJECTIVE_FLOOR = 1e-5
OBJECTIVES = ("discriminator", "entropy")
# Each ablation's switch on the command line (as lab/experiments.py's METHODS has them).
ABLATIONS = {
    "Ours+OnP": ("--on-policy",),
    "Ours+IRL(D)": ("--reward-learning", "discriminator"),
    "Ours+IRL(E)": ("--reward-learning", "entropy"),
    "Ours+GP": ("--policy-type", "gaussian"),
    "Ours+DP": ("--policy-type", "deterministic"),
}


def ablation_learner(seed: int, **overrides):
    """small_learner with lab/ablations.py's config and variant."""
    return small_learner(
        seed, config_class=AblationConfig, variant_of=ablations.variant_of, **overrides
    )


# ---------------------------------------------------------------------------------------
# Ours+IRL: the reward objectives (2) and (8), and the critic's objective (15).
# ---------------------------------------------------------------------------------------


def reward_learner(seed: int, objective="entropy", **overrides):
    """A small float64 learner with a reward network r_omega (QN's hidden sizes)."""
    learner, config, rng = ablation_learner(seed, reward_learning=objective, **overrides)
    reward = learner.extra_state["reward"].net
    assert reward.sizes == learner.critic.sizes and reward.head == "sigmoid"
    assert reward.dtype == np.float64
    return learner, config, rng


def reward_of(learner) -> nets.MLP:
    return learner.extra_state["reward"].net


def reward_loss_direct(learner, batch, n_expert, objective) -> float:
    """Objectives (2) (as GAIL's discriminator) and (8), negated, written out in p."""
    r, _ = reward_of(learner).forward((batch.states, batch.actions))
    r_expert, r_learner = r[:n_expert, 0], r[n_expert:, 0]
    if objective == "discriminator":
        return -np.log(r_expert).mean() - np.log(1 - r_learner).mean()
    entropy = -r_learner * np.log(r_learner) - (1 - r_learner) * np.log(1 - r_learner)  # (9)
    return -r_expert.mean() - entropy.mean()


@given(
    seed=st.integers(0, 2**16),
    n_expert=st.integers(1, 4),
    n_learner=st.integers(1, 4),
    objective=st.sampled_from(OBJECTIVES),
)
def test_reward_objective_gradient_matches_finite_differences(seed, n_expert, n_learner, objective):
    learner, _, rng = reward_learner(seed, objective)
    reward = reward_of(learner)
    batch = random_triplets(rng, n_expert + n_learner)
    assume(away_from_kinks(reward.forward((batch.states, batch.actions))[1]))
    args = (reward, batch.states, batch.actions, n_expert, objective)

    def loss():
        return ablations.reward_loss_and_grads(*args)[0]

    np.testing.assert_allclose(
        loss(), reward_loss_direct(learner, batch, n_expert, objective), rtol=1e-12
    )
    _, grads, _ = ablations.reward_loss_and_grads(*args)
    assert set(grads) == set(reward.params)
    for name, param in reward.params.items():
        assert_gradient_close(
            grads[name],
            numerical_gradient(loss, param, OBJECTIVE_EPS),
            OBJECTIVE_TOL,
            f"objective ({'2' if objective == 'discriminator' else '8'}) d/d{name}",
            floor=OBJECTIVE_FLOOR,
        )


@pytest.mark.parametrize("objective", OBJECTIVES)
def test_reward_objective_check_catches_a_wrong_gradient(objective, monkeypatch):
    """Two common slips, each caught: (2) backpropagated through the sigmoid head once
    more (dL/dx taken for dL/dr), (8) with dH/dp = -x used as dH/dx."""
    learner, _, rng = reward_learner(5, objective)
    reward = reward_of(learner)
    batch = random_triplets(rng, 6)
    args = (reward, batch.states, batch.actions, 3, objective)

    def loss():
        return ablations.reward_loss_and_grads(*args)[0]

    numeric = numerical_gradient(loss, reward.params["W1"], OBJECTIVE_EPS)
    right = ablations.reward_loss_and_grads(*args)[1]["W1"]
    assert_gradient_close(right, numeric, OBJECTIVE_TOL, floor=OBJECTIVE_FLOOR)
    if objective == "discriminator":
        backward = reward.backward
        monkeypatch.setattr(
            reward, "backward", lambda d, cache, **kw: backward(d, cache, input_grads=False)
        )
    else:
        monkeypatch.setattr(ablations, "bernoulli_entropy_grad", lambda x: -x)
    wrong = ablations.reward_loss_and_grads(*args)[1]["W1"]
    with pytest.raises(AssertionError):
        assert_gradient_close(wrong, numeric, OBJECTIVE_TOL, floor=OBJECTIVE_FLOOR)


def test_reward_objectives_move_r_where_the_paper_says():
    """Gradient descent on (2) sends r to 1 on expert pairs and 0 on the learner's; on (8)
    to 1 on expert pairs and 1/2 on the learner's (Sec. 3.1.1)."""
    for objective, r_learner in (("discriminator", 0.0), ("entropy", 0.5)):
        learner, config, rng = reward_learner(6, objective, critic_hidden=(16, 16))
        reward = reward_of(learner)
        batch = random_triplets(rng, 8)
        batch.states[4:] += 3.0  # the learner's pairs, apart from the expert's
        optimizer = nets.RMSProp()
        for _ in range(1500):
            _, grads, _ = ablations.reward_loss_and_grads(
                reward, batch.states, batch.actions, 4, objective
            )
            optimizer.step(reward.params, grads, 1e-2)
        r, _ = reward.forward((batch.states, batch.actions))
        np.testing.assert_allclose(r[:4, 0], 1.0, atol=0.05)
        np.testing.assert_allclose(r[4:, 0], r_learner, atol=0.05)


@pytest.mark.parametrize("termination", offpac_il.TERMINATIONS)
def test_critic_targets_with_a_learned_reward(termination):
    """t = r_omega(s, a) mean_k q'(s', a'_k)^gamma on every row (Eq. 13 in 15): no /2."""
    learner, config, rng = reward_learner(3, termination=termination, target_samples=4)
    t, expected, batch, _ = targets_and_continuation(learner, config, rng, ablations.irl_targets)
    r, _ = reward_of(learner).forward((batch.states, batch.actions))
    np.testing.assert_allclose(t, r[:, 0] * expected, rtol=1e-10)


@given(seed=st.integers(0, 2**16), n=st.integers(1, 4), objective=st.sampled_from(OBJECTIVES))
def test_critic_objective_15_gradient_matches_finite_differences(seed, n, objective):
    """Objective (15) w.r.t. every critic parameter, its target (r_omega and nu') frozen."""
    learner, config, rng = reward_learner(seed, objective, target_samples=3)
    batch = random_triplets(rng, 2 * n, terminal_fraction=0.2)
    t = ablations.irl_targets(learner, batch, n, config, rng)[0][:, None]
    assume(away_from_kinks(learner.critic.forward((batch.states, batch.actions))[1]))

    def loss():
        return offpac_il.critic_loss_and_grads(learner.critic, batch, t, n)[0]

    q, _ = learner.critic.forward((batch.states, batch.actions))
    js = nets.js_divergence(np.log(q) - np.log1p(-q), t)[:, 0]
    expected = js[:n].mean() + js[n:].mean()  # the expert rows' mean + the replay rows'
    np.testing.assert_allclose(loss(), expected, rtol=1e-10)
    _, grads, _ = offpac_il.critic_loss_and_grads(learner.critic, batch, t, n)
    assert set(grads) == set(learner.critic.params)
    for name, param in learner.critic.params.items():
        assert_gradient_close(
            grads[name],
            numerical_gradient(loss, param, OBJECTIVE_EPS),
            OBJECTIVE_TOL,
            f"objective (15) d/d{name}",
            floor=OBJECTIVE_FLOOR,
        )


def test_critic_objective_15_check_catches_a_wrong_gradient():
    """The gradient of (18) (targets 1 and 1/2) taken for (15)'s loss is caught."""
    learner, config, rng = reward_learner(7)
    batch = random_triplets(rng, 6)
    t15 = ablations.irl_targets(learner, batch, 3, config, np.random.default_rng(1))[0][:, None]
    t18 = offpac_il.critic_targets(learner, batch, 3, config, np.random.default_rng(1))[0]
    assert not np.allclose(t15[:, 0], t18)

    def loss():
        return offpac_il.critic_loss_and_grads(learner.critic, batch, t15, 3)[0]

    numeric = numerical_gradient(loss, learner.critic.params["W0"], OBJECTIVE_EPS)
    right = offpac_il.critic_loss_and_grads(learner.critic, batch, t15, 3)[1]["W0"]
    wrong = offpac_il.critic_loss_and_grads(learner.critic, batch, t18[:, None], 3)[1]["W0"]
    assert_gradient_close(right, numeric, OBJECTIVE_TOL, floor=OBJECTIVE_FLOOR)
    with pytest.raises(AssertionError):
        assert_gradient_close(wrong, numeric, OBJECTIVE_TOL, floor=OBJECTIVE_FLOOR)


def test_reward_step_comes_before_the_critic_step(monkeypatch):
    """Each update moves r_omega on the critic's triplets, then the critic by (15), whose
    targets read the reward as that step left it."""
    learner, config, rng = reward_learner(8, objective="discriminator", batch_size=4)
    reward = reward_of(learner)
    before = reward.copy()
    order = []
    reward_step, critic_step = ablations.reward_loss_and_grads, offpac_il.critic_step

    def recording_reward(reward, states, *args):
        order.append(("reward", states.copy()))
        return reward_step(reward, states, *args)

    def recording_targets(learner, batch, *args):
        order.append(("targets", batch.states.copy()))
        assert not np.array_equal(reward_of(learner).params["W0"], before.params["W0"])
        return ablations.irl_targets(learner, batch, *args)

    monkeypatch.setattr(ablations, "reward_loss_and_grads", recording_reward)
    monkeypatch.setattr(
        offpac_il,
        "critic_step",
        lambda *args, **kw: critic_step(*args[:6], targets=recording_targets),
    )
    expert_rows, replay_rows = random_triplets(rng, 4), random_triplets(rng, 4)
    stats = ablations.irl_critic_step(learner, expert_rows, replay_rows, config, 1e-3, rng)
    assert [name for name, _ in order] == ["reward", "targets"]
    np.testing.assert_array_equal(order[0][1], order[1][1])  # the same 8 triplets
    assert {"reward_loss", "r_expert", "r_replay", "critic_loss"} <= set(stats)
    assert all(not np.array_equal(before.params[k], v) for k, v in reward.params.items())


# ---------------------------------------------------------------------------------------
# Ours+GP: a = mu(s) + sigma(s) eps, reparameterised (gradient 6).
# ---------------------------------------------------------------------------------------


def gaussian_learner(seed: int, log_std_bias: float | None = None):
    learner, config, rng = ablation_learner(seed, policy_type="gaussian")
    net = learner.policy.net
    assert learner.policy.noise_dim == 2 and net.sizes == [3, 6, 5, 4]  # [s] -> mu, l
    last = net.n_layers - 1
    assert not net.params[f"W{last}"][:, 2:].any()  # sigma = 1 at the start
    for value in net.params.values():  # a general point: l depends on s
        value += 0.3 * rng.standard_normal(value.shape)
    if log_std_bias is not None:
        net.params[f"b{last}"][2:] = log_std_bias
    return learner, rng


@given(seed=st.integers(0, 2**16), states=st.integers(1, 4), noise_samples=st.integers(1, 5))
def test_gaussian_policy_gradient_matches_finite_differences(seed, states, noise_samples):
    """Gradient (6) w.r.t. every PN parameter, mean and log-std heads alike."""
    learner, rng = gaussian_learner(seed)
    s = rng.standard_normal((states, 3))
    eps = rng.standard_normal((states * noise_samples, 2))
    actions, policy_cache = learner.policy.forward(s, eps)
    critic_cache = learner.critic.forward((np.repeat(s, noise_samples, axis=0), actions))[1]
    assume(away_from_kinks(policy_cache.net, critic_cache))

    # The action written out: a = mu(s) + exp(l(s)) eps, unbounded.
    out, _ = learner.policy.net.forward(s)
    mean, log_std = np.repeat(out[:, :2], noise_samples, 0), np.repeat(out[:, 2:], noise_samples, 0)
    # Inside the log-std bounds, away from the clip's kinks (checked separately below).
    assume(np.all(np.abs(log_std - ablations.LOG_STD_MAX) > 1e-2))
    np.testing.assert_allclose(actions, mean + np.exp(np.minimum(log_std, 2.0)) * eps, rtol=1e-12)

    def loss():
        return offpac_il.policy_loss_and_grads(learner, s, eps)[0]

    _, grads, _ = offpac_il.policy_loss_and_grads(learner, s, eps)
    assert set(grads) == set(learner.policy.net.params)
    for name, param in learner.policy.net.params.items():
        assert_gradient_close(
            grads[name],
            numerical_gradient(loss, param, OBJECTIVE_EPS),
            OBJECTIVE_TOL,
            f"gaussian gradient (6) d/d{name}",
            floor=OBJECTIVE_FLOOR,
        )


def test_gaussian_policy_check_catches_a_wrong_gradient():
    """da/dl = eps (sigma forgotten) instead of sigma eps is caught, on the log-std head."""
    learner, rng = gaussian_learner(9, log_std_bias=0.8)
    s, eps = rng.standard_normal((2, 3)), rng.standard_normal((6, 2))

    def loss():
        return offpac_il.policy_loss_and_grads(learner, s, eps)[0]

    last = f"W{learner.policy.net.n_layers - 1}"
    numeric = numerical_gradient(loss, learner.policy.net.params[last], OBJECTIVE_EPS)
    right = offpac_il.policy_loss_and_grads(learner, s, eps)[1][last]
    assert_gradient_close(right, numeric, OBJECTIVE_TOL, floor=OBJECTIVE_FLOOR)
    assert np.abs(right[:, 2:]).max() > 1e-3  # the log-std head is being checked

    actions, cache = learner.policy.forward(s, eps)
    _, critic_cache = learner.critic.forward((s, actions))
    (_, d_actions), _ = learner.critic.backward(
        -(1 - critic_cache.output) / len(eps), critic_cache, through_head=False
    )
    wrong_cache = dataclasses.replace(cache, std=np.ones_like(cache.std))
    wrong = learner.policy.backward(d_actions, wrong_cache)[last]
    with pytest.raises(AssertionError):
        assert_gradient_close(wrong, numeric, OBJECTIVE_TOL, floor=OBJECTIVE_FLOOR)


def test_gaussian_log_std_outside_its_bounds_gets_no_gradient():
    learner, rng = gaussian_learner(10, log_std_bias=ablations.LOG_STD_MAX + 5.0)
    s, eps = rng.standard_normal((2, 3)), rng.standard_normal((4, 2))
    actions = learner.policy.act(s, eps)
    mean = np.repeat(learner.policy.net.forward(s)[0][:, :2], 2, axis=0)
    np.testing.assert_allclose(actions, mean + np.exp(ablations.LOG_STD_MAX) * eps, rtol=1e-12)
    last = learner.policy.net.n_layers - 1
    grads = offpac_il.policy_loss_and_grads(learner, s, eps)[1]
    assert not grads[f"b{last}"][2:].any() and not grads[f"W{last}"][:, 2:].any()
    assert grads[f"b{last}"][:2].any()
    np.testing.assert_allclose(learner.policy.std(s), np.exp(ablations.LOG_STD_MAX))


def test_gaussian_actions_are_clipped_only_for_the_environment(hopper_demos):
    """The environment gets clip(a) (mapped to its bounds); the replay keeps a itself."""
    import expert

    env = expert.make_env("Hopper-v4")
    demos = expert.load_demos(hopper_demos, "Hopper-v4")
    config = AblationConfig(policy_type="gaussian", policy_hidden=(4, 4), critic_hidden=(4, 4))
    spaces = offpac_il.make_spaces(env, demos, config)
    rng = np.random.default_rng(0)
    policy = ablations.GaussianPolicy.create(11, 11, 3, config, rng)
    learner = offpac_il.Learner.create(policy, 11, 3, config, rng)
    learner.policy.net.params["b2"][3:] = 1.0  # sigma = e: most actions out of [-1, 1]
    executed = []
    step = env.step
    env.step = lambda a: executed.append(a) or step(a)
    replay = offpac_il.ReplayBuffer(2000, 11, 3)
    _, length = offpac_il.run_episode(env, learner, spaces, np.random.default_rng(1), 0, replay)
    stored = replay.data.actions[:length]
    assert np.abs(stored).max() > 1.5  # the critic sees the sampled, unbounded actions
    np.testing.assert_allclose(np.array(executed), spaces.to_env_action(np.clip(stored, -1, 1)))


# ---------------------------------------------------------------------------------------
# Ours+DP: tanh(PN([s, z_0])) with one fixed z_0.
# ---------------------------------------------------------------------------------------


def test_deterministic_policy_ignores_the_noise_it_is_given():
    learner, config, rng = ablation_learner(11, policy_type="deterministic")
    z0 = learner.policy.fixed_noise
    assert z0.shape == (3,) and np.abs(z0).max() > 0  # one draw of N(0, I), not zeros
    np.testing.assert_array_equal(learner.average_policy.fixed_noise, z0)
    s = rng.standard_normal((2, 3))
    a1 = learner.policy.act(s, rng.standard_normal((2, 3)))
    a2 = learner.policy.act(s, rng.standard_normal((2, 3)))
    np.testing.assert_array_equal(a1, a2)
    np.testing.assert_allclose(a1, learner.policy.net.forward((s, np.tile(z0, (2, 1))))[0])
    assert learner.policy.samples_per_state(128) == 1
    assert small_learner(0)[0].policy.samples_per_state(128) == 128
    # Its gradient (6) is Ours' with z = z_0, checked like Ours' on every parameter.
    z = np.tile(z0, (2, 1))
    actions, policy_cache = learner.policy.forward(s, z)
    assert away_from_kinks(policy_cache, learner.critic.forward((s, actions))[1])

    def loss():
        return offpac_il.policy_loss_and_grads(learner, s, z)[0]

    grads = offpac_il.policy_loss_and_grads(learner, s, z)[1]
    for name, param in learner.policy.net.params.items():
        assert_gradient_close(
            grads[name],
            numerical_gradient(loss, param, OBJECTIVE_EPS),
            OBJECTIVE_TOL,
            f"deterministic gradient (6) d/d{name}",
            floor=OBJECTIVE_FLOOR,
        )


def test_deterministic_policy_starts_from_ours_networks_and_checkpoints_z0():
    """At one seed Ours+DP's PN and QN are Ours' (z_0 is drawn after QN); z_0 is part of
    the policy's state and comes back with it."""
    ours, _, _ = small_learner(12)
    learner, _, _ = ablation_learner(12, policy_type="deterministic")
    for name, value in ours.policy.net.params.items():
        np.testing.assert_array_equal(learner.policy.net.params[name], value)
    for name, value in ours.critic.params.items():
        np.testing.assert_array_equal(learner.critic.params[name], value)
    state = learner.policy.state()
    other, _, _ = ablation_learner(13, policy_type="deterministic")
    other.policy.load_state(state)
    np.testing.assert_array_equal(other.policy.fixed_noise, learner.policy.fixed_noise)


def test_policy_noise_spread_of_the_deterministic_policy_is_zero():
    expert = random_triplets(np.random.default_rng(0), 5)
    learner = ablation_learner(3, policy_type="deterministic")[0]
    diagnostics = offpac_il.imitation_diagnostics(learner, expert, np.random.default_rng(1))
    assert diagnostics["policy_noise_spread"] == pytest.approx(0, abs=1e-12)


# ---------------------------------------------------------------------------------------
# The switches, and Ours+OnP.
# ---------------------------------------------------------------------------------------


def test_each_switch_replaces_one_field_of_the_variant():
    assert ablations.variant_of(AblationConfig()) == offpac_il.OURS
    gaussian = ablations.variant_of(AblationConfig(policy_type="gaussian"))
    assert gaussian.make_policy == ablations.GaussianPolicy.create
    assert gaussian.progress_fields == ("policy_std",)
    deterministic = ablations.variant_of(AblationConfig(policy_type="deterministic"))
    assert deterministic.make_policy == ablations.FixedNoisePolicy.create
    assert deterministic.make_extras is ablations.fix_noise
    irl = ablations.variant_of(AblationConfig(reward_learning="entropy", policy_type="gaussian"))
    assert irl.critic_step is ablations.irl_critic_step
    assert irl.progress_fields == ("reward_loss", "r_expert", "r_replay", "policy_std")
    assert ablations.variant_of(AblationConfig(on_policy=True)).after_updates is ablations.empty
    for config, flag in (
        (AblationConfig(reward_learning="gail"), "--reward-learning"),
        (AblationConfig(policy_type="beta"), "--policy-type"),
        (AblationConfig(reward_learning="entropy", policy_type="deterministic"), "not combined"),
    ):
        with pytest.raises(harness.UserError, match=flag):
            ablations.variant_of(config)


def test_empty_leaves_a_replay_buffer_with_nothing_in_it():
    replay = offpac_il.ReplayBuffer(5, 1, 1)
    for i in range(3):
        replay.add([i], [0.0], [i], False)
    ablations.empty(replay)
    assert (replay.size, replay.next_index) == (0, 0)
    replay.add([7.0], [0.0], [7.0], False)
    assert replay.sample(np.random.default_rng(0), 4).states[:, 0].tolist() == [7.0] * 4


@pytest.mark.parametrize("on_policy", [False, True])
def test_on_policy_updates_see_only_the_latest_episode(
    tmp_path, hopper_demos, monkeypatch, on_policy
):
    lengths, seen = [], []
    run_episode, update = offpac_il.run_episode, offpac_il.update

    def recording_episode(*args, **kwargs):
        result = run_episode(*args, **kwargs)
        if len(args) >= 6:  # a training episode (it fills the replay)
            lengths.append(result[1])
        return result

    def recording_update(learner, expert_buffer, replay, *args):
        seen.append((len(lengths), replay.size))
        return update(learner, expert_buffer, replay, *args)

    monkeypatch.setattr(offpac_il, "run_episode", recording_episode)
    monkeypatch.setattr(offpac_il, "update", recording_update)
    extra = ["--on-policy"] if on_policy else []
    config = tiny_config(tmp_path / "run", hopper_demos, extra=extra, config_class=AblationConfig)
    offpac_il.train(config, variant=ablations.variant_of(config))
    assert len(lengths) >= 3
    for episode, size in seen:
        latest = lengths[episode - 1]
        assert size == (latest if on_policy else min(sum(lengths[:episode]), 15_000))


# ---------------------------------------------------------------------------------------
# The command line: python -m lab.ablations, from the repository root.
# ---------------------------------------------------------------------------------------


def read_progress(run_dir):
    return read_rows(run_dir / "progress.csv")


def test_with_every_switch_off_it_is_ours_draw_for_draw(tmp_path, hopper_demos):
    run_module("lab.ablations", *TINY_RUN, "--demos", hopper_demos, "--run-dir", tmp_path / "a")
    run_script("offpac_il.py", *TINY_RUN, "--demos", hopper_demos, "--run-dir", tmp_path / "o")
    assert read_progress(tmp_path / "a") == read_progress(tmp_path / "o")


@pytest.mark.parametrize("method", ABLATIONS)
def test_each_ablation_runs_from_the_command_line_and_resumes(
    method, tmp_path, hopper_demos, monkeypatch
):
    """Each ablation's switch on the command line: a few hundred interactions on
    Hopper-v4, its progress and checkpoint; then the same run killed halfway and resumed
    from its checkpoint with `python -m lab.ablations --resume` gives the same progress."""
    selector = ABLATIONS[method]
    whole = tmp_path / "whole"
    run_module("lab.ablations", *TINY_RUN, *selector, "--demos", hopper_demos, "--run-dir", whole)
    saved = harness.read_config(whole)
    config = harness.saved_config(AblationConfig, saved, offpac_il.PAPER_SETTINGS)
    switches = ("on_policy", "reward_learning", "policy_type")
    default = AblationConfig()
    assert [getattr(config, k) != getattr(default, k) for k in switches].count(True) == 1
    rows = read_progress(whole)
    interactions = [int(r["interactions"]) for r in rows]
    assert interactions[0] == 0 and interactions[-1] >= 300
    assert all(n >= 100 * i for i, n in enumerate(interactions))  # one row per 100 or more
    variant = ablations.variant_of(config)
    fields = (*offpac_il.PROGRESS_FIELDS, *variant.progress_fields, *offpac_il.AVERAGE_FIELDS)
    fields += offpac_il.HANDOVER_FIELDS
    assert list(rows[0]) == [f for f in fields if f != "wall_seconds"]
    for row in rows[1:]:  # every column filled and finite after the first updates
        assert row["updates"] == row["interactions"]
        assert row["handover"] == "policy_average.npz"
        assert all(math.isfinite(float(v)) for k, v in row.items() if k != "handover"), row
    last = rows[-1]
    checkpoint = harness.load_arrays(whole / "checkpoint.npz")
    policy = harness.load_arrays(whole / "policy_final.npz")
    if config.on_policy:
        assert checkpoint["replay/size_next"].tolist() == [0, 0]  # emptied after updates
    if config.reward_learning != "none":
        assert {f"reward/W{i}" for i in range(3)} <= set(checkpoint)
        assert {f"reward_rmsprop/W{i}" for i in range(3)} <= set(checkpoint)
        assert float(last["r_expert"]) > float(last["r_replay"])
    if config.policy_type == "gaussian":
        assert policy["policy/W2"].shape == (8, 6)  # [s] -> 8 -> 8 -> mu, log sigma
        assert float(last["policy_std"]) > 0
    if config.policy_type == "deterministic":
        assert policy["policy/fixed_noise"].shape == (11,)
        np.testing.assert_array_equal(
            policy["policy/fixed_noise"], checkpoint["policy/fixed_noise"]
        )

    interrupted = tmp_path / "interrupted"
    config = tiny_config(interrupted, hopper_demos, extra=selector, config_class=AblationConfig)
    with threadpool_limits(limits=1, user_api="blas"):  # as the command line runs
        with monkeypatch.context() as patch:
            episodes = int(last["episodes"]) // 2  # killed halfway
            patch.setattr(offpac_il, "run_episode", interrupted_after(episodes))
            with pytest.raises(KeyboardInterrupt):
                offpac_il.train(config, variant=ablations.variant_of(config))
    release(interrupted)
    counters = harness.load_arrays(interrupted / "checkpoint.npz")["counters"]
    saved = json.loads(str(counters))
    assert saved["episodes"] == episodes and 0 < saved["interactions"] < interactions[-1]
    run_module("lab.ablations", "--resume", interrupted)
    assert read_progress(interrupted) == rows


@pytest.mark.parametrize(
    "args, message",
    [
        (["--reward-learning", "gail"], "--reward-learning"),
        (["--policy-type", "beta"], "--policy-type"),
        (["--reward-learning", "entropy", "--policy-type", "deterministic"], "not combined"),
        (["--on-policy", "--tau", "0"], "--tau"),
    ],
)
def test_bad_ablation_flags_are_one_line_and_exit_2(tmp_path, args, message):
    result = run_module("lab.ablations", *args, "--run-dir", tmp_path / "r", check=False)
    assert_one_line_error(result, message)
    assert not (tmp_path / "r").exists()


def test_a_resumed_ablation_keeps_its_switch(tmp_path, hopper_demos):
    """--resume reads the switches from config.json; giving another one is refused."""
    run_dir = tmp_path / "run"
    flags = [*TINY_RUN, "--total-steps", "100", "--policy-type", "gaussian"]
    run_module("lab.ablations", *flags, "--demos", hopper_demos, "--run-dir", run_dir)
    refused = run_module(
        "lab.ablations", "--resume", run_dir, "--policy-type", "deterministic", check=False
    )
    assert_one_line_error(refused, "--policy-type")
    run_module("lab.ablations", "--resume", run_dir, "--total-steps", "200")
    rows = read_progress(run_dir)
    assert int(rows[-1]["interactions"]) >= 200 and float(rows[-1]["policy_std"]) > 0


def test_gradient_noise_of_the_deterministic_policy_is_zero(tmp_path, hopper_demos):
    """lab/experiments.py's gradient_noise restores an ablation run with its variant: with
    z fixed at z_0, no part of gradient (6) varies with the noise."""
    from lab import experiments

    run = tmp_path / "deterministic"
    extra = ["--policy-type", "deterministic"]
    config = tiny_config(run, hopper_demos, extra=extra, config_class=AblationConfig)
    offpac_il.train(config, variant=ablations.variant_of(config))
    (row,) = experiments.gradient_noise(run, samples=(8,), draws=5)
    assert row["noise_variance"] == 0 and row["total_variance"] > 0
