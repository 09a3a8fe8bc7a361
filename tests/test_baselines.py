"""The baselines (BC, GAIL, BC+GAIL): finite-difference checks of every hand-written
gradient, each with a wrong gradient that the check must reject; GAE against its
definition; the command line end to end on Hopper-v4 with tiny networks; resume."""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import numpy as np
import pytest
from gradcheck import assert_gradient_close, numerical_gradient
from helpers import assert_one_line_error, interrupted_after, read_rows, run_module
from hypothesis import assume, given
from hypothesis import strategies as st

# The finite-difference settings are the other tests', with their measured rationale:
# the MLP losses' step and tolerance and the ReLU-kink guard (test_offpac_il), and the
# noise floor below which a gradient element is compared absolutely (test_nets: a
# gradient element can be far smaller than the loss's rounding noise / eps).
from test_nets import FD_FLOOR
from test_offpac_il import OBJECTIVE_EPS, OBJECTIVE_TOL, away_from_kinks

import harness
import nets
import offpac_il
from lab import baselines

ROOT = Path(__file__).resolve().parent.parent
STATE_DIM, ACTION_DIM = 3, 2


def small_policy(rng, log_std_scale=0.5) -> baselines.GaussianPolicy:
    """A float64 Gaussian policy with small networks and log sigma away from 0, so that
    sigma^2 != 1 and a gradient that drops 1/sigma^2 is wrong."""
    policy = baselines.GaussianPolicy.create(STATE_DIM, ACTION_DIM, (6, 5), 0.0, rng, np.float64)
    policy.log_std[...] = rng.uniform(-log_std_scale, log_std_scale, ACTION_DIM) - 0.3
    return policy


def check_every_param(loss, grads, params, name, eps=OBJECTIVE_EPS, tol=OBJECTIVE_TOL):
    assert set(grads) == set(params)
    for key, param in params.items():
        numeric = numerical_gradient(loss, param, eps)
        assert_gradient_close(grads[key], numeric, tol, f"{name} d/d{key}", floor=FD_FLOOR)


# ---------------------------------------------------------------------------------------
# Gaussian log-likelihood: w.r.t. mu and log sigma, then through the policy MLP (BC loss).
# ---------------------------------------------------------------------------------------


@given(seed=st.integers(0, 2**16), n=st.integers(1, 6), dim=st.integers(1, 4))
def test_gaussian_log_likelihood_gradient(seed, n, dim):
    rng = np.random.default_rng(seed)
    actions, mean = rng.uniform(-1, 1, (n, dim)), rng.uniform(-1, 1, (n, dim))
    log_std = rng.uniform(-1.5, 0.5, dim)
    weights = rng.standard_normal(n)  # any linear use of the per-row log-likelihoods

    log_prob, d_mean, d_log_std = baselines.gaussian_log_prob(actions, mean, log_std)
    # The value against the product of the normal densities, written out.
    std = np.exp(log_std)
    density = np.exp(-((actions - mean) ** 2) / (2 * std**2)) / (np.sqrt(2 * np.pi) * std)
    np.testing.assert_allclose(log_prob, np.log(density.prod(axis=1)), rtol=1e-12)

    def loss():
        return weights @ baselines.gaussian_log_prob(actions, mean, log_std)[0]

    # log N is quadratic in mu, so a centered difference is exact but for rounding: a
    # large step keeps the rounding noise (~1e-16 |f| / eps) far below tiny elements.
    assert_gradient_close(
        weights[:, None] * d_mean,
        numerical_gradient(loss, mean, 1e-3),
        name="log N d/d mu",
        floor=FD_FLOOR,
    )
    assert_gradient_close(
        (weights[:, None] * d_log_std).sum(axis=0),
        numerical_gradient(loss, log_std),
        name="log N d/d log sigma",
        floor=FD_FLOOR,
    )


