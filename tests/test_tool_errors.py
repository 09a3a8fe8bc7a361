"""The tools' remaining tracebacks, each now one line and exit status 2 with nothing
written (issue 46, items 10-16)."""

from __future__ import annotations

import dataclasses
import json
import os
import subprocess
import sys

import pytest
from helpers import ROOT
from test_offpac_il import no_run_files

import harness
import offpac_il
from lab import baselines, experiments, sac, table


def one_line(capsys, *fragments: str) -> str:
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and err.startswith("error:"), err
    for fragment in fragments:
        assert fragment in err, (fragment, err)
    return err


@pytest.mark.parametrize(
    "main, argv",
    [
        (table.main, ["--tasks", "Hopper-v4"]),
        (experiments.main, ["evaluate", "RUN"]),
    ],
)
def test_a_negative_seed_is_one_line(capsys, main, argv):
    assert main([*argv, "--seed", "-1"]) == 2
    one_line(capsys, "--seed")


def test_lab_render_refuses_a_negative_seed(capsys):
    from lab import render

    assert render.main(["RUN", "--seed", "-1"]) == 2
    one_line(capsys, "--seed")


@pytest.mark.parametrize(
    "flags, message",
    [
        (["--replay-size", "1e12"], "--replay-size"),
        (["--critic-hidden", "100000", "100000"], "--critic-hidden"),
        (["--noise-samples", "1e10"], "--noise-samples"),
        (["--batch-size", "1e9"], "--batch-size"),
        (["--target-samples", "1e9"], "--target-samples"),
        (["--eval-episodes", "1e12"], "--eval-episodes must lie in"),
    ],
)
def test_sizes_that_cannot_fit_in_memory_are_refused_before_anything_is_written(
    tmp_path, capsys, flags, message
):
    run_dir = tmp_path / "run"
    assert offpac_il.main([*flags, "--run-dir", str(run_dir)]) == 2
    one_line(capsys, message)
    assert no_run_files(run_dir)


@pytest.mark.parametrize(
    "edit, message",
    [
        (lambda c: [c], "does not hold settings"),
        (lambda c: None, "does not hold settings"),
        (lambda c: {**c, "seed": "zero"}, "seed must be a whole number"),
        (lambda c: {**c, "seed": 0.5}, "seed must be a whole number"),
        (lambda c: {**c, "policy_hidden": "abc"}, "policy_hidden must be a list"),
        (lambda c: {**c, "policy_hidden": 16}, "policy_hidden must be a list"),
        (lambda c: {**c, "policy_hidden": [[16], [16]]}, "policy_hidden must be a list"),
        (lambda c: {**c, "policy_lr": "fast"}, "policy_lr must be a number"),
        (lambda c: {**c, "batch_size": True}, "batch_size must be a whole number"),
        (lambda c: {**c, "noise_samples": 2.5}, "noise_samples must be a whole number"),
        (lambda c: {**c, "total_steps": "300"}, "total_steps must be a whole number"),
        (lambda c: {**c, "total_steps": None}, "total_steps must be a whole number"),
        (lambda c: {**c, "noise_samples": 0}, "--noise-samples must lie in"),
    ],
)
def test_a_hand_edited_config_is_refused_in_one_line(tmp_path, capsys, edit, message):
    run_dir = tmp_path / "run"
    saved = {harness.PROGRAM: offpac_il.Config.program, **offpac_il.Config().__dict__}
    harness.write_text(run_dir / harness.CONFIG, json.dumps(edit(saved)))
    assert offpac_il.main(["--resume", str(run_dir)]) == 2
    one_line(capsys, message)
    assert {p.name for p in run_dir.iterdir()} <= {harness.CONFIG, harness.LOCK}


def test_a_run_made_with_a_removed_setting_is_not_resumed_without_it(tmp_path, capsys):
    """--policy-entropy left the code; a run made with it on would be silently changed by
    a resume that dropped it, so it is refused, naming the commit that still has it. A
    run that had it off resumes as before (here: up to its missing checkpoint)."""
    run_dir = tmp_path / "run"
    saved = {harness.PROGRAM: offpac_il.Config.program, **offpac_il.Config().__dict__}
    harness.write_text(run_dir / harness.CONFIG, json.dumps({**saved, "policy_entropy": 0.1}))
    assert offpac_il.main(["--resume", str(run_dir)]) == 2
    one_line(capsys, "was made with --policy-entropy 0.1, a setting this code no longer has;")
    harness.write_text(run_dir / harness.CONFIG, json.dumps({**saved, "policy_entropy": 0.0}))
    assert offpac_il.main(["--resume", str(run_dir)]) == 2
    one_line(capsys, "checkpoint.npz is missing")


