"""The learner: finite-difference checks of objective (18) and gradient (6) as the
learner computes them, the targets, and the command line end to end."""

from __future__ import annotations

import dataclasses
import json
import math
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from gradcheck import assert_gradient_close, numerical_gradient
from helpers import interrupted_after, read_rows, run_script
from hypothesis import assume, given
from hypothesis import strategies as st
from threadpoolctl import threadpool_limits

import experiments
import nets
import offpac_il

ROOT = Path(__file__).resolve().parent.parent
# The losses are O(0.1-1) while units on the leaky side of their ReLU give parameter
# gradients of O(1e-7), where a centered difference's rounding error (~1e-16 |f| / eps)
# dominates. Measured worst relative error over 40 seeds of the critic objective:
# eps 1e-6: 9e-4, 1e-5: 1e-4, 1e-4: 9e-6, 1e-3: 0.2 (steps cross ReLU kinks). Hence
# eps = 1e-4 and a tolerance of 5e-5; a wrong gradient is off by O(1) (see the tests
# that check the check).
OBJECTIVE_EPS, OBJECTIVE_TOL = 1e-4, 5e-5
SMALL = dict(policy_hidden=(6, 5), critic_hidden=(7, 6))


def small_learner(seed: int, state_dim=3, action_dim=2, dtype=np.float64, **overrides):
    config = offpac_il.Config(**{**SMALL, **overrides})
    rng = np.random.default_rng(seed)
    learner = offpac_il.Learner.create(state_dim, state_dim, action_dim, config, rng, dtype)
    # A target critic that differs from the critic, as it does during training.
    for value in learner.target_critic.params.values():
        value += 0.1 * rng.standard_normal(value.shape)
    return learner, config, rng


def away_from_kinks(*caches, margin=1e-2) -> bool:
    """True when every hidden pre-activation is at least `margin` from the ReLU kink, so
    that finite-difference steps of 1e-4 cannot cross it (as in cs231n's checks)."""
    for cache in caches:
        for activation in cache.activations:
            pre_activation = np.where(activation > 0, activation, activation / 0.01)
            if np.abs(pre_activation).min() < margin:
                return False
    return True


def random_triplets(rng, n, state_dim=3, action_dim=2, terminal_fraction=0.0):
    return offpac_il.Triplets(
        rng.standard_normal((n, state_dim)),
        rng.uniform(-1, 1, (n, action_dim)),
        rng.standard_normal((n, state_dim)),
        rng.random(n) < terminal_fraction,
    )


# ---------------------------------------------------------------------------------------
# Objective (18): the critic's loss, w.r.t. every critic parameter, target frozen.
# ---------------------------------------------------------------------------------------


@given(
    seed=st.integers(0, 2**16),
    n=st.integers(1, 5),
    critic_reg=st.sampled_from([0.0, 0.7]),
    grad_penalty=st.sampled_from([0.0, 0.3]),
)
def test_critic_objective_gradient_matches_finite_differences(seed, n, critic_reg, grad_penalty):
    learner, _, rng = small_learner(seed)
    batch = random_triplets(rng, 2 * n)
    t = rng.uniform(0.0, 1.0, (2 * n, 1))
    t[n:] *= 0.5  # replay rows' targets are halved, as in Eq. (18)
    assume(away_from_kinks(learner.critic.forward((batch.states, batch.actions))[1]))

    def loss():
        return offpac_il.critic_loss_and_grads(learner, batch, t, n, critic_reg, grad_penalty)[0]

    _, grads, _ = offpac_il.critic_loss_and_grads(learner, batch, t, n, critic_reg, grad_penalty)
    assert set(grads) == set(learner.critic.params)
    for name, param in learner.critic.params.items():
        assert_gradient_close(
            grads[name],
            numerical_gradient(loss, param, OBJECTIVE_EPS),
            OBJECTIVE_TOL,
            f"objective (18) d/d{name}",
        )


def test_critic_objective_check_catches_a_wrong_gradient():
    """The check above fails if the JS gradient loses its factor 1/2."""
    learner, _, rng = small_learner(1)
    batch = random_triplets(rng, 4)
    t = rng.uniform(0.0, 1.0, (4, 1))
    _, grads, _ = offpac_il.critic_loss_and_grads(learner, batch, t, 2, 0.0)

    def loss():
        return offpac_il.critic_loss_and_grads(learner, batch, t, 2, 0.0)[0]

    numeric = numerical_gradient(loss, learner.critic.params["W0"], OBJECTIVE_EPS)
    assert_gradient_close(grads["W0"], numeric, OBJECTIVE_TOL)  # the right one passes
    with pytest.raises(AssertionError):
        assert_gradient_close(2.0 * grads["W0"], numeric, OBJECTIVE_TOL)


# ---------------------------------------------------------------------------------------
# Gradient (6): the policy objective, through the critic's action Jacobian and the tanh.
# ---------------------------------------------------------------------------------------


@given(seed=st.integers(0, 2**16), states=st.integers(1, 4), noise_samples=st.integers(1, 5))
def test_policy_gradient_matches_finite_differences(seed, states, noise_samples):
    learner, _, rng = small_learner(seed)
    s = rng.standard_normal((states, 3))
    z = rng.standard_normal((states * noise_samples, 3))
    critic_before = {k: v.copy() for k, v in learner.critic.params.items()}
    actions, policy_cache = learner.policy.forward((s, z))
    assume(away_from_kinks(policy_cache, learner.critic.forward((s, actions))[1]))

    def loss():
        return offpac_il.policy_loss_and_grads(learner, s, z)[0]

    # The loss is -mean log q(s, pi(s, z)) over every (state, noise) pair.
    actions = learner.act(np.repeat(s, noise_samples, axis=0), z)
    q, _ = learner.critic.forward((np.repeat(s, noise_samples, axis=0), actions))
    np.testing.assert_allclose(loss(), -np.log(q).mean(), rtol=1e-12)

    _, grads, _ = offpac_il.policy_loss_and_grads(learner, s, z)
    assert set(grads) == set(learner.policy.params)
    for name, param in learner.policy.params.items():
        assert_gradient_close(
            grads[name],
            numerical_gradient(loss, param, OBJECTIVE_EPS),
            OBJECTIVE_TOL,
            f"gradient (6) d/d{name}",
        )
    for name, value in learner.critic.params.items():  # the critic is not updated here
        np.testing.assert_array_equal(value, critic_before[name])


def test_policy_gradient_check_catches_a_wrong_gradient():
    """Dropping the tanh derivative (a common slip) is caught."""
    learner, _, rng = small_learner(2)
    s, z = rng.standard_normal((2, 3)), rng.standard_normal((6, 3))
    actions, policy_cache = learner.policy.forward((s, z))
    _, critic_cache = learner.critic.forward((s, actions))
    d_x = -(1 - critic_cache.output) / len(z)
    (_, d_actions), _ = learner.critic.backward(
        d_x, critic_cache, through_head=False, param_grads=False
    )
    _, wrong = learner.policy.backward(d_actions, policy_cache, through_head=False)

    def loss():
        return offpac_il.policy_loss_and_grads(learner, s, z)[0]

    numeric = numerical_gradient(loss, learner.policy.params["W1"], OBJECTIVE_EPS)
    right = offpac_il.policy_loss_and_grads(learner, s, z)[1]["W1"]
    assert_gradient_close(right, numeric, OBJECTIVE_TOL)
    with pytest.raises(AssertionError):
        assert_gradient_close(wrong["W1"], numeric, OBJECTIVE_TOL)