def test_gaussian_log_likelihood_check_catches_a_wrong_gradient():
    """d log N / d log sigma without its -1 (the normaliser's share) is rejected."""
    rng = np.random.default_rng(0)
    actions, mean, log_std = rng.uniform(-1, 1, (4, 2)), rng.uniform(-1, 1, (4, 2)), np.zeros(2)
    _, _, d_log_std = baselines.gaussian_log_prob(actions, mean, log_std)

    def loss():
        return baselines.gaussian_log_prob(actions, mean, log_std)[0].sum()

    numeric = numerical_gradient(loss, log_std)
    assert_gradient_close(d_log_std.sum(axis=0), numeric, floor=FD_FLOOR)
    with pytest.raises(AssertionError):
        assert_gradient_close((d_log_std + 1.0).sum(axis=0), numeric, floor=FD_FLOOR)


@given(seed=st.integers(0, 2**16), n=st.integers(1, 8))
def test_bc_loss_gradient_through_the_policy(seed, n):
    rng = np.random.default_rng(seed)
    policy = small_policy(rng)
    states, actions = rng.standard_normal((n, STATE_DIM)), rng.uniform(-1, 1, (n, ACTION_DIM))
    assume(away_from_kinks(policy.mean_net.forward(states)[1]))

    def loss():
        return baselines.bc_loss_and_grads(policy, states, actions)[0]

    value, grads = baselines.bc_loss_and_grads(policy, states, actions)
    # The loss is the mean negative log-likelihood of N(mu(s), sigma^2).
    log_prob, _, _ = baselines.gaussian_log_prob(
        actions, policy.mean_net.forward(states)[0], policy.log_std
    )
    np.testing.assert_allclose(value, -log_prob.mean(), rtol=1e-12)
    check_every_param(loss, grads, policy.params, "BC negative log-likelihood")


def test_bc_gradient_check_catches_a_wrong_gradient():
    """A mean-network gradient that drops 1/sigma^2 (the squared-error gradient) is rejected."""
    rng = np.random.default_rng(3)
    policy = small_policy(rng)
    states, actions = rng.standard_normal((5, STATE_DIM)), rng.uniform(-1, 1, (5, ACTION_DIM))
    mean, cache = policy.mean_net.forward(states)
    _, wrong = policy.mean_net.backward(-(actions - mean) / 5, cache)

    def loss():
        return baselines.bc_loss_and_grads(policy, states, actions)[0]

    numeric = numerical_gradient(loss, policy.mean_net.params["W0"], OBJECTIVE_EPS)
    right = baselines.bc_loss_and_grads(policy, states, actions)[1]["W0"]
    assert_gradient_close(right, numeric, OBJECTIVE_TOL, floor=FD_FLOOR)
    with pytest.raises(AssertionError):
        assert_gradient_close(wrong["W0"], numeric, OBJECTIVE_TOL, floor=FD_FLOOR)


# ---------------------------------------------------------------------------------------
# PPO's clipped surrogate: away from the clip boundary, and zero in the clipped region.
# ---------------------------------------------------------------------------------------


def ppo_case(seed, n, spread=0.5):
    rng = np.random.default_rng(seed)
    policy = small_policy(rng)
    states = rng.standard_normal((n, STATE_DIM))
    actions = policy.act(states, rng.standard_normal((n, ACTION_DIM)))
    log_prob, _ = policy.log_prob(states, actions)
    old_log_prob = log_prob + rng.uniform(-spread, spread, n)  # ratios in [0.6, 1.65]
    return rng, policy, states, actions, old_log_prob, rng.standard_normal(n)


@given(
    seed=st.integers(0, 2**16),
    n=st.integers(1, 8),
    clip_range=st.sampled_from([0.1, 0.2, 0.3]),
    entropy_coef=st.sampled_from([0.0, 0.01]),
)
def test_ppo_surrogate_gradient(seed, n, clip_range, entropy_coef):
    _, policy, states, actions, old_log_prob, advantages = ppo_case(seed, n)
    ratio = np.exp(policy.log_prob(states, actions)[0] - old_log_prob)
    # Finite-difference steps must not carry a ratio across 1 +/- eps (the kink of min).
    assume(np.abs(np.abs(ratio - 1.0) - clip_range).min() > 1e-2)
    assume(away_from_kinks(policy.mean_net.forward(states)[1]))

    def loss():
        return baselines.ppo_policy_loss_and_grads(
            policy, states, actions, old_log_prob, advantages, clip_range, entropy_coef
        )[0]

    value, grads, _ = baselines.ppo_policy_loss_and_grads(
        policy, states, actions, old_log_prob, advantages, clip_range, entropy_coef
    )
    expected = -np.minimum(
        ratio * advantages, np.clip(ratio, 1 - clip_range, 1 + clip_range) * advantages
    ).mean() - entropy_coef * (policy.log_std.sum() + ACTION_DIM * 0.5 * (1 + np.log(2 * np.pi)))
    np.testing.assert_allclose(value, expected, rtol=1e-12)
    check_every_param(loss, grads, policy.params, "PPO clipped surrogate")


