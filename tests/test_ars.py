"""lab/ars.py: ARS V2-t improves a policy and resumes exactly; its command line trains,
resumes and refuses what it cannot do in one line.

The task is InvertedPendulum-v4 (a few thousand steps), never a shipped expert's.
"""

from __future__ import annotations

import numpy as np
import pytest
from helpers import run_module

import expert
from lab import ars

PENDULUM = "InvertedPendulum-v4"  # obs (x, theta, x', theta'), one force in [-3, 3]


def run_cli(*args):
    return run_module("lab.ars", *args, check=False)


def fresh_pendulum_run() -> ars.ARSState:
    config = ars.ARSConfig(
        step_size=0.05, directions=4, top=2, noise=0.1, survival_bonus=0.0, eval_episodes=3
    )
    return ars.ARSState(
        env_id=PENDULUM,
        seed=0,
        config=config,
        weights=np.zeros((1, 4)),
        statistics=ars.ObservationStatistics(4),
        rng=np.random.default_rng(0),
    )


def test_ars_improves_and_resumes_exactly(tmp_path):
    runner = ars.RolloutRunner(PENDULUM, workers=1)
    try:
        untrained = ars.evaluate_linear(fresh_pendulum_run(), runner).mean()
        straight = fresh_pendulum_run()
        for _ in range(6):
            ars.ars_iteration(straight, runner)
        # The same six iterations, stopped after three and continued from the checkpoint.
        interrupted = fresh_pendulum_run()
        for _ in range(3):
            ars.ars_iteration(interrupted, runner)
        interrupted.save(tmp_path / "checkpoint.npz")
        resumed = ars.ARSState.load(tmp_path / "checkpoint.npz")
        for _ in range(3):
            ars.ars_iteration(resumed, runner)
        trained = ars.evaluate_linear(straight, runner).mean()
    finally:
        runner.close()
    np.testing.assert_array_equal(resumed.weights, straight.weights)
    np.testing.assert_array_equal(resumed.statistics.std(), straight.statistics.std())
    assert resumed.env_steps == straight.env_steps and resumed.iteration == 6
    assert trained > untrained + 20, (untrained, trained)


def test_train_command_writes_expert_and_checkpoint(tmp_path, capsys):
    checkpoint, out = tmp_path / "pendulum.ckpt.npz", tmp_path / "pendulum.npz"
    arguments = [
        "--env",
        PENDULUM,
        "--workers",
        "1",
        "--steps",
        "3000",
        "--directions",
        "4",
        "--top",
        "2",
        "--step-size",
        "0.05",
        "--noise",
        "0.1",
        "--eval-every",
        "2",
        "--checkpoint",
        str(checkpoint),
        "--out",
        str(out),
    ]
    assert ars.main(arguments) == 0
    printed = capsys.readouterr().out
    assert "env steps" in printed and "eval return" in printed
    policy = expert.load_expert(PENDULUM, out)
    assert policy.metadata["seed"] == 0 and "lab.ars --env" in policy.metadata["commands"][0]
    assert policy.metadata["env_steps"] > 0 and policy.metadata["wall_seconds"] >= 0
    assert policy.act(np.zeros(4)).shape == (1,)
    # Resuming with a bigger budget continues; changing the settings is refused.
    resume = ["--env", PENDULUM, "--workers", "1", "--resume", "--checkpoint", str(checkpoint)]
    assert ars.main([*resume, "--steps", "4000", "--out", str(out)]) == 0
    assert ars.ARSState.load(checkpoint).env_steps >= 4000
    assert ars.main([*resume, "--out", str(out)]) == 0  # its own budget, reached: no step
    assert ars.ARSState.load(checkpoint).config.steps == 4000
    capsys.readouterr()
    assert ars.main([*resume, "--noise", "0.2", "--out", str(out)]) == 2
    assert "may change only: --steps" in capsys.readouterr().err
    # A fresh run does not overwrite a checkpoint that holds a run.
    assert ars.main(arguments) == 2
    assert "already holds a run" in capsys.readouterr().err


@pytest.mark.parametrize(
    "args, says",
    [
        (["--env", "CartPole-v1"], "Discrete(2)"),
        (["--env", PENDULUM, "--hidden", "8"], "--hidden"),  # a SAC setting (lab/sac.py)
        (["--env", PENDULUM, "--top", "5", "--directions", "4"], "--top"),
        (["--env", PENDULUM, "--noise", "nan"], "--noise"),
        (["--env", PENDULUM, "--steps", "inf"], "--steps"),
        (["--env", PENDULUM, "--resume"], "no checkpoint"),
    ],
)
def test_bad_input_is_one_line_and_exit_2(tmp_path, args, says):
    result = run_cli(
        *args, "--workers", "1", "--checkpoint", tmp_path / "c.npz", "--out", tmp_path / "e.npz"
    )
    assert result.returncode == 2
    assert result.stderr.count("\n") == 1 and result.stderr.startswith("error: ")
    assert says in result.stderr
    assert list(tmp_path.iterdir()) == []  # nothing half-written


def test_help_lists_the_settings_and_the_task_defaults():
    result = run_cli("--help")
    assert result.returncode == 0
    assert "--step-size" in result.stdout and "Hopper-v4: --step-size 0.01" in result.stdout