# ---------------------------------------------------------------------------------------
# The critic's targets t (Eq. 17-18) and the termination treatments.
# ---------------------------------------------------------------------------------------


def targets_and_continuation(learner, config, rng):
    """critic_targets on 6 random triplets (3 expert, 3 replay; terminal s' included),
    and the same expectation written out: mean over 4 noise vectors of q'(s', a')^gamma,
    0 at a terminal s' under zero continuation."""
    batch = random_triplets(rng, 6, terminal_fraction=0.5)
    batch.terminal[:2] = [True, False]
    from_replay = np.arange(6) >= 3
    t = offpac_il.critic_targets(learner, batch, from_replay, config, np.random.default_rng(9))
    noise = np.random.default_rng(9).standard_normal((6 * 4, 3), np.float32)
    next_states = np.repeat(batch.next_states, 4, axis=0)
    q_next, _ = learner.target_critic.forward((next_states, learner.act(next_states, noise)))
    continuation = (q_next[:, 0] ** config.gamma).reshape(6, 4).mean(axis=1)
    if config.termination == "zero":
        continuation[batch.terminal] = 0.0
    return t, continuation, batch, from_replay


def test_critic_input_grad_diagnostic_is_half_the_squared_input_gradient():
    """The progress column critic_input_grad: 1/2 mean_n ||dx_n/d[s_n, a_n]||^2 at the
    expert's states and the policy's actions there, against finite differences of x."""
    learner, _, rng = small_learner(3)
    expert = random_triplets(rng, 4)
    diagnostics = offpac_il.imitation_diagnostics(learner, expert, np.random.default_rng(0))
    noise = np.random.default_rng(0).standard_normal((4, learner.noise_dim), np.float32)
    inputs = np.concatenate([expert.states, learner.act(expert.states, noise)], axis=1)
    squared = []
    for row in inputs:

        def logit(row=row):
            return float(learner.critic.forward(row[None])[1].logits[0, 0])

        squared.append((numerical_gradient(logit, row) ** 2).sum())
    assert diagnostics["critic_input_grad"] == pytest.approx(0.5 * np.mean(squared), rel=1e-6)


def test_rows_written_before_a_column_existed_leave_it_blank():
    later = ("critic_input_grad", "policy_noise_spread", "eval_falls")
    old = {name: 1.0 for name in offpac_il.PROGRESS_FIELDS if name not in later}
    new = {name: 2.0 for name in offpac_il.PROGRESS_FIELDS}
    header, first, second = offpac_il.progress_csv([old, new]).splitlines()
    assert header.split(",") == list(offpac_il.PROGRESS_FIELDS)
    assert first.split(",")[-3:] == ["", "", ""] and second.split(",")[-3:] == ["2.0"] * 3


@pytest.mark.parametrize("time_limit, falls", [(1000, 3), (4, 0)])
def test_evaluation_counts_the_episodes_that_fell(time_limit, falls):
    """An untrained Hopper falls within a few dozen steps: with the 1000-step limit every
    episode ends by a fall; cut off by a 4-step limit first, none does."""
    import expert

    env = expert.make_env("Hopper-v4", max_episode_steps=time_limit)
    config = offpac_il.Config(policy_hidden=(4, 4), critic_hidden=(4, 4), eval_episodes=3)
    zeros = np.zeros((2, 11), np.float32)
    demos = expert.Demos(zeros, np.zeros((2, 3), np.float32), zeros, np.zeros(2, bool))
    spaces = offpac_il.make_spaces(env, demos, config)
    learner = offpac_il.Learner.create(11, 11, 3, config, np.random.default_rng(0))
    returns, counted = offpac_il.evaluate(env, learner, spaces, config, round_index=0)
    assert returns.shape == (3,) and counted == falls


def test_policy_noise_spread_is_how_much_the_action_moves_with_z():
    """0 for the deterministic policy (z fixed); for Ours it grows with PN's weights on
    z, the columns of the first layer that multiply the noise input."""
    rng = np.random.default_rng(0)
    expert = random_triplets(rng, 5)

    def spread(learner):
        return offpac_il.imitation_diagnostics(learner, expert, np.random.default_rng(1))[
            "policy_noise_spread"
        ]

    assert spread(small_learner(3, policy_type="deterministic")[0]) == pytest.approx(0, abs=1e-12)
    learner = small_learner(3)[0]
    before = spread(learner)
    learner.policy.params["W0"][3:] *= 3.0  # the rows of W0 that read z (state_dim = 3)
    assert 0.0 < before < spread(learner)


def test_exploration_noise_is_executed_and_stored():
    """With --exploration-noise sigma, step t executes and stores
    clip(pi(s_t, z_t) + sigma * eps_t, -1, 1), z_t and eps_t drawn in turn from the
    run's Generator; with sigma = 0 no eps is drawn and pi(s_t, z_t) is used."""
    import expert

    env = expert.make_env("Hopper-v4")
    config = offpac_il.Config(policy_hidden=(4, 4), critic_hidden=(4, 4))
    zeros = np.zeros((2, 11), np.float32)
    demos = expert.Demos(zeros, np.zeros((2, 3), np.float32), zeros, np.zeros(2, bool))
    spaces = offpac_il.make_spaces(env, demos, config)
    learner = offpac_il.Learner.create(11, 11, 3, config, np.random.default_rng(0))
    executed = []
    step = env.step
    env.step = lambda a: executed.append(a) or step(a)
    for sigma in (0.0, 0.5):
        replay, executed[:] = offpac_il.ReplayBuffer(2000, 11, 3), []
        _, length = offpac_il.run_episode(
            env, learner, spaces, np.random.default_rng(1), 0, replay, sigma
        )
        draws, expected = np.random.default_rng(1), []
        for state in replay.data.states[:length]:
            action = learner.act(state[None], draws.standard_normal((1, 11), np.float32))[0]
            if sigma:
                action = np.clip(action + sigma * draws.standard_normal(3, np.float32), -1, 1)
            expected.append(action)
        stored = replay.data.actions[:length]
        np.testing.assert_array_equal(stored, np.array(expected))
        np.testing.assert_allclose(np.array(executed), spaces.to_env_action(stored), rtol=1e-6)
    assert np.abs(stored).max() == 1.0  # sigma = 0.5 pushes some components to the bound