def test_ppo_clipped_region_has_zero_gradient():
    """Rows whose clipped term is the minimum (A > 0 with rho > 1 + eps, A < 0 with
    rho < 1 - eps) give exactly zero gradient, and finite differences agree."""
    _, policy, states, actions, _, _ = ppo_case(5, 6)
    log_prob, _ = policy.log_prob(states, actions)
    advantages = np.array([1.0, 2.0, 0.5, -1.0, -0.3, -2.0])
    old_log_prob = log_prob - np.where(advantages > 0, 0.5, -0.5)  # rho = e^0.5 or e^-0.5
    _, grads, stats = baselines.ppo_policy_loss_and_grads(
        policy, states, actions, old_log_prob, advantages, 0.2
    )
    assert stats["clip_fraction"] == 1.0
    for key, grad in grads.items():
        assert np.all(grad == 0.0), key

    def loss():
        return baselines.ppo_policy_loss_and_grads(
            policy, states, actions, old_log_prob, advantages, 0.2
        )[0]

    for key, param in policy.params.items():
        assert np.abs(numerical_gradient(loss, param, OBJECTIVE_EPS)).max() < 1e-10, key


def test_ppo_gradient_check_catches_a_wrong_gradient():
    """The unclipped policy gradient -mean rho A grad log pi, ignoring the clip, is rejected."""
    _, policy, states, actions, old_log_prob, advantages = ppo_case(7, 8, spread=1.0)
    ratio = np.exp(policy.log_prob(states, actions)[0] - old_log_prob)
    _, cache = policy.log_prob(states, actions)
    wrong = policy.backward(-ratio * advantages / len(states), cache)

    def loss():
        return baselines.ppo_policy_loss_and_grads(
            policy, states, actions, old_log_prob, advantages, 0.2
        )[0]

    _, right, stats = baselines.ppo_policy_loss_and_grads(
        policy, states, actions, old_log_prob, advantages, 0.2
    )
    assert 0 < stats["clip_fraction"] < 1
    numeric = numerical_gradient(loss, policy.log_std, OBJECTIVE_EPS)
    assert_gradient_close(right["log_std"], numeric, OBJECTIVE_TOL, floor=FD_FLOOR)
    with pytest.raises(AssertionError):
        assert_gradient_close(wrong["log_std"], numeric, OBJECTIVE_TOL, floor=FD_FLOOR)


# ---------------------------------------------------------------------------------------
# Value loss and the discriminator's logistic loss.
# ---------------------------------------------------------------------------------------


def small_value(rng):
    return nets.MLP.create([STATE_DIM, 6, 5, 1], "identity", rng, np.float64)


@given(seed=st.integers(0, 2**16), n=st.integers(1, 8))
def test_value_loss_gradient(seed, n):
    rng = np.random.default_rng(seed)
    value_net = small_value(rng)
    states, returns = rng.standard_normal((n, STATE_DIM)), rng.standard_normal(n)
    assume(away_from_kinks(value_net.forward(states)[1]))

    def loss():
        return baselines.value_loss_and_grads(value_net, states, returns)[0]

    value, grads = baselines.value_loss_and_grads(value_net, states, returns)
    values = value_net.forward(states)[0][:, 0]
    np.testing.assert_allclose(value, 0.5 * ((values - returns) ** 2).mean(), rtol=1e-12)
    check_every_param(loss, grads, value_net.params, "value loss")