def test_lab_baselines_names_the_program_of_a_learner_run(tmp_path, capsys):
    run_dir = tmp_path / "run"
    harness.write_config(run_dir, {harness.PROGRAM: "python offpac_il.py", "env": "Hopper-v4"})
    harness.save_arrays(run_dir / harness.CHECKPOINT, {})
    assert baselines.main(["gail", "--resume", str(run_dir)]) == 2
    one_line(capsys, f"resume it with `python offpac_il.py --resume {run_dir}`")


def test_sac_and_learner_runs_are_each_resumed_by_their_own_program(tmp_path, capsys):
    """A SAC expert run, with or without the "program" key of newer runs, is refused by
    the learner, and a learner run by lab.sac, each naming the command that resumes it."""
    sac_run, learner_run = tmp_path / "sac", tmp_path / "learner"
    saved = {**dataclasses.asdict(sac.SACConfig(env="Hopper-v4")), "run_dir": str(sac_run)}
    for config in ({harness.PROGRAM: sac.SACConfig.program, **saved}, saved):
        harness.write_config(sac_run, config)
        assert offpac_il.main(["--resume", str(sac_run)]) == 2
        one_line(capsys, f"resume it with `python -m lab.sac --resume {sac_run}`")
    harness.write_config(learner_run, {harness.PROGRAM: offpac_il.Config.program})
    assert sac.main(["--resume", str(learner_run)]) == 2
    one_line(capsys, f"resume it with `python offpac_il.py --resume {learner_run}`")


def test_lab_render_without_a_gl_back_end_is_one_line(tmp_path):
    run_dir = tmp_path / "run"
    harness.write_config(run_dir, {"env": "Hopper-v4"})
    result = subprocess.run(
        [sys.executable, "-m", "lab.render", str(run_dir), "--out", str(tmp_path / "p.gif")],
        capture_output=True,
        text=True,
        cwd=ROOT,
        env={**os.environ, "MUJOCO_GL": ""},
        timeout=120,
    )
    assert result.returncode == 2
    assert len(result.stderr.strip().splitlines()) == 1, result.stderr
    assert "MuJoCo cannot render offscreen" in result.stderr


def test_lab_table_checks_out_before_measuring(tmp_path, capsys, monkeypatch):
    monkeypatch.setattr(table, "measure_table", lambda *a, **k: pytest.fail("measured"))
    listed = tmp_path / "list.json"
    listed.write_text("[1, 2]")
    assert table.main(["--tasks", "Hopper-v4", "--out", str(listed)]) == 2
    one_line(capsys, "not a valid table")
    assert table.main(["--tasks", "Hopper-v4", "--out", str(tmp_path)]) == 2
    one_line(capsys, "is a directory")


def test_lab_experiments_checks_its_arguments_first(tmp_path, capsys):
    """curves to a non-PNG file or onto a directory, hold with --until below --since, and a
    sweep whose --envs match no run of the plan: one line, status 2, nothing written."""
    run = tmp_path / "run"
    run.mkdir()
    (run / "progress.csv").write_text("interactions,normalized_score\n5000,0.5\n")
    folder = tmp_path / "folder"
    folder.mkdir()
    cases = [
        (["curves", str(tmp_path / "out.txt"), str(run)], "must be a .png file"),
        (["curves", str(folder), str(run)], "is a directory"),
        (["hold", str(run), "--until", "-10"], "0 <= since <= until"),
        (["sweep", "quick", "--envs", "NotAnEnv-v0", "--runs", str(tmp_path / "sweep")],
         "the plan's tasks are"),
    ]  # fmt: skip
    for argv, fragment in cases:
        assert experiments.main(argv) == 2, argv
        one_line(capsys, fragment)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["folder", "run"]
    assert not any(folder.iterdir())
