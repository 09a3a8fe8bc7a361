"""The learner: finite-difference checks of objective (18) and gradient (6) as the
learner computes them, the targets, and the command line end to end."""

from __future__ import annotations

import dataclasses
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from gradcheck import assert_gradient_close, numerical_gradient
from helpers import interrupted_after, read_rows, run_script
from hypothesis import assume, given
from hypothesis import strategies as st

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


@pytest.mark.parametrize("termination", offpac_il.TERMINATIONS)
def test_critic_targets(termination):
    learner, config, rng = small_learner(3, termination=termination, target_samples=4)
    batch = random_triplets(rng, 6, terminal_fraction=0.5)
    batch.terminal[:2] = [True, False]
    from_replay = np.arange(6) >= 3
    t = offpac_il.critic_targets(learner, batch, from_replay, config, np.random.default_rng(9))

    # The same expectation written out: mean over 4 noise vectors of q'(s', a')^gamma.
    noise = np.random.default_rng(9).standard_normal((6 * 4, 3), np.float32)
    next_states = np.repeat(batch.next_states, 4, axis=0)
    q_next, _ = learner.target_critic.forward((next_states, learner.act(next_states, noise)))
    expected = (q_next[:, 0] ** config.gamma).reshape(6, 4).mean(axis=1)
    if termination == "zero":
        expected[batch.terminal] = 0.0
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


def tiny_config(run_dir: Path, demos: Path, seed=0) -> offpac_il.Config:
    args = offpac_il.build_parser().parse_args(
        TINY_RUN + ["--demos", str(demos), "--seed", str(seed), "--run-dir", str(run_dir)]
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
        patch.setattr(offpac_il, "run_episode", interrupted_after(7))
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