def test_value_loss_check_catches_a_wrong_gradient():
    """The gradient of mean (V - R)^2 instead of its half is rejected."""
    rng = np.random.default_rng(4)
    value_net = small_value(rng)
    states, returns = rng.standard_normal((5, STATE_DIM)), rng.standard_normal(5)
    _, grads = baselines.value_loss_and_grads(value_net, states, returns)

    def loss():
        return baselines.value_loss_and_grads(value_net, states, returns)[0]

    numeric = numerical_gradient(loss, value_net.params["W2"], OBJECTIVE_EPS)
    assert_gradient_close(grads["W2"], numeric, OBJECTIVE_TOL, floor=FD_FLOOR)
    with pytest.raises(AssertionError):
        assert_gradient_close(2.0 * grads["W2"], numeric, OBJECTIVE_TOL, floor=FD_FLOOR)


def small_discriminator(rng):
    return nets.MLP.create([STATE_DIM + ACTION_DIM, 6, 5, 1], "sigmoid", rng, np.float64)


def discriminator_case(seed, n_expert, n_policy):
    rng = np.random.default_rng(seed)
    discriminator = small_discriminator(rng)
    pairs = [
        (rng.standard_normal((n, STATE_DIM)), rng.uniform(-1, 1, (n, ACTION_DIM)))
        for n in (n_expert, n_policy)
    ]
    return discriminator, pairs[0], pairs[1]


@given(seed=st.integers(0, 2**16), n_expert=st.integers(1, 5), n_policy=st.integers(1, 5))
def test_discriminator_logistic_loss_gradient(seed, n_expert, n_policy):
    discriminator, (s_e, a_e), (s_p, a_p) = discriminator_case(seed, n_expert, n_policy)
    caches = [discriminator.forward((s, a))[1] for s, a in ((s_e, a_e), (s_p, a_p))]
    assume(away_from_kinks(*caches))

    def loss():
        return baselines.discriminator_loss_and_grads(discriminator, s_e, a_e, s_p, a_p)[0]

    value, grads, stats = baselines.discriminator_loss_and_grads(discriminator, s_e, a_e, s_p, a_p)
    d_expert, d_policy = caches[0].output[:, 0], caches[1].output[:, 0]
    expected = -np.log(d_expert).mean() - np.log(1 - d_policy).mean()
    np.testing.assert_allclose(value, expected, rtol=1e-10)
    np.testing.assert_allclose(stats["d_expert"], d_expert.mean(), rtol=1e-12)
    check_every_param(loss, grads, discriminator.params, "discriminator logistic loss")


def test_discriminator_check_catches_a_wrong_gradient():
    """Expert rows given the policy rows' derivative sigmoid(x) (labels mixed up) are rejected."""
    discriminator, (s_e, a_e), (s_p, a_p) = discriminator_case(6, 3, 4)
    states, actions = np.concatenate([s_e, s_p]), np.concatenate([a_e, a_p])
    _, cache = discriminator.forward((states, actions))
    n = np.array([3] * 3 + [4] * 4)[:, None]
    _, wrong = discriminator.backward(
        nets.sigmoid(cache.logits) / n, cache, through_head=False, input_grads=False
    )

    def loss():
        return baselines.discriminator_loss_and_grads(discriminator, s_e, a_e, s_p, a_p)[0]

    numeric = numerical_gradient(loss, discriminator.params["b2"], OBJECTIVE_EPS)
    right = baselines.discriminator_loss_and_grads(discriminator, s_e, a_e, s_p, a_p)[1]
    assert_gradient_close(right["b2"], numeric, OBJECTIVE_TOL, floor=FD_FLOOR)
    with pytest.raises(AssertionError):
        assert_gradient_close(wrong["b2"], numeric, OBJECTIVE_TOL, floor=FD_FLOOR)


def test_gail_reward_is_minus_log_one_minus_d():
    rng = np.random.default_rng(8)
    discriminator = small_discriminator(rng)
    states, actions = rng.standard_normal((5, STATE_DIM)), rng.uniform(-1, 1, (5, ACTION_DIM))
    d = discriminator.forward((states, actions))[0][:, 0]
    reward = baselines.gail_reward(discriminator, states, actions)
    np.testing.assert_allclose(reward, -np.log(1 - d), rtol=1e-12)
    assert np.all(reward > 0)


# ---------------------------------------------------------------------------------------
# GAE against its definition, written as a direct sum.
# ---------------------------------------------------------------------------------------