def test_critic_input_noise_perturbs_only_the_critic_steps_inputs(monkeypatch):
    """--critic-input-noise sigma: the critic's loss sees (s + sigma eps, a + sigma eps'),
    drawn after the targets from the run's Generator; the targets see the clean triplets;
    with sigma = 0 nothing is drawn, so runs made before the flag replay unchanged."""
    seen = []
    loss = offpac_il.critic_loss_and_grads
    monkeypatch.setattr(
        offpac_il,
        "critic_loss_and_grads",
        lambda ln, batch, *a: seen.append(batch) or loss(ln, batch, *a),
    )
    targets = offpac_il.critic_targets
    monkeypatch.setattr(
        offpac_il,
        "critic_targets",
        lambda ln, batch, *a: seen.append(batch) or targets(ln, batch, *a),
    )
    rng = np.random.default_rng(0)
    expert_rows, replay_rows = random_triplets(rng, 3), random_triplets(rng, 3)
    clean = np.concatenate([expert_rows.states, replay_rows.states])
    clean_actions = np.concatenate([expert_rows.actions, replay_rows.actions])
    for sigma in (0.0, 0.5):
        learner, config, _ = small_learner(2, critic_input_noise=sigma, target_samples=2)
        seen[:] = []
        draws = np.random.default_rng(7)
        offpac_il.critic_step(learner, expert_rows, replay_rows, config, 1e-3, draws)
        for_targets, for_loss = seen
        np.testing.assert_array_equal(for_targets.states, clean)
        expected = np.random.default_rng(7)
        expected.standard_normal((6 * 2, learner.noise_dim), np.float32)  # the targets' z
        if sigma:
            noise_s = expected.standard_normal(clean.shape, np.float32)
            noise_a = expected.standard_normal(clean_actions.shape, np.float32)
            np.testing.assert_allclose(for_loss.states, clean + sigma * noise_s, rtol=1e-6)
            np.testing.assert_allclose(for_loss.actions, clean_actions + sigma * noise_a, rtol=1e-6)
        else:
            assert for_loss is for_targets
        np.testing.assert_array_equal(for_loss.next_states, for_targets.next_states)
        # Whatever the critic step drew, the generator stands where `expected` does.
        assert draws.random() == expected.random()


@pytest.mark.parametrize("termination", offpac_il.TERMINATIONS)
def test_critic_targets(termination):
    learner, config, rng = small_learner(3, termination=termination, target_samples=4)
    t, expected, _, from_replay = targets_and_continuation(learner, config, rng)
    expected[from_replay] /= 2
    np.testing.assert_allclose(t, expected, rtol=1e-10)
    assert np.all((t >= 0) & (t <= 1))


def test_action_scaling_round_trip():
    spaces = offpac_il.Spaces(
        np.array([-0.4, 0.0]), np.array([0.4, 2.0]), np.zeros(2), np.ones(2), absorbing=False
    )
    a = np.array([[-1.0, 1.0], [0.0, 0.5]])
    env_a = spaces.to_env_action(a)
    np.testing.assert_allclose(env_a, [[-0.4, 2.0], [0.0, 1.5]])
    np.testing.assert_allclose(spaces.from_env_action(env_a), a, atol=1e-6)
    assert spaces.from_env_action(np.array([9.0, -9.0])).tolist() == [1.0, -1.0]


# ---------------------------------------------------------------------------------------
# The command line, end to end on Hopper-v4 with small networks.
# ---------------------------------------------------------------------------------------

TINY_RUN = [
    "--env",
    "Hopper-v4",
    "--total-steps",
    "300",
    "--eval-every",
    "100",
    "--eval-episodes",
    "1",
    "--policy-hidden",
    "8",
    "8",
    "--critic-hidden",
    "16",
    "16",
    "--noise-samples",
    "4",
    "--target-samples",
    "2",
    "--batch-size",
    "8",
    "--checkpoint-every",
    "0",
    "--log-every",
    "0",
]


def run_cli(*args, check=True):
    return run_script("offpac_il.py", *args, check=check)


def read_progress(run_dir: Path) -> list[dict]:
    return read_rows(run_dir / "progress.csv")


def test_command_line_run_writes_its_files(tmp_path, hopper_demos):
    run_dir = tmp_path / "run"
    result = run_cli(*TINY_RUN, "--demos", hopper_demos, "--run-dir", run_dir)
    for name in (
        "config.json",
        "progress.csv",
        "checkpoint.npz",
        "policy_best.npz",
        "policy_final.npz",
    ):
        assert (run_dir / name).is_file(), name
    rows = read_progress(run_dir)
    assert [int(r["interactions"]) >= 100 * i for i, r in enumerate(rows)]
    assert int(rows[-1]["interactions"]) >= 300
    assert all(np.isfinite(float(r["normalized_score"])) for r in rows)
    assert "eval" in result.stdout
    assert not list(run_dir.glob("*.tmp")) and not list(run_dir.glob(".*.tmp"))
    # A second start in the same directory is refused rather than overwriting the run.
    again = run_cli(*TINY_RUN, "--demos", hopper_demos, "--run-dir", run_dir, check=False)
    assert again.returncode == 2 and "--resume" in again.stderr


def tiny_config(run_dir: Path, demos: Path, seed=0, extra=()) -> offpac_il.Config:
    args = offpac_il.build_parser().parse_args(
        TINY_RUN
        + [*map(str, extra), "--demos", str(demos), "--seed", str(seed), "--run-dir", str(run_dir)]
    )
    return offpac_il.Config(
        **{
            f.name: (tuple(v) if isinstance(v, list) else v)
            for f in dataclasses.fields(offpac_il.Config)
            for v in [getattr(args, f.name)]
        }
    )


def test_resume_reproduces_an_uninterrupted_run(tmp_path, hopper_demos, monkeypatch):
    offpac_il.train(tiny_config(tmp_path / "whole", hopper_demos))
    same_seed = tmp_path / "again"
    offpac_il.train(tiny_config(same_seed, hopper_demos))
    other_seed = tmp_path / "other"
    offpac_il.train(tiny_config(other_seed, hopper_demos, seed=1))

    interrupted = tmp_path / "interrupted"
    with monkeypatch.context() as patch:
        patch.setattr(offpac_il, "run_episode", interrupted_after(3))
        with pytest.raises(KeyboardInterrupt):
            offpac_il.train(tiny_config(interrupted, hopper_demos))
    partial = read_progress(interrupted)
    assert 0 < int(partial[-1]["interactions"]) < 300
    offpac_il.train(tiny_config(interrupted, hopper_demos), resume=True)

    whole = read_progress(tmp_path / "whole")
    # Resuming a finished run adds nothing.
    offpac_il.train(tiny_config(tmp_path / "whole", hopper_demos), resume=True)
    assert read_progress(tmp_path / "whole") == whole
    assert read_progress(same_seed) == whole
    assert read_progress(other_seed) != whole
    assert read_progress(interrupted) == whole