def gae_by_definition(rewards, values, next_values, terminal, episode_end, gamma, lam):
    """A_t = sum_{l >= 0} (gamma lam)^l delta_{t+l}, up to the end of t's episode."""
    deltas = rewards + gamma * (1.0 - terminal) * next_values - values
    advantages = np.zeros(len(rewards))
    for t in range(len(rewards)):
        for step in range(t, len(rewards)):
            advantages[t] += (gamma * lam) ** (step - t) * deltas[step]
            if episode_end[step]:
                break
    return advantages


@st.composite
def rollouts(draw):
    """Whole episodes, each ending by a fall (terminal) or by the time limit."""
    lengths = draw(st.lists(st.integers(1, 6), min_size=1, max_size=4))
    falls = draw(st.lists(st.booleans(), min_size=len(lengths), max_size=len(lengths)))
    terminal, episode_end = [], []
    for length, fell in zip(lengths, falls, strict=True):
        terminal += [0.0] * (length - 1) + [float(fell)]
        episode_end += [0.0] * (length - 1) + [1.0]
    seed = draw(st.integers(0, 2**16))
    return np.array(terminal), np.array(episode_end), np.random.default_rng(seed)


@given(
    rollout=rollouts(),
    gamma=st.sampled_from([0.0, 0.9, 0.99]),
    lam=st.sampled_from([0.0, 0.95, 1.0]),
)
def test_gae_matches_its_definition(rollout, gamma, lam):
    terminal, episode_end, rng = rollout
    n = len(terminal)
    rewards, values, next_values = (rng.standard_normal(n) for _ in range(3))
    args = (rewards, values, next_values, terminal, episode_end, gamma, lam)
    np.testing.assert_allclose(
        baselines.gae(*args), gae_by_definition(*args), rtol=1e-12, atol=1e-12
    )


def test_gae_check_catches_a_wrong_estimate():
    """Bootstrapping through a fall (terminal ignored) does not pass for GAE."""
    terminal, episode_end = np.array([0.0, 1.0, 0.0, 0.0]), np.array([0.0, 1.0, 0.0, 1.0])
    rng = np.random.default_rng(0)
    rewards, values, next_values = (rng.standard_normal(4) for _ in range(3))
    right = gae_by_definition(rewards, values, next_values, terminal, episode_end, 0.99, 0.95)
    wrong = baselines.gae(rewards, values, next_values, 0 * terminal, episode_end, 0.99, 0.95)
    with pytest.raises(AssertionError):
        np.testing.assert_allclose(wrong, right, rtol=1e-12, atol=1e-12)


# ---------------------------------------------------------------------------------------
# The command line, end to end on Hopper-v4 with tiny networks and budgets.
# ---------------------------------------------------------------------------------------

TINY = ["--env", "Hopper-v4", "--eval-episodes", "1", "--policy-hidden", "8", "8"]
TINY_BC = ["bc", *TINY, "--total-steps", "60", "--eval-every", "20", "--batch-size", "16"]
TINY_GAIL_FLAGS = [
    *TINY,
    "--total-steps",
    "300",
    "--eval-every",
    "100",
    "--value-hidden",
    "8",
    "8",
    "--discriminator-hidden",
    "8",
    "8",
    "--rollout-steps",
    "50",
    "--ppo-epochs",
    "2",
    "--minibatch-size",
    "16",
    "--discriminator-steps",
    "2",
    "--discriminator-batch",
    "16",
    "--checkpoint-every",
    "0",
    "--log-every",
    "0",
]
TINY_GAIL_CONFIG = {"env": "Hopper-v4", "policy_hidden": (8, 8)}
RUN_FILES = ("config.json", "progress.csv", "diagnostics.csv", "checkpoint.npz")
POLICIES = ("policy_best.npz", "policy_final.npz")


def run_cli(*args, check=True):
    return run_module("lab.baselines", *args, check=check)


read_csv = read_rows


@pytest.fixture(scope="module")
def bc_run(tmp_path_factory, hopper_demos) -> Path:
    run_dir = tmp_path_factory.mktemp("bc") / "run"
    run_cli(*TINY_BC, "--demos", hopper_demos, "--run-dir", run_dir)
    return run_dir