def test_policy_average_is_evaluated_beside_pn_and_changes_nothing_else(
    tmp_path, hopper_demos, monkeypatch
):
    """--policy-average r: after each update theta_avg <- r theta + (1 - r) theta_avg;
    training (episodes, updates, PN's evaluation) is the run without the flag, row for
    row; the averaged PN is evaluated on the same episode seeds and resumes exactly."""
    plain = tmp_path / "plain"
    offpac_il.train(tiny_config(plain, hopper_demos, extra=["--policy-average", "0"]))
    averaged = tmp_path / "averaged"
    offpac_il.train(tiny_config(averaged, hopper_demos, extra=["--policy-average", "0.05"]))
    rows, plain_rows = read_progress(averaged), read_progress(plain)
    assert [
        {k: v for k, v in row.items() if k not in offpac_il.AVERAGE_FIELDS}
        for row in without_wall_time(rows)
    ] == without_wall_time(plain_rows)
    # At the start the average is PN itself: the same episodes, the same return.
    assert rows[0]["average_return_mean"] == rows[0]["eval_return_mean"]
    assert rows[-1]["average_return_mean"] != rows[-1]["eval_return_mean"]
    assert {int(r["average_falls"]) for r in rows} <= set(range(2))
    saved = nets.load_arrays(averaged / "policy_average.npz")
    with np.load(averaged / "checkpoint.npz") as checkpoint:
        for name, value in saved.items():
            np.testing.assert_array_equal(
                value, checkpoint[name.replace("policy", "average_policy")]
            )
    # ... and `experiments.py evaluate --policy average` plays it.
    played = experiments.evaluate_policy(averaged, "average", episodes=2, seed=7)
    assert played != experiments.evaluate_policy(averaged, "final", episodes=2, seed=7)

    # The update rule, on one update.
    learner, config, rng = small_learner(4, policy_average=0.25, batch_size=3)
    before = {k: v.copy() for k, v in learner.average_policy.params.items()}
    replay = offpac_il.ReplayBuffer(10, 3, 2)
    for row in range(5):
        replay.add(*(x[row] for x in dataclasses.astuple(random_triplets(rng, 5))))
    offpac_il.update(learner, random_triplets(rng, 4), replay, config, 0, rng)
    for name, value in learner.average_policy.params.items():
        np.testing.assert_allclose(value, 0.75 * before[name] + 0.25 * learner.policy.params[name])

    # A killed run resumes to the same rows, averaged PN included.
    interrupted = tmp_path / "interrupted"
    flags = ["--policy-average", "0.05"]
    with monkeypatch.context() as patch:
        patch.setattr(offpac_il, "run_episode", interrupted_after(3))
        with pytest.raises(KeyboardInterrupt):
            offpac_il.train(tiny_config(interrupted, hopper_demos, extra=flags))
    offpac_il.train(tiny_config(interrupted, hopper_demos, extra=flags), resume=True)
    assert without_wall_time(read_progress(interrupted)) == without_wall_time(rows)


def without_wall_time(rows: list[dict]) -> list[dict]:
    return [{k: v for k, v in row.items() if k != "wall_seconds"} for row in rows]


def test_kill_and_resume_from_the_command_line(tmp_path, hopper_demos):
    run_dir = tmp_path / "run"
    process = subprocess.Popen(
        [
            sys.executable,
            str(ROOT / "offpac_il.py"),
            *TINY_RUN,
            "--demos",
            str(hopper_demos),
            "--run-dir",
            str(run_dir),
        ],
        cwd=ROOT,
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
    )
    # Kill -9 as soon as the first checkpoint exists (the run may be anywhere after it).
    import time

    deadline = time.time() + 300
    while not (run_dir / "checkpoint.npz").exists() and time.time() < deadline:
        time.sleep(0.05)
    process.kill()
    process.wait()
    run_cli("--resume", run_dir)
    whole = tmp_path / "whole"
    run_cli(*TINY_RUN, "--demos", hopper_demos, "--run-dir", whole)
    assert read_progress(run_dir) == read_progress(whole)


@pytest.mark.parametrize(
    "args, message",
    [
        (["--env", "CartPole-v1"], "action space"),
        (["--env", "NoSuchEnv-v0"], "NoSuchEnv-v0"),
        (["--termination", "sometimes"], "--termination"),
        (["--reward-learning", "gail"], "--reward-learning"),
        (["--policy-type", "beta"], "--policy-type"),
        (["--resume", "/nonexistent/run"], "/nonexistent/run"),
        (["--bogus-flag"], "--bogus-flag"),
        (["--seed", "many"], "--seed"),
    ],
)
def test_bad_input_is_one_line_and_exit_2(tmp_path, args, message):
    result = run_cli(*args, "--run-dir", tmp_path / "r", check=False)
    assert result.returncode == 2
    lines = result.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("error:") and message in lines[0]
    assert not (tmp_path / "r").exists()


def test_bad_demo_file_is_refused(tmp_path):
    bad = tmp_path / "bad.npz"
    bad.write_bytes(b"PK\x03\x04 truncated")
    result = run_cli("--demos", bad, "--run-dir", tmp_path / "r", check=False)
    assert result.returncode == 2
    assert len(result.stderr.strip().splitlines()) == 1 and str(bad) in result.stderr
    assert not (tmp_path / "r").exists()


@pytest.mark.parametrize("fraction", [0.0, 0.5, 1.0])
def test_policy_expert_states_fraction(monkeypatch, fraction):
    """--policy-expert-states draws that share of the policy step's states from B_pi_E."""
    learner, config, rng = small_learner(
        4, policy_expert_states=fraction, batch_size=8, noise_samples=2, target_samples=2
    )
    expert_buffer = random_triplets(rng, 20)
    replay = offpac_il.ReplayBuffer(50, 3, 2)
    for _ in range(30):
        replay.add(rng.standard_normal(3) + 100.0, rng.uniform(-1, 1, 2), np.zeros(3), False)
    seen = {}

    def capture(learner, states, *args):
        seen["states"] = states
        return {}

    monkeypatch.setattr(offpac_il, "policy_step", capture)
    offpac_il.update(learner, expert_buffer, replay, config, 0, rng)
    from_expert = (np.abs(seen["states"]) < 50).all(axis=1)  # replay states sit near 100
    assert from_expert.sum() == round(fraction * 8)


# ---------------------------------------------------------------------------------------
# The ablations (Sec. 5.3, Figure 4): every new gradient against finite differences, each
# check shown to catch a wrong gradient; then each switch end to end.
# ---------------------------------------------------------------------------------------

OBJECTIVES = ("discriminator", "entropy")
# The dev profile (1000 examples per test) found small gradient elements (behind units
# on the leaky side of their ReLU) that missed 5e-5 relative error: ~4e-9 ones by ~1e-12
# absolute (the difference's rounding), a 9e-7 one by 1.3e-10 (its truncation error,
# O(eps^2) with the curvature of the whole loss). The checks below hold elements under
# 1e-5 to 5e-5 * 1e-5 = 5e-10 absolute instead; a wrong gradient is off by O(1) on the
# large elements (~1e-2 and more), as the wrong-gradient tests show.
OBJECTIVE_FLOOR = 1e-5


def reward_learner(seed: int, objective="entropy", **overrides):
    """A small float64 learner with a reward network r_omega (QN's hidden sizes)."""
    learner, config, rng = small_learner(seed, reward_learning=objective, **overrides)
    assert learner.reward.sizes == learner.critic.sizes and learner.reward.head == "sigmoid"
    return learner, config, rng


def reward_loss_direct(learner, batch, n_expert, objective) -> float:
    """Objectives (2) (as GAIL's discriminator) and (8), negated, written out in p."""
    r, _ = learner.reward.forward((batch.states, batch.actions))
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
    batch = random_triplets(rng, n_expert + n_learner)
    assume(away_from_kinks(learner.reward.forward((batch.states, batch.actions))[1]))

    def loss():
        return offpac_il.reward_loss_and_grads(
            learner.reward, batch.states, batch.actions, n_expert, objective
        )[0]

    np.testing.assert_allclose(
        loss(), reward_loss_direct(learner, batch, n_expert, objective), rtol=1e-12
    )
    _, grads, _ = offpac_il.reward_loss_and_grads(
        learner.reward, batch.states, batch.actions, n_expert, objective
    )
    assert set(grads) == set(learner.reward.params)
    for name, param in learner.reward.params.items():
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
    batch = random_triplets(rng, 6)
    args = (learner.reward, batch.states, batch.actions, 3, objective)

    def loss():
        return offpac_il.reward_loss_and_grads(*args)[0]

    numeric = numerical_gradient(loss, learner.reward.params["W1"], OBJECTIVE_EPS)
    right = offpac_il.reward_loss_and_grads(*args)[1]["W1"]
    assert_gradient_close(right, numeric, OBJECTIVE_TOL, floor=OBJECTIVE_FLOOR)
    if objective == "discriminator":
        backward = learner.reward.backward
        monkeypatch.setattr(
            learner.reward, "backward", lambda d, cache, **kw: backward(d, cache, input_grads=False)
        )
    else:
        monkeypatch.setattr(offpac_il.nets, "bernoulli_entropy_grad", lambda x: -x)
    wrong = offpac_il.reward_loss_and_grads(*args)[1]["W1"]
    with pytest.raises(AssertionError):
        assert_gradient_close(wrong, numeric, OBJECTIVE_TOL, floor=OBJECTIVE_FLOOR)


def test_reward_objectives_move_r_where_the_paper_says():
    """Gradient descent on (2) sends r to 1 on expert pairs and 0 on the learner's; on (8)
    to 1 on expert pairs and 1/2 on the learner's (Sec. 3.1.1)."""
    for objective, r_learner in (("discriminator", 0.0), ("entropy", 0.5)):
        learner, config, rng = reward_learner(6, objective, critic_hidden=(16, 16))
        batch = random_triplets(rng, 8)
        batch.states[4:] += 3.0  # the learner's pairs, apart from the expert's
        optimizer = offpac_il.nets.RMSProp()
        for _ in range(1500):
            _, grads, _ = offpac_il.reward_loss_and_grads(
                learner.reward, batch.states, batch.actions, 4, objective
            )
            optimizer.step(learner.reward.params, grads, 1e-2)
        r, _ = learner.reward.forward((batch.states, batch.actions))
        np.testing.assert_allclose(r[:4, 0], 1.0, atol=0.05)
        np.testing.assert_allclose(r[4:, 0], r_learner, atol=0.05)


# Objective (15): the critic against Eq. (13)'s target r_omega(s, a) E q'(s', a')^gamma.


@pytest.mark.parametrize("termination", offpac_il.TERMINATIONS)
def test_critic_targets_with_a_learned_reward(termination):
    """t = r_omega(s, a) mean_k q'(s', a'_k)^gamma on every row (Eq. 13 in 15): no /2."""
    learner, config, rng = reward_learner(3, termination=termination, target_samples=4)
    t, expected, batch, _ = targets_and_continuation(learner, config, rng)
    r, _ = learner.reward.forward((batch.states, batch.actions))
    np.testing.assert_allclose(t, r[:, 0] * expected, rtol=1e-10)


@given(
    seed=st.integers(0, 2**16),
    n=st.integers(1, 4),
    objective=st.sampled_from(OBJECTIVES),
    critic_reg=st.sampled_from([0.0, 0.7]),
)
def test_critic_objective_15_gradient_matches_finite_differences(seed, n, objective, critic_reg):
    """Objective (15) w.r.t. every critic parameter, its target (r_omega and nu') frozen."""
    learner, config, rng = reward_learner(seed, objective, target_samples=3)
    batch = random_triplets(rng, 2 * n, terminal_fraction=0.2)
    from_replay = np.arange(2 * n) >= n
    t = offpac_il.critic_targets(learner, batch, from_replay, config, rng)[:, None]
    assume(away_from_kinks(learner.critic.forward((batch.states, batch.actions))[1]))

    def loss():
        return offpac_il.critic_loss_and_grads(learner, batch, t, n, critic_reg)[0]

    q, _ = learner.critic.forward((batch.states, batch.actions))
    js = offpac_il.nets.js_divergence(np.log(q) - np.log1p(-q), t)[:, 0]
    expected = js[:n].mean() + js[n:].mean()  # the expert rows' mean + the replay rows'
    if critic_reg == 0:
        np.testing.assert_allclose(loss(), expected, rtol=1e-10)
    _, grads, _ = offpac_il.critic_loss_and_grads(learner, batch, t, n, critic_reg)
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
    from_replay = np.arange(6) >= 3
    t15 = offpac_il.critic_targets(learner, batch, from_replay, config, rng)[:, None]
    learner_18 = dataclasses.replace(learner, reward=None)  # the same networks, targets (18)
    t18 = offpac_il.critic_targets(learner_18, batch, from_replay, config, rng)[:, None]

    def loss():
        return offpac_il.critic_loss_and_grads(learner, batch, t15, 3, 0.0)[0]

    numeric = numerical_gradient(loss, learner.critic.params["W0"], OBJECTIVE_EPS)
    right = offpac_il.critic_loss_and_grads(learner, batch, t15, 3, 0.0)[1]["W0"]
    wrong = offpac_il.critic_loss_and_grads(learner, batch, t18, 3, 0.0)[1]["W0"]
    assert_gradient_close(right, numeric, OBJECTIVE_TOL, floor=OBJECTIVE_FLOOR)
    with pytest.raises(AssertionError):
        assert_gradient_close(wrong, numeric, OBJECTIVE_TOL, floor=OBJECTIVE_FLOOR)


def test_reward_step_comes_before_the_critic_step():
    """Each update moves r_omega on the critic's triplets, then the critic by (15)."""
    learner, config, rng = reward_learner(8, objective="discriminator", batch_size=4)
    before = {k: v.copy() for k, v in learner.reward.params.items()}
    stats = offpac_il.critic_step(
        learner, random_triplets(rng, 4), random_triplets(rng, 4), config, 1e-3, rng
    )
    assert {"reward_loss", "r_expert", "r_replay", "critic_loss"} <= set(stats)
    assert all(not np.array_equal(before[k], v) for k, v in learner.reward.params.items())