def test_bc_command_line_writes_its_files(bc_run):
    for name in RUN_FILES + POLICIES:
        assert (bc_run / name).is_file(), name
    assert json.loads((bc_run / "config.json").read_text())["method"] == "bc"
    rows = read_csv(bc_run / "progress.csv")
    assert [int(r["updates"]) for r in rows] == [0, 20, 40, 60]
    assert all(r["interactions"] == "0" for r in rows)  # BC never interacts
    assert all(np.isfinite(float(r["normalized_score"])) for r in rows)
    diagnostics = read_csv(bc_run / "diagnostics.csv")
    nll = [float(r["validation_nll"]) for r in diagnostics]
    assert nll[-1] < nll[0]  # 60 steps of maximum likelihood do improve it
    # policy_final.npz holds the parameters with the best held-out likelihood.
    best = int(diagnostics[int(np.argmin(nll))]["updates"])
    assert diagnostics[-1]["best_update"] == str(best)
    final = harness.load_arrays(bc_run / "policy_final.npz")
    assert set(final) == {"policy/W0", "policy/b0", "policy/W1", "policy/b1"} | {
        "policy/W2",
        "policy/b2",
        "policy/log_std",
    }
    assert not list(bc_run.glob(".*.tmp"))


def test_gail_and_bc_gail_command_lines_write_their_files(tmp_path, hopper_demos, bc_run):
    for method, extra in (("gail", []), ("bc-gail", ["--bc-init", bc_run])):
        run_dir = tmp_path / method
        result = run_cli(
            method, *TINY_GAIL_FLAGS, *extra, "--demos", hopper_demos, "--run-dir", run_dir
        )
        for name in RUN_FILES + POLICIES:
            assert (run_dir / name).is_file(), (method, name)
        assert json.loads((run_dir / "config.json").read_text())["method"] == method
        rows = read_csv(run_dir / "progress.csv")
        assert int(rows[-1]["interactions"]) >= 300 and "eval" in result.stdout
        assert all(np.isfinite(float(r["normalized_score"])) for r in rows)
        assert rows[-1]["policy_grad_norm"] != "" and rows[-1]["q_expert"] == ""
    # BC+GAIL's policy starts as the BC run's final policy, log sigma included; with
    # bc_reset_log_std, with the BC run's mean network and log sigma at log_std_init.
    bc_final = harness.load_arrays(bc_run / "policy_final.npz")
    assert np.all(bc_final["policy/log_std"] != -0.5)
    for reset in (False, True):
        config = baselines.GAILConfig(
            **{**TINY_GAIL_CONFIG, "demos": str(hopper_demos), "bc_init": str(bc_run)},
            log_std_init=-0.5,
            bc_reset_log_std=reset,
        )
        policy = baselines.GaussianPolicy.create(11, 3, (8, 8), 0.0, np.random.default_rng(0))
        baselines.load_bc_init(config, policy)
        for key, value in policy.state("policy").items():
            expected = np.full(3, -0.5) if key == "policy/log_std" and reset else bc_final[key]
            np.testing.assert_array_equal(value, expected, err_msg=f"{key}, reset={reset}")


def tiny_gail_config(run_dir: Path, demos: Path, seed=0) -> baselines.GAILConfig:
    args = baselines.build_parser().parse_args(
        ["gail", *TINY_GAIL_FLAGS, "--demos", str(demos), "--seed", str(seed)]
        + ["--run-dir", str(run_dir)]
    )
    return baselines.config_from(args)


def test_gail_resume_reproduces_an_uninterrupted_run(tmp_path, hopper_demos, monkeypatch):
    baselines.train_gail(tiny_gail_config(tmp_path / "whole", hopper_demos))
    other_seed = tmp_path / "other"
    baselines.train_gail(tiny_gail_config(other_seed, hopper_demos, seed=1))

    interrupted = tmp_path / "interrupted"
    with monkeypatch.context() as patch:
        patch.setattr(offpac_il, "run_episode", interrupted_after(12))
        with pytest.raises(KeyboardInterrupt):
            baselines.train_gail(tiny_gail_config(interrupted, hopper_demos))
    partial = read_csv(interrupted / "progress.csv")
    assert 0 < int(partial[-1]["interactions"]) < 300
    baselines.train_gail(tiny_gail_config(interrupted, hopper_demos), resume=True)

    whole = read_csv(tmp_path / "whole" / "progress.csv")
    assert read_csv(interrupted / "progress.csv") == whole
    assert read_csv(other_seed / "progress.csv") != whole
    assert read_csv(interrupted / "diagnostics.csv") == read_csv(
        tmp_path / "whole" / "diagnostics.csv"
    )
    # Resuming a finished run changes nothing.
    baselines.train_gail(tiny_gail_config(interrupted, hopper_demos), resume=True)
    assert read_csv(interrupted / "progress.csv") == whole