# The Gaussian policy (Ours+GP): a = mu(s) + sigma(s) eps, reparameterised (gradient 6).


def gaussian_learner(seed: int, log_std_bias: float | None = None):
    learner, config, rng = small_learner(seed, policy_type="gaussian")
    assert learner.noise_dim == 2 and learner.policy.sizes == [3, 6, 5, 4]  # [s] -> mu, l
    last = learner.policy.n_layers - 1
    assert not learner.policy.params[f"W{last}"][:, 2:].any()  # sigma = 1 at the start
    for value in learner.policy.params.values():  # a general point: l depends on s
        value += 0.3 * rng.standard_normal(value.shape)
    if log_std_bias is not None:
        learner.policy.params[f"b{last}"][2:] = log_std_bias
    return learner, rng


@given(seed=st.integers(0, 2**16), states=st.integers(1, 4), noise_samples=st.integers(1, 5))
def test_gaussian_policy_gradient_matches_finite_differences(seed, states, noise_samples):
    """Gradient (6) w.r.t. every PN parameter, mean and log-std heads alike."""
    learner, rng = gaussian_learner(seed)
    s = rng.standard_normal((states, 3))
    eps = rng.standard_normal((states * noise_samples, 2))
    actions, policy_cache = learner.policy_forward(s, eps)
    critic_cache = learner.critic.forward((np.repeat(s, noise_samples, axis=0), actions))[1]
    assume(away_from_kinks(policy_cache.net, critic_cache))

    # The action written out: a = mu(s) + exp(l(s)) eps, unbounded.
    out, _ = learner.policy.forward(s)
    mean, log_std = np.repeat(out[:, :2], noise_samples, 0), np.repeat(out[:, 2:], noise_samples, 0)
    # Inside the log-std bounds, away from the clip's kinks (checked separately below).
    assume(np.all(np.abs(log_std - offpac_il.LOG_STD_MAX) > 1e-2))
    np.testing.assert_allclose(actions, mean + np.exp(np.minimum(log_std, 2.0)) * eps, rtol=1e-12)

    def loss():
        return offpac_il.policy_loss_and_grads(learner, s, eps)[0]

    _, grads, _ = offpac_il.policy_loss_and_grads(learner, s, eps)
    assert set(grads) == set(learner.policy.params)
    for name, param in learner.policy.params.items():
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

    last = f"W{learner.policy.n_layers - 1}"
    numeric = numerical_gradient(loss, learner.policy.params[last], OBJECTIVE_EPS)
    right = offpac_il.policy_loss_and_grads(learner, s, eps)[1][last]
    assert_gradient_close(right, numeric, OBJECTIVE_TOL, floor=OBJECTIVE_FLOOR)
    assert np.abs(right[:, 2:]).max() > 1e-3  # the log-std head is being checked

    actions, cache = learner.policy_forward(s, eps)
    _, critic_cache = learner.critic.forward((s, actions))
    (_, d_actions), _ = learner.critic.backward(
        -(1 - critic_cache.output) / len(eps), critic_cache, through_head=False
    )
    wrong_cache = dataclasses.replace(cache, std=np.ones_like(cache.std))
    wrong = learner.policy_backward(d_actions, wrong_cache)[last]
    with pytest.raises(AssertionError):
        assert_gradient_close(wrong, numeric, OBJECTIVE_TOL, floor=OBJECTIVE_FLOOR)


def test_gaussian_log_std_outside_its_bounds_gets_no_gradient():
    learner, rng = gaussian_learner(10, log_std_bias=offpac_il.LOG_STD_MAX + 5.0)
    s, eps = rng.standard_normal((2, 3)), rng.standard_normal((4, 2))
    actions = learner.act(s, eps)
    mean = np.repeat(learner.policy.forward(s)[0][:, :2], 2, axis=0)
    np.testing.assert_allclose(actions, mean + np.exp(offpac_il.LOG_STD_MAX) * eps, rtol=1e-12)
    last = learner.policy.n_layers - 1
    grads = offpac_il.policy_loss_and_grads(learner, s, eps)[1]
    assert not grads[f"b{last}"][2:].any() and not grads[f"W{last}"][:, 2:].any()
    assert grads[f"b{last}"][:2].any()


def test_gaussian_actions_are_clipped_only_for_the_environment(hopper_demos):
    """The environment gets clip(a) (mapped to its bounds); the replay keeps a itself."""
    import expert

    env = expert.make_env("Hopper-v4")
    demos = expert.load_demos(hopper_demos, "Hopper-v4")
    config = offpac_il.Config(policy_type="gaussian", policy_hidden=(4, 4), critic_hidden=(4, 4))
    spaces = offpac_il.make_spaces(env, demos, config)
    learner = offpac_il.Learner.create(11, 11, 3, config, np.random.default_rng(0))
    learner.policy.params["b2"][3:] = 1.0  # sigma = e: most actions out of [-1, 1]
    executed = []
    step = env.step
    env.step = lambda a: executed.append(a) or step(a)
    replay = offpac_il.ReplayBuffer(2000, 11, 3)
    _, length = offpac_il.run_episode(env, learner, spaces, np.random.default_rng(1), 0, replay)
    stored = replay.data.actions[:length]
    assert np.abs(stored).max() > 1.5  # the critic sees the sampled, unbounded actions
    np.testing.assert_allclose(np.array(executed), spaces.to_env_action(np.clip(stored, -1, 1)))


# The deterministic policy (Ours+DP): tanh(PN([s, z_0])) with one fixed z_0.


def test_deterministic_policy_ignores_the_noise_it_is_given():
    learner, config, rng = small_learner(11, policy_type="deterministic")
    z0 = learner.fixed_noise
    assert z0.shape == (3,) and np.abs(z0).max() > 0  # one draw of N(0, I), not zeros
    s = rng.standard_normal((2, 3))
    a1 = learner.act(s, rng.standard_normal((2, 3)))
    a2 = learner.act(s, rng.standard_normal((2, 3)))
    np.testing.assert_array_equal(a1, a2)
    np.testing.assert_allclose(a1, learner.policy.forward((s, np.tile(z0, (2, 1))))[0])
    assert learner.samples_per_state(128) == 1 and small_learner(0)[0].samples_per_state(128) == 128
    # Its gradient (6) is Ours' with z = z_0, checked like Ours' on every parameter.
    z = np.tile(z0, (2, 1))
    actions, policy_cache = learner.policy.forward((s, z))
    assert away_from_kinks(policy_cache, learner.critic.forward((s, actions))[1])

    def loss():
        return offpac_il.policy_loss_and_grads(learner, s, z)[0]

    grads = offpac_il.policy_loss_and_grads(learner, s, z)[1]
    for name, param in learner.policy.params.items():
        assert_gradient_close(
            grads[name],
            numerical_gradient(loss, param, OBJECTIVE_EPS),
            OBJECTIVE_TOL,
            f"deterministic gradient (6) d/d{name}",
            floor=OBJECTIVE_FLOOR,
        )


# The on-policy switch (Ours+OnP): updates see the latest episode's triplets only.


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
    offpac_il.train(tiny_config(tmp_path / "run", hopper_demos, extra=extra))
    assert len(lengths) >= 3
    for episode, size in seen:
        latest = lengths[episode - 1]
        assert size == (latest if on_policy else min(sum(lengths[:episode]), 15_000))


@pytest.mark.parametrize("method", experiments.ABLATIONS)
def test_each_ablation_runs_from_the_command_line_and_resumes(
    method, tmp_path, hopper_demos, monkeypatch
):
    """experiments.METHODS' selector of each ablation, on the command line: a few hundred
    interactions on Hopper-v4, its progress and checkpoint; then the same run killed
    halfway and resumed from its checkpoint gives the same progress."""
    script, selector = experiments.METHODS[method]
    assert script == "offpac_il.py" and selector
    whole = tmp_path / "whole"
    run_cli(*TINY_RUN, *selector, "--demos", hopper_demos, "--run-dir", whole)
    config = offpac_il.Config(**{
        k: tuple(v) if isinstance(v, list) else v
        for k, v in json.loads((whole / "config.json").read_text()).items()
    })  # fmt: skip
    switches = ("on_policy", "reward_learning", "policy_type")
    default = offpac_il.Config()
    assert [getattr(config, k) != getattr(default, k) for k in switches].count(True) == 1
    rows = read_progress(whole)
    interactions = [int(r["interactions"]) for r in rows]
    assert interactions[0] == 0 and interactions[-1] >= 300
    assert all(n >= 100 * i for i, n in enumerate(interactions))  # one row per 100 or more
    assert list(rows[0]) == [f for f in offpac_il.progress_fields(config) if f != "wall_seconds"]
    for row in rows[1:]:  # every column filled and finite after the first updates
        assert row["updates"] == row["interactions"]
        assert all(math.isfinite(float(v)) for v in row.values()), row
    last = rows[-1]
    checkpoint = nets.load_arrays(whole / "checkpoint.npz")
    policy = nets.load_arrays(whole / "policy_final.npz")
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
    with threadpool_limits(limits=1, user_api="blas"):  # as the command line runs
        with monkeypatch.context() as patch:
            episodes = int(last["episodes"]) // 2  # killed halfway
            patch.setattr(offpac_il, "run_episode", interrupted_after(episodes))
            with pytest.raises(KeyboardInterrupt):
                offpac_il.train(tiny_config(interrupted, hopper_demos, extra=selector))
        saved = json.loads(str(nets.load_arrays(interrupted / "checkpoint.npz")["counters"]))
        assert saved["episodes"] == episodes and 0 < saved["interactions"] < interactions[-1]
        offpac_il.train(tiny_config(interrupted, hopper_demos, extra=selector), resume=True)
    assert read_progress(interrupted) == rows


def test_paper_flag_restores_appendix_b_and_explicit_flags_win():
    defaults = offpac_il.parse_args([])
    assert defaults.policy_expert_states == 0.5 and defaults.policy_lr == 2.3e-5
    paper = offpac_il.parse_args(["--paper"])
    for name, value in offpac_il.PAPER_SETTINGS.items():
        assert getattr(paper, name) == value
    assert (paper.policy_lr, paper.critic_lr, paper.policy_expert_states) == (1e-4, 1e-3, 0.0)
    mixed = offpac_il.parse_args(["--critic-lr", "5e-4", "--paper"])
    assert (mixed.critic_lr, mixed.policy_lr) == (5e-4, 1e-4)
    assert paper.noise_samples == defaults.noise_samples == 128  # gradient (6) as specified


def test_a_config_saved_before_a_setting_existed_keeps_the_papers_behaviour():
    """config.json of an old run lacks policy_expert_states: that run drew its policy
    states from the replay only, and must resume (and be labelled) that way."""
    saved = dataclasses.asdict(offpac_il.Config(policy_lr=1e-4, critic_lr=1e-3))
    del saved["policy_expert_states"], saved["policy_average"]
    saved["policy_hidden"] = list(saved["policy_hidden"])  # as JSON gives it back
    config = offpac_il.saved_config(saved)
    assert config.policy_expert_states == 0.0
    assert config.policy_average == 0.0  # and its checkpoint holds no averaged PN
    assert config.policy_hidden == (100, 100)
    saved["policy_expert_states"] = 0.5
    assert offpac_il.saved_config(saved).policy_expert_states == 0.5


def test_restore_and_the_critic_probe(tmp_path, hopper_demos, monkeypatch):
    """`restore` gives back the checkpoint's learner; `experiments.probe_critic` compares
    the critic at the expert's and the policy's actions. Checked with stand-in experts
    whose action is the policy's own (no difference), and the policy's moved a small
    step along d log q / da (cosine 1, expert action preferred everywhere)."""
    import experiments
    import expert

    config = tiny_config(tmp_path / "run", hopper_demos)
    offpac_il.train(config)
    _, spaces, _, learner, replay, progress = offpac_il.restore(tmp_path / "run")
    assert progress.interactions >= 300 and replay.size == progress.interactions
    saved = nets.load_arrays(tmp_path / "run" / "policy_final.npz")
    for name, value in learner.policy_state().items():
        np.testing.assert_array_equal(value, saved[name])

    def policy_action(observation):
        state = spaces.state(observation)[None]
        return learner.act(state, np.zeros((1, learner.noise_dim), np.float32))

    def along_gradient(observation):
        action = policy_action(observation)
        state = spaces.state(observation)[None]
        q, cache = learner.critic.forward((state, action))
        grad = learner.critic.backward(1.0 - q, cache, through_head=False, param_grads=False)
        step = grad[0][1] / np.linalg.norm(grad[0][1])
        return spaces.to_env_action(np.clip(action + 1e-3 * step, -1, 1))[0]

    class StandIn:
        def __init__(self, act):
            self.act = act

    monkeypatch.setattr(
        expert,
        "load_expert",
        lambda env_id: StandIn(lambda o: spaces.to_env_action(policy_action(o))[0]),
    )
    (same,) = experiments.probe_critic(tmp_path / "run", episodes=1, steps=20)
    assert same["squared_distance"] < 1e-10  # up to the round trip through env units
    assert same["q_at_expert_action"] == pytest.approx(same["q_at_policy_action"], rel=1e-5)
    monkeypatch.setattr(expert, "load_expert", lambda env_id: StandIn(along_gradient))
    (better,) = experiments.probe_critic(tmp_path / "run", episodes=1, steps=20)
    assert 0 < better["steps"] <= 20
    assert better["gradient_cosine"] > 0.99 and better["expert_action_preferred"] == 1.0