def test_ppo_epochs_stop_once_the_policy_moved_past_target_kl(tmp_path, hopper_demos, monkeypatch):
    """target_kl 0 runs every epoch; a tiny one stops each iteration after its first
    step (the policy then differs from pi_old); resuming a run whose config.json predates
    target_kl keeps running without it."""
    original, updates = baselines.gail_iteration, {}
    for target_kl in (0.0, 1e-12):
        counts = updates[target_kl] = []

        def counting(*args, counts=counts, **kwargs):
            stats = original(*args, **kwargs)
            counts.append(stats["ppo_updates"])
            return stats

        monkeypatch.setattr(baselines, "gail_iteration", counting)
        config = tiny_gail_config(tmp_path / str(target_kl), hopper_demos)
        baselines.train_gail(dataclasses.replace(config, target_kl=target_kl))
    assert min(updates[0.0]) >= 2 * 4  # 2 epochs of >= 50 steps in minibatches of 16
    assert set(updates[1e-12]) == {1}

    old_run = tmp_path / "0.0"
    saved = json.loads((old_run / "config.json").read_text())
    del saved["target_kl"]
    (old_run / "config.json").write_text(json.dumps(saved))
    args = baselines.build_parser().parse_args(["gail", "--resume", str(old_run)])
    assert baselines.config_from(args).target_kl == 0.0


@pytest.mark.parametrize(
    "args, message",
    [
        (["bc", "--env", "CartPole-v1"], "action space"),
        (["gail", "--env", "NoSuchEnv-v0"], "NoSuchEnv-v0"),
        (["bc", "--sampling", "some"], "--sampling"),
        (["bc", "--validation-fraction", "1.5"], "--validation-fraction"),
        (["gail", "--gae-lambda", "2"], "--gae-lambda"),
        (["gail", "--resume", "/nonexistent/run"], "/nonexistent/run"),
        (["bc-gail"], "--bc-init"),
        (["bc-gail", "--bc-init", "/nonexistent/bc"], "/nonexistent/bc"),
    ],
)
def test_bad_input_is_one_line_and_exit_2(tmp_path, args, message):
    result = run_cli(*args, "--run-dir", tmp_path / "r", check=False)
    assert result.returncode == 2
    lines = result.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("error:") and message in lines[0]
    assert not (tmp_path / "r").exists()


def test_bc_run_dir_that_is_a_file_is_refused(tmp_path, hopper_demos):
    taken = tmp_path / "taken"
    taken.write_text("someone's file")
    result = run_cli(*TINY_BC, "--demos", hopper_demos, "--run-dir", taken, check=False)
    assert_one_line_error(result, f"--run-dir {taken} is a file")
    assert taken.read_text() == "someone's file"


def test_bc_on_plain_triplets_says_every_s_prime_is_taken_as_non_terminal(tmp_path, hopper_demos):
    with np.load(hopper_demos) as file:
        triplets = {k: file[k] for k in ("observations", "actions", "next_observations")}
    np.savez(tmp_path / "triplets.npz", **triplets)
    args = (*TINY_BC, "--total-steps", "20", "--demos", tmp_path / "triplets.npz")
    result = run_cli(*args, "--run-dir", tmp_path / "run")
    first = result.stdout.splitlines()[:3]
    assert any("100 triplets" in line and "non-terminal" in line for line in first), first


def test_resuming_with_the_wrong_method_is_refused(bc_run):
    result = run_cli("gail", "--resume", bc_run, check=False)
    assert result.returncode == 2
    assert len(result.stderr.strip().splitlines()) == 1 and "bc --resume" in result.stderr