def test_evaluate_plays_the_saved_policy_from_new_starts(tmp_path, hopper_demos):
    """`experiments.evaluate_policy` plays the run's policy file, episode i from reset
    seed `seed + i` with noise from a Generator seeded by `seed`, as run_episode does
    with the restored learner, and says which episodes fell."""
    import experiments
    import expert

    offpac_il.train(tiny_config(tmp_path / "run", hopper_demos))
    rows = experiments.evaluate_policy(tmp_path / "run", "final", episodes=3, seed=7)
    assert rows == experiments.evaluate_policy(tmp_path / "run", "checkpoint", 3, seed=7)
    _, spaces, _, learner, _, _ = offpac_il.restore(tmp_path / "run")
    env, rng = expert.make_env("Hopper-v4"), np.random.default_rng(7)
    random_return, expert_return = expert.reference_returns("Hopper-v4")
    for i, row in enumerate(rows):
        total, length = offpac_il.run_episode(env, learner, spaces, rng, 7 + i)
        assert (row["seed"], row["return"], row["length"]) == (7 + i, round(total, 1), length)
        assert row["fell"] == (length < 1000)
        assert row["normalized_score"] == pytest.approx(
            (total - random_return) / (expert_return - random_return)
        )
    # One snapshot per evaluation, the last one the final policy.
    rows_of_run = read_progress(tmp_path / "run")
    snapshots = sorted((tmp_path / "run" / offpac_il.SNAPSHOTS).glob("*.npz"))
    assert [int(p.stem) for p in snapshots] == [int(r["interactions"]) for r in rows_of_run]
    last = experiments.evaluate_policy(tmp_path / "run", snapshots[-1].stem, 3, seed=7)
    assert last == rows
    table = experiments.evaluate_snapshots(tmp_path / "run", episodes=3, seed=7)
    assert [row["interactions"] for row in table] == [int(p.stem) for p in snapshots]
    scores = [row["normalized_score"] for row in rows]
    assert table[-1]["normalized_score"] == pytest.approx(np.mean(scores))
    assert (table[-1]["lowest"], table[-1]["fell"]) == (min(scores), sum(r["fell"] for r in rows))
    # A different policy in the file plays differently.
    arrays = nets.load_arrays(tmp_path / "run" / "policy_final.npz")
    nets.save_arrays(tmp_path / "run" / "policy_final.npz", {k: 2 * v for k, v in arrays.items()})
    assert experiments.evaluate_policy(tmp_path / "run", "final", 3, seed=7) != rows


def test_exponential_averages_are_the_polyak_average_seen_at_the_snapshots():
    """`experiments.exponential_averages`: after a gap of t interactions the old average
    keeps exp(-t / horizon) of its weight, as t soft updates at rate 1 / horizon towards
    a fixed PN would leave it; z_0 is never averaged; dtypes are kept."""
    rng = np.random.default_rng(0)
    first, second = (
        {"policy/w": rng.normal(size=(3, 2)).astype(np.float32), "policy/fixed_noise": z}
        for z in (np.zeros(2, np.float32), np.ones(2, np.float32))
    )
    horizon, gap = 10_000.0, 5_000
    start, after = experiments.exponential_averages([(0, first), (gap, second)], horizon)
    np.testing.assert_array_equal(start["policy/w"], first["policy/w"])
    kept = np.exp(-gap / horizon)
    expected = kept * first["policy/w"] + (1 - kept) * second["policy/w"]
    np.testing.assert_allclose(after["policy/w"], expected, rtol=1e-5)
    np.testing.assert_array_equal(after["policy/fixed_noise"], second["policy/fixed_noise"])
    assert after["policy/w"].dtype == np.float32

    initial = nets.MLP.create([3, 2], "identity", np.random.default_rng(1), np.float64)
    policy = nets.MLP.create([3, 2], "identity", np.random.default_rng(2), np.float64)
    average = initial.copy()
    for _ in range(gap):
        nets.soft_update(average, policy, 1 / horizon)
    snapshots = [(0, initial.state("policy")), (gap, policy.state("policy"))]
    offline = experiments.exponential_averages(snapshots, horizon)[-1]
    for name, online in average.state("policy").items():
        np.testing.assert_allclose(offline[name], online, atol=1e-4)  # (1 - 1/h)^t ~ e^(-t/h)


def test_averaged_snapshots_with_a_tiny_horizon_play_the_snapshots(tmp_path, hopper_demos):
    """`experiments.averaged_snapshots`: one row per snapshot; a horizon far shorter than
    the gap between snapshots averages nothing, so it scores what PN scored."""
    offpac_il.train(tiny_config(tmp_path / "run", hopper_demos))
    rows = experiments.averaged_snapshots(tmp_path / "run", [1e-9, 1e15], episodes=2, seed=7)
    snapshots = sorted((tmp_path / "run" / offpac_il.SNAPSHOTS).glob("*.npz"))
    assert [row["interactions"] for row in rows] == [int(p.stem) for p in snapshots]
    for row in rows:
        assert (row["h1e-09_score"], row["h1e-09_fell"]) == (row["pn_score"], row["pn_fell"])
    # A horizon far longer than the run keeps the initial PN throughout.
    assert len({row["h1e+15_score"] for row in rows}) == 1
    assert rows[0]["h1e+15_score"] == rows[0]["pn_score"]


def test_gradient_noise_separates_the_noise_part_of_gradient_6(tmp_path, hopper_demos):
    """`experiments.gradient_noise`: with the states fixed, what varies is the mean over
    Z noise rows, whose variance shrinks as 1/Z; a deterministic policy has none."""
    import experiments

    offpac_il.train(tiny_config(tmp_path / "stochastic", hopper_demos))
    low, high = experiments.gradient_noise(tmp_path / "stochastic", samples=(2, 32), draws=40)
    assert (low["noise_samples"], high["noise_samples"]) == (2, 32)
    assert 0 < high["noise_variance"] < low["noise_variance"]
    assert 8 < low["noise_variance"] / high["noise_variance"] < 32  # 16 in expectation
    for row in (low, high):
        assert (
            0 < row["noise_share"] == pytest.approx(row["noise_variance"] / row["total_variance"])
        )
        assert 0 < row["mean_step_fraction"] <= 1  # |E g| <= sqrt(E g^2)

    run = tmp_path / "deterministic"
    offpac_il.train(tiny_config(run, hopper_demos, extra=["--policy-type", "deterministic"]))
    (row,) = experiments.gradient_noise(run, samples=(8,), draws=5)
    assert row["noise_variance"] == 0 and row["total_variance"] > 0


def test_eta_uses_this_process_pace_and_never_goes_negative():
    # Resumed at 200 000 interactions (earlier sessions' pace is not used); 1 000 more in
    # 100 s since: 10 per second.
    pace = offpac_il.Pace(200_000, now=50.0)
    assert pace.rate(201_000, now=150.0) == pytest.approx(10.0)
    assert pace.eta_seconds(5_000, 201_000, now=150.0) == pytest.approx(500.0)
    # The last episode may run past the budget.
    assert pace.eta_seconds(-300, 201_000, now=150.0) == 0.0
    assert np.isnan(pace.eta_seconds(5_000, 200_000, now=53.0))
