"""harness.py, the run plumbing every trainer shares, tested once: atomic files, the
command line made from a dataclass, the run directory and its lock, checkpoints and
exact resume, progress rows, the clock, signals and one-line errors. Then the learner's
command line refusing what cannot work: one line on stderr, exit status 2, nothing
written."""

from __future__ import annotations

import argparse
import dataclasses
import errno
import json
import math
import os
import shutil
import signal
import subprocess
import sys
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest
from helpers import ROOT, assert_one_line_error, read_rows, release, run_script
from test_offpac_il import tiny_config

import harness
import offpac_il
from harness import UserError

# ----------------------------------------------------------------------------------------
# Files, written atomically.
# ----------------------------------------------------------------------------------------


def some_arrays(seed: int) -> dict[str, np.ndarray]:
    rng = np.random.default_rng(seed)
    return {
        "critic/W0": rng.normal(size=(3, 5)).astype(np.float32),
        "replay/terminal": rng.random(4) < 0.5,
        "step": np.array(7),
    }


def test_save_and_load_round_trip(tmp_path):
    arrays = some_arrays(0)
    path = tmp_path / "nested" / "state.npz"
    harness.save_arrays(path, arrays)
    loaded = harness.load_arrays(path)
    assert set(loaded) == set(arrays)
    for key, value in arrays.items():
        assert loaded[key].dtype == value.dtype
        np.testing.assert_array_equal(loaded[key], value)
    assert [p.name for p in path.parent.iterdir()] == ["state.npz"]  # no temporary left
    assert path.stat().st_mode & 0o777 == 0o644  # readable by others, as results are shared
    harness.write_text(tmp_path / "a.txt", "one\n")
    harness.write_text(tmp_path / "a.txt", "two\n")
    assert (tmp_path / "a.txt").read_text() == "two\n"


def test_failed_save_leaves_previous_file_intact(tmp_path, monkeypatch):
    path = tmp_path / "state.npz"
    first = some_arrays(0)
    harness.save_arrays(path, first)

    def failing_savez(file, **arrays):
        file.write(b"half a file")
        raise OSError("disk full")

    with monkeypatch.context() as patch:
        patch.setattr(np, "savez", failing_savez)
        with pytest.raises(OSError, match="disk full"):
            harness.save_arrays(path, some_arrays(1))

    assert [p.name for p in tmp_path.iterdir()] == ["state.npz"]  # no temporary left
    loaded = harness.load_arrays(path)
    for key, value in first.items():
        np.testing.assert_array_equal(loaded[key], value)


def test_a_write_interrupted_before_its_rename_leaves_no_temporary(tmp_path, monkeypatch):
    """Ctrl-C (KeyboardInterrupt, not an Exception) between the write and the rename:
    the old file stays, the temporary goes."""
    path = tmp_path / "progress.csv"
    harness.write_text(path, "old\n")

    def interrupted(source, target):
        assert Path(source).exists() and Path(source).parent == tmp_path  # written beside
        raise KeyboardInterrupt

    with monkeypatch.context() as patch:
        patch.setattr(harness.os, "replace", interrupted)
        with pytest.raises(KeyboardInterrupt):
            harness.write_text(path, "new\n")
    assert [p.name for p in tmp_path.iterdir()] == ["progress.csv"]
    assert path.read_text() == "old\n"


def test_writing_where_no_file_can_be_is_a_user_error(tmp_path):
    (tmp_path / "a_file").write_text("")
    with pytest.raises(UserError, match="a parent of it is a file"):
        harness.write_text(tmp_path / "a_file" / "x.txt", "")
    with pytest.raises(UserError, match="is a directory"):
        harness.save_arrays(tmp_path, some_arrays(0))
    assert [p.name for p in tmp_path.iterdir()] == ["a_file"]


def damaged(tmp_path: Path, kind: str) -> Path:
    """A file that is not a readable .npz, of one kind."""
    path = tmp_path / "state.npz"
    harness.save_arrays(path, some_arrays(0))
    data = path.read_bytes()
    if kind == "truncated":
        path.write_bytes(data[: len(data) // 2])
    elif kind == "corrupted":  # 8 bytes flipped inside the first array's data
        flipped = bytearray(data)
        start = data.index(b"\x93NUMPY") + 130  # past the .npy header of 128 bytes
        flipped[start : start + 8] = bytes(b ^ 0xFF for b in data[start : start + 8])
        path.write_bytes(bytes(flipped))
    elif kind == "text":
        path.write_text("interactions,updates\n0,0\n")
    elif kind == "empty":
        path.write_bytes(b"")
    elif kind == "npy":
        path = tmp_path / "state.npy"
        np.save(path, np.zeros(3))
    elif kind == "pickled":
        np.savez(path, objects=np.array([{"a": 1}], dtype=object))
    return path


@pytest.mark.parametrize("kind", ["truncated", "corrupted", "text", "empty", "npy", "pickled"])
def test_load_arrays_of_a_damaged_file_is_a_user_error_naming_it(tmp_path, kind):
    path = damaged(tmp_path, kind)
    with pytest.raises(UserError, match=str(path)):
        harness.load_arrays(path)


def test_load_arrays_of_a_missing_file_is_a_user_error_naming_it(tmp_path):
    with pytest.raises(UserError, match=f"{tmp_path / 'absent.npz'}: no such file"):
        harness.load_arrays(tmp_path / "absent.npz")


# ----------------------------------------------------------------------------------------
# The command line made from a dataclass.
# ----------------------------------------------------------------------------------------


@dataclass
class Settings:
    """A trainer's hyperparameters."""

    rate: float = 0.5
    """The rate."""
    sizes: tuple[int, ...] = (3, 4)
    """Layer sizes."""
    verbose: bool = False
    """Talk more."""
    name: str = "x"
    """A name."""


@dataclass
class MoreSettings(Settings):
    steps: int = 10
    """The budget."""


def settings_parser(cls=MoreSettings) -> argparse.ArgumentParser:
    parser = harness.CommandLineParser(prog="trainer")
    harness.add_dataclass_flags(parser, cls)
    return parser


def test_flags_are_made_from_the_dataclass_with_its_docstrings():
    parser = settings_parser()
    args = parser.parse_args(["--rate", "0.1", "--sizes", "5", "6", "--verbose", "--steps", "3"])
    config = harness.config_from_args(MoreSettings, args)
    assert config == MoreSettings(rate=0.1, sizes=(5, 6), verbose=True, name="x", steps=3)
    assert harness.config_from_args(MoreSettings, parser.parse_args([])) == MoreSettings()
    assert not harness.config_from_args(MoreSettings, parser.parse_args(["--no-verbose"])).verbose
    text = parser.format_help()
    for doc in ("The rate.", "Layer sizes.", "Talk more.", "The budget."):  # inherited too
        assert doc in text


def test_a_bad_flag_is_one_line_and_exit_2(capsys):
    with pytest.raises(SystemExit) as exit:
        settings_parser().parse_args(["--bogus"])
    assert exit.value.code == 2
    assert (
        capsys.readouterr().err == "error: unrecognized arguments: --bogus (see trainer --help)\n"
    )


def test_counts_may_be_written_as_3e5_but_must_be_whole():
    parser = settings_parser()
    assert parser.parse_args(["--steps", "3e5"]).steps == 300_000
    assert harness.whole_number("12") == 12 and harness.positive_int("7e6") == 7_000_000
    for bad in ("2.5", "many"):
        with pytest.raises((argparse.ArgumentTypeError, ValueError)):
            harness.whole_number(bad)
    with pytest.raises(argparse.ArgumentTypeError, match="at least 1"):
        harness.positive_int("0")


RANGES = {
    "rate": (0, math.inf, "()"),
    "steps": (1, math.inf, "[)"),
    "sizes": (1, 10, "[]"),
}


@pytest.mark.parametrize(
    "changes, message",
    [
        ({"rate": math.nan}, "--rate must be a finite number, got nan"),
        ({"rate": math.inf}, "--rate must be a finite number, got inf"),
        ({"rate": -math.inf}, "--rate must be a finite number"),
        ({"rate": 0.0}, r"--rate must lie in \(0, inf\)"),
        ({"rate": -1.0}, r"--rate must lie in \(0, inf\)"),
        ({"steps": 0}, r"--steps must lie in \[1, inf\)"),
        ({"sizes": (4, 0)}, r"--sizes must lie in \[1, 10\]"),
        ({"sizes": (11,)}, r"--sizes must lie in \[1, 10\]"),
    ],
)
def test_check_numbers_refuses_non_finite_and_out_of_range(changes, message):
    with pytest.raises(UserError, match=message):
        harness.check_numbers(dataclasses.replace(MoreSettings(), **changes), RANGES)


def test_check_numbers_allows_the_ends_its_ranges_include():
    for changes in ({"steps": 1}, {"sizes": (1, 10)}, {"rate": 1e-300}, {"verbose": True}):
        harness.check_numbers(dataclasses.replace(MoreSettings(), **changes), RANGES)
    for kind, low_ok, high_ok in (("[]", True, True), ("(]", False, True), ("[)", True, False)):
        for value, ok in ((0.0, low_ok), (1.0, high_ok), (0.5, True)):
            config = dataclasses.replace(MoreSettings(), rate=value)
            if ok:
                harness.check_numbers(config, {"rate": (0, 1, kind)})
            else:
                with pytest.raises(UserError, match="--rate"):
                    harness.check_numbers(config, {"rate": (0, 1, kind)})
    with pytest.raises(UserError, match="--steps must be a finite"):  # unranged: still finite
        harness.check_numbers(dataclasses.replace(MoreSettings(), steps=math.inf), {})


def test_check_choices_and_check_finite_name_what_is_wrong():
    harness.check_choices(MoreSettings(), {"name": ("x", "y")})
    with pytest.raises(UserError, match="--name must be one of y, z"):
        harness.check_choices(MoreSettings(), {"name": ("y", "z")})
    harness.check_finite({"critic/W0": np.ones(3)}, "by 10 interactions")
    with pytest.raises(
        UserError, match="critic/W1 became non-finite by 10 interactions; the last checkpoint"
    ):
        harness.check_finite(
            {"critic/W0": np.ones(3), "critic/W1": np.array([0.0, np.inf])}, "by 10 interactions"
        )
    assert harness.shown(None, ".3f") == harness.shown("", ".3f") == "-"
    assert harness.shown(0.12345, ".3f") == "0.123"


def command_line(argv, paper=None, may_change=("steps",)):
    return harness.config_from_command_line(
        [str(a) for a in argv], MoreSettings, "", paper or {"rate": 0.25}, may_change
    )


def test_paper_values_become_the_defaults_and_flags_given_win():
    assert command_line([]) == (MoreSettings(), False)
    assert command_line(["--paper"])[0].rate == 0.25
    assert command_line(["--rate", "0.7", "--paper"])[0].rate == 0.7


def test_resume_takes_the_saved_settings_and_refuses_a_conflicting_flag(tmp_path):
    saved = dataclasses.asdict(MoreSettings(rate=0.1, sizes=(7,)))
    harness.write_config(tmp_path, saved)
    config, resume = command_line(["--resume", tmp_path])
    assert resume and config == MoreSettings(rate=0.1, sizes=(7,))
    config, _ = command_line(["--resume", tmp_path, "--steps", "99", "--sizes", "7"])
    assert config == MoreSettings(rate=0.1, sizes=(7,), steps=99)
    with pytest.raises(UserError, match="--rate conflicts with the saved run"):
        command_line(["--resume", tmp_path, "--rate", "0.2"])
    with pytest.raises(UserError, match="--paper cannot be combined with --resume"):
        command_line(["--resume", tmp_path, "--paper"])
    with pytest.raises(UserError, match="holds no run"):
        command_line(["--resume", tmp_path / "absent"])


def test_resumed_settings_refuses_a_conflicting_flag_and_allows_the_listed_ones():
    saved = {"env": "Hopper-v4", "total_steps": 300, "policy_hidden": [8, 8], "seed": 0}
    allowed = offpac_il.RESUMABLE_CHANGES
    changed = {"total_steps": 600, "eval_every": 7, "checkpoint_every": 1.0, "log_every": 2.0}
    assert set(changed) == set(allowed)
    assert harness.resumed_settings(saved, changed, allowed) == {**saved, **changed}
    # Flags given with the saved values are no conflict (tuples as lists, as in JSON).
    same = {"env": "Hopper-v4", "policy_hidden": (8, 8), "seed": 0}
    assert harness.resumed_settings(saved, same, allowed) == saved
    for name, value in (("env", "Walker2d-v4"), ("policy_hidden", (8, 9)), ("seed", 1)):
        with pytest.raises(UserError) as error:
            harness.resumed_settings(saved, {name: value}, allowed)
        message = str(error.value)
        assert message.startswith(f"{harness.flag(name)} conflicts with the saved run")
        assert "--total-steps, --eval-every, --checkpoint-every, --log-every" in message


def test_saved_config_fills_missing_settings_from_the_paper_and_drops_unknown_ones():
    saved = {"rate": 0.1, "sizes": [5], "removed_setting": 3.0}
    config = harness.saved_config(MoreSettings, saved, {"steps": 42})
    assert config == MoreSettings(rate=0.1, sizes=(5,), steps=42)


# ----------------------------------------------------------------------------------------
# The run directory and its lock.
# ----------------------------------------------------------------------------------------


def test_open_run_dir_creates_and_locks_a_fresh_directory(tmp_path):
    run_dir = harness.open_run_dir(tmp_path / "runs" / "a", resume=False)
    assert run_dir == tmp_path / "runs" / "a" and (run_dir / harness.LOCK).is_file()
    assert harness.open_run_dir(run_dir, resume=False) == run_dir  # this process: again fine


def test_a_fresh_run_over_a_checkpoint_is_refused(tmp_path):
    (tmp_path / harness.CHECKPOINT).write_bytes(b"a run")
    with pytest.raises(UserError, match=f"{tmp_path} already holds a run; continue it with"):
        harness.open_run_dir(tmp_path, resume=False)
    assert (tmp_path / harness.CHECKPOINT).read_bytes() == b"a run"


@pytest.mark.parametrize("missing", [harness.CONFIG, harness.PROGRESS, harness.CHECKPOINT])
def test_a_resume_without_each_run_file_is_refused(tmp_path, missing):
    for name in (harness.CONFIG, harness.PROGRESS, harness.CHECKPOINT):
        if name != missing:
            (tmp_path / name).write_text("x")
    with pytest.raises(UserError, match=f"cannot be resumed: its {missing} is missing"):
        harness.open_run_dir(tmp_path, resume=True)
    with pytest.raises(UserError, match="holds no run"):
        harness.open_run_dir(tmp_path / "absent", resume=True)
    assert not (tmp_path / "absent").exists()


def test_a_run_dir_that_is_a_file_or_lies_under_one_is_refused(tmp_path):
    a_file = tmp_path / "a_file"
    a_file.write_text("keep")
    with pytest.raises(UserError, match="is a file, not a directory"):
        harness.open_run_dir(a_file, resume=False)
    with pytest.raises(UserError, match="lies under a file"):
        harness.open_run_dir(a_file / "run", resume=False)
    assert a_file.read_text() == "keep"


def test_a_run_dir_that_is_not_writable_is_refused(tmp_path):
    locked = tmp_path / "read_only"
    locked.mkdir()
    locked.chmod(0o500)
    try:
        if os.access(locked, os.W_OK):
            pytest.skip("this user (root) may write into a read-only directory")
        with pytest.raises(UserError, match="not writable|permission denied"):
            harness.open_run_dir(locked, resume=False)
        with pytest.raises(UserError, match="permission denied"):
            harness.open_run_dir(locked / "run", resume=False)
    finally:
        locked.chmod(0o700)


# A process that opens a run directory and holds it until its stdin closes.
HOLDER = (
    "import sys, harness\n"
    "def body():\n"
    "    harness.open_run_dir(sys.argv[1], resume=False)\n"
    "    print('locked', flush=True)\n"
    "    sys.stdin.read()\n"
    "sys.exit(harness.run_cli(body))\n"
)


def holder(run_dir: Path) -> subprocess.Popen:
    return subprocess.Popen(
        [sys.executable, "-c", HOLDER, str(run_dir)],
        cwd=ROOT,
        stdin=subprocess.PIPE,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )


def test_two_processes_started_together_on_one_run_dir_one_is_refused(tmp_path):
    run_dir = tmp_path / "run"
    processes = [holder(run_dir), holder(run_dir)]
    try:
        deadline = time.time() + 120
        while all(p.poll() is None for p in processes) and time.time() < deadline:
            time.sleep(0.02)
        outputs = [p.communicate(input="", timeout=60) for p in processes]
        results = [(p.returncode, *output) for p, output in zip(processes, outputs, strict=True)]
    finally:
        for p in processes:
            if p.poll() is None:
                p.kill()
                p.wait()
    assert sorted(code for code, _, _ in results) == [0, 2], results
    (_, out_winner, err_winner), (_, out_loser, err_loser) = sorted(
        results, key=lambda r: r[0] != 0
    )
    assert out_winner == "locked\n" and err_winner == ""
    assert out_loser == ""
    assert err_loser == f"error: {run_dir} is in use by another running process\n"


def test_a_lock_left_by_a_killed_process_does_not_block_a_new_run(tmp_path):
    run_dir = tmp_path / "run"
    process = holder(run_dir)
    try:
        assert process.stdout.readline() == "locked\n"
        with pytest.raises(UserError, match="in use by another running process"):
            harness.open_run_dir(run_dir, resume=False)  # while it lives
        process.kill()  # kill -9: no clean-up in the process, the lock file stays
        process.wait()
    finally:
        if process.poll() is None:
            process.kill()
            process.wait()
    assert (run_dir / harness.LOCK).exists()
    assert harness.open_run_dir(run_dir, resume=False) == run_dir


# ----------------------------------------------------------------------------------------
# Checkpoints: exact resume.
# ----------------------------------------------------------------------------------------

FIELDS = ("interactions", "eval_return_mean")


def a_progress() -> harness.Progress:
    return harness.Progress(
        interactions=301,
        updates=300,
        episodes=21,
        eval_rounds=2,
        wall_seconds=26.25,
        best_eval_return=6.12,
        recent_returns=[1.5, 2.25],
        last_stats={"q_expert": 0.53},
        rows=[{"interactions": 0, "eval_return_mean": 5.23, "extra": ""}],
    )


def test_a_checkpoint_restores_the_generator_and_counters_exactly(tmp_path):
    rng = np.random.default_rng(5)
    rng.standard_normal(3)  # somewhere along its stream
    arrays = some_arrays(0)
    progress = a_progress()
    harness.save_checkpoint(tmp_path, arrays, rng, progress, FIELDS)
    following = rng.standard_normal(4)

    restored_rng, loaded = np.random.default_rng(99), {}
    restored = harness.load_checkpoint(tmp_path, restored_rng, loaded.update)
    assert restored == progress
    np.testing.assert_array_equal(restored_rng.standard_normal(4), following)
    assert set(loaded) == set(arrays)
    for key, value in arrays.items():
        assert loaded[key].dtype == value.dtype
        np.testing.assert_array_equal(loaded[key], value)
    assert (tmp_path / harness.PROGRESS).read_text() == (
        "interactions,eval_return_mean,extra\n0,5.23,\n"
    )
    # A fresh run's -inf best return survives JSON too; so does a trainer's own Progress.
    harness.save_checkpoint(tmp_path, {}, rng, harness.Progress(), FIELDS)
    assert harness.load_checkpoint(tmp_path, rng, lambda a: None).best_eval_return == -math.inf

    @dataclass
    class StepsProgress(harness.Progress):
        env_steps: int = 0

    harness.save_checkpoint(tmp_path, {}, rng, StepsProgress(env_steps=17), FIELDS)
    back = harness.load_checkpoint(tmp_path, rng, lambda a: None, StepsProgress)
    assert back == StepsProgress(env_steps=17)


def test_a_checkpoint_of_another_version_is_a_user_error_and_changes_nothing(tmp_path):
    rng = np.random.default_rng(5)
    harness.save_checkpoint(tmp_path, some_arrays(0), rng, a_progress(), FIELDS)
    path = tmp_path / harness.CHECKPOINT

    def needs_a_network(arrays):
        arrays["policy/W0"]  # a network this checkpoint does not hold

    untouched = np.random.default_rng(7)
    with pytest.raises(UserError, match=f"{path}: not a checkpoint of this run or version"):
        harness.load_checkpoint(tmp_path, untouched, needs_a_network)
    assert untouched.standard_normal() == np.random.default_rng(7).standard_normal()

    arrays = harness.load_arrays(path)
    del arrays["counters"]
    harness.save_arrays(path, arrays)
    with pytest.raises(UserError, match=str(path)):
        harness.load_checkpoint(tmp_path, rng, lambda a: None)


def test_a_checkpoint_whose_counters_this_version_does_not_have_is_a_user_error(tmp_path):
    rng = np.random.default_rng(5)
    harness.save_checkpoint(tmp_path, {}, rng, a_progress(), FIELDS)
    path = tmp_path / harness.CHECKPOINT
    arrays = harness.load_arrays(path)
    counters = json.loads(str(arrays["counters"]))
    arrays["counters"] = np.array(json.dumps({**counters, "iteration": 4}))  # e.g. ARS's
    harness.save_arrays(path, arrays)
    with pytest.raises(UserError, match=str(path)):
        harness.load_checkpoint(tmp_path, rng, lambda a: None)


# ----------------------------------------------------------------------------------------
# Progress rows and the clock.
# ----------------------------------------------------------------------------------------


def test_evaluation_is_due_at_0_past_each_every_and_at_the_end_once():
    progress = harness.Progress()
    due = []
    for interactions in (0, 0, 60, 99, 130, 130, 199, 230, 290, 310, 310):
        progress.interactions = interactions
        if progress.evaluation_due(100, 300):
            progress.record(np.array([1.0]), 0.0, {}, FIELDS)
            due.append(interactions)
    assert due == [0, 130, 230, 310]  # 310: the end (the last episode ran past 300)
    assert progress.eval_rounds == 4
    # A finished run that is resumed adds no second final row.
    assert not progress.evaluation_due(100, 300)
    # Another counter (the updates of a trainer that counts them).
    progress = harness.Progress(updates=250, eval_rounds=2, rows=[{"updates": 100}])
    assert progress.evaluation_due(100, 1000, counter="updates")
    assert not progress.evaluation_due(300, 1000, counter="updates")


def test_record_appends_a_row_of_the_counters_and_the_measurements():
    progress = harness.Progress(interactions=301, updates=300, episodes=21, wall_seconds=26.24)
    progress.recent_returns[:] = [10.0, 11.5]
    fields = (*offpac_il.PROGRESS_FIELDS[:8], "q_expert", "critic_loss", "eval_falls")
    measured = {"q_expert": 0.535342, "eval_falls": 2, "not_a_field": 1.0}
    row = progress.record(np.array([6.0, 6.25]), 0.123456, measured, fields)
    assert row == {
        "interactions": 301,
        "wall_seconds": 26.2,
        "updates": 300,
        "episodes": 21,
        "eval_return_mean": 6.12,
        "eval_return_std": 0.12,
        "normalized_score": 0.1235,
        "train_return": 10.75,
        "q_expert": 0.53534,  # 5 significant digits
        "critic_loss": "",  # no value yet
        "eval_falls": 2,  # counts stay counts
    }
    assert progress.rows == [row] and progress.eval_rounds == 1
    assert progress.recent_returns == []  # the next row's training returns start afresh
    assert progress.record(np.array([1.0]), 0.0, {}, fields)["train_return"] == ""


class FakeTime:
    """time.perf_counter as the test sets it."""

    def __init__(self, now: float):
        self.now = now

    def perf_counter(self) -> float:
        return self.now


def test_clock_eta_uses_this_process_pace_and_is_never_negative(monkeypatch):
    fake = FakeTime(50.0)
    monkeypatch.setattr(harness, "time", fake)
    # Resumed at 200 000 interactions after 1000 s: earlier sessions' pace is not used.
    progress = harness.Progress(interactions=200_000, wall_seconds=1000.0)
    clock = harness.Clock(progress, checkpoint_every=60.0, log_every=10.0)
    assert math.isnan(clock.eta_minutes(206_000))  # no progress in this process yet
    fake.now, progress.interactions = 150.0, 201_000  # 1 000 more in 100 s: 10 per second
    assert clock.eta_minutes(206_000) == pytest.approx(5_000 / 10 / 60)
    progress.interactions = 206_300  # the last episode ran past the budget
    assert clock.eta_minutes(206_000) == 0.0
    clock.tick()
    assert progress.wall_seconds == pytest.approx(1100.0)  # the wall time carries over


def test_clock_paces_logs_and_checkpoints(monkeypatch):
    fake = FakeTime(0.0)
    monkeypatch.setattr(harness, "time", fake)
    clock = harness.Clock(harness.Progress(), checkpoint_every=60.0, log_every=10.0)
    assert not clock.log_due() and not clock.checkpoint_due()
    fake.now = 10.0
    assert clock.log_due() and not clock.log_due()  # once per period
    fake.now = 60.0
    assert clock.checkpoint_due()
    clock.checkpointed()
    assert not clock.checkpoint_due()


# ----------------------------------------------------------------------------------------
# Signals and one-line errors.
# ----------------------------------------------------------------------------------------


def test_a_signal_asks_for_a_checkpoint_and_a_second_one_stops_at_once(capsys):
    before = signal.getsignal(signal.SIGTERM)
    clock = harness.Clock(harness.Progress(), checkpoint_every=1e9, log_every=1e9)
    with harness.stop_at_next_checkpoint():
        assert not clock.checkpoint_due()
        harness.stop_if_requested()  # nothing asked yet
        os.kill(os.getpid(), signal.SIGTERM)
        time.sleep(0.01)  # the handler runs in the main thread, between bytecodes
        assert clock.checkpoint_due()  # the signal asked for a checkpoint
        with pytest.raises(KeyboardInterrupt):
            harness.stop_if_requested()
        with pytest.raises(KeyboardInterrupt):
            os.kill(os.getpid(), signal.SIGINT)
            time.sleep(0.01)
    assert signal.getsignal(signal.SIGTERM) is before  # handlers restored
    assert not clock.checkpoint_due()  # request forgotten
    assert "stopping at the next checkpoint" in capsys.readouterr().err


def raises(error: BaseException):
    def body():
        raise error

    return body


@pytest.mark.parametrize(
    "error, status, line",
    [
        (UserError("--tau must lie in (0, 1]"), 2, "error: --tau must lie in (0, 1]"),
        (KeyboardInterrupt(), 130, "interrupted before the run started, nothing written"),
        (
            OSError(errno.ENOSPC, "No space left on device", "/r/checkpoint.npz"),
            2,
            "error: disk full writing /r/checkpoint.npz; the last checkpoint is kept,"
            " free space and --resume",
        ),
        (OSError(errno.EDQUOT, "Disk quota exceeded"), 2, "error: disk full; the last"),
    ],
)
def test_run_cli_turns_errors_a_user_can_cause_into_one_line(capsys, error, status, line):
    assert harness.run_cli(raises(error)) == status
    captured = capsys.readouterr()
    assert captured.err.count("\n") == 1 and captured.err.startswith(line)
    assert captured.out == ""


def test_run_cli_passes_other_errors_on_and_runs_blas_on_one_thread(capsys):
    with pytest.raises(OSError, match="Permission denied"):
        harness.run_cli(raises(OSError(errno.EACCES, "Permission denied")))
    with pytest.raises(ZeroDivisionError):
        harness.run_cli(raises(ZeroDivisionError()))
    from threadpoolctl import threadpool_info

    seen = []
    assert harness.run_cli(lambda: seen.extend(threadpool_info())) == 0
    assert all(pool["num_threads"] == 1 for pool in seen if pool["user_api"] == "blas")


def test_cli_main_gives_help_and_bad_flags_their_status(capsys):
    def parse(argv):
        return settings_parser().parse_args(argv)

    ran = []
    assert harness.cli_main(["--rate", "2"], parse, lambda args, argv: ran.append(args.rate)) == 0
    assert ran == [2.0]
    assert harness.cli_main(["--help"], parse, lambda args, argv: None) == 0
    assert "The rate." in capsys.readouterr().out
    assert harness.cli_main(["--bogus"], parse, lambda args, argv: None) == 2
    assert capsys.readouterr().err.count("\n") == 1

    def refuses(args, argv):
        raise UserError("no such task")

    assert harness.cli_main([], parse, refuses) == 2
    assert capsys.readouterr().err == "error: no such task\n"


def test_cli_main_without_checkpoints_stops_at_once_on_a_signal(capsys):
    """A command with nothing to resume: the first signal ends it, status 130."""
    before = signal.getsignal(signal.SIGTERM)

    def long_command(args, argv):
        os.kill(os.getpid(), signal.SIGTERM)
        time.sleep(5)  # interrupted at once, not at a checkpoint that never comes
        raise AssertionError("the signal did not stop the command")

    started = time.time()
    status = harness.cli_main([], lambda argv: None, long_command, checkpoints=False)
    assert status == 130 and time.time() - started < 4
    assert capsys.readouterr().err.strip().splitlines()[-1] == "interrupted"
    assert signal.getsignal(signal.SIGTERM) is before


# ----------------------------------------------------------------------------------------
# The big passes' row chunks.
# ----------------------------------------------------------------------------------------


@pytest.mark.parametrize(
    "n_states, rows_per_state", [(64, 128), (64, 8), (6, 4), (1, 128), (3, 5000)]
)
def test_map_row_chunks_covers_every_state_once_in_order(n_states, rows_per_state):
    def slow(rows: slice):  # early chunks finish last
        time.sleep(0.002 * (n_states - rows.start) / n_states)
        return rows

    chunks = harness.map_row_chunks(slow, n_states, rows_per_state)
    assert chunks[0].start == 0 and chunks[-1].stop == n_states
    assert all(a.stop == b.start for a, b in zip(chunks, chunks[1:], strict=False))
    largest = max(1, harness.CHUNK_ROWS // rows_per_state)
    assert all(0 < c.stop - c.start <= largest for c in chunks)
    assert len(chunks) >= min(n_states, os.cpu_count() or 1)  # every core gets work


# ----------------------------------------------------------------------------------------
# The learner's command line: what cannot work is one line on stderr, exit status 2,
# and nothing written.
# ----------------------------------------------------------------------------------------


@pytest.mark.parametrize(
    "flags, says",
    [
        (["--policy-lr", "-1"], r"--policy-lr must lie in (0, inf)"),
        (["--policy-lr", "nan"], "--policy-lr must be a finite number"),
        (["--policy-lr", "inf"], "--policy-lr must be a finite number"),
        (["--tau", "2"], "--tau must lie in (0, 1]"),
        (["--rmsprop-decay", "1.5"], "--rmsprop-decay must lie in [0, 1)"),
        (["--rmsprop-eps", "0"], "--rmsprop-eps must lie in (0, inf)"),
        (["--checkpoint-every", "-1"], "--checkpoint-every must lie in [0, inf)"),
        (["--policy-hidden", "0", "16"], "--policy-hidden needs layer sizes of at least 1"),
        (["--critic-hidden", "-4"], "--critic-hidden needs layer sizes of at least 1"),
        (["--seed", "-1"], "--seed must lie in [0, 9.22337e+18]"),
        (["--eval-episodes", "0"], "--eval-episodes must lie in [1, 100000]"),
    ],
)
def test_a_setting_that_cannot_work_is_refused_before_anything_is_written(
    tmp_path, capsys, flags, says
):
    run_dir = tmp_path / "run"
    assert offpac_il.main([*flags, "--run-dir", str(run_dir)]) == 2
    captured = capsys.readouterr()
    assert captured.err.startswith(f"error: {says}") and captured.err.count("\n") == 1
    assert captured.out == ""
    assert not run_dir.exists()  # no directory, no config.json


def test_the_command_line_refuses_a_bad_setting_in_one_line():
    """The same through a real process: exit 2, one line, no traceback."""
    result = run_script(
        "offpac_il.py", "--policy-lr", "nan", "--run-dir", "/nonexistent/run", check=False
    )
    assert_one_line_error(result, "--policy-lr must be a finite number")


def test_a_run_dir_that_is_a_file_is_refused(tmp_path, capsys):
    a_file = tmp_path / "a_file"
    a_file.write_text("keep")
    assert offpac_il.main(["--run-dir", str(a_file)]) == 2
    assert capsys.readouterr().err == f"error: --run-dir {a_file} is a file, not a directory\n"
    assert a_file.read_text() == "keep"


def test_a_npy_file_as_demonstrations_is_refused(tmp_path):
    demos = tmp_path / "demos.npy"
    np.save(demos, np.zeros((3, 11)))
    result = run_script("offpac_il.py", "--demos", demos, "--run-dir", tmp_path / "r", check=False)
    assert_one_line_error(result, str(demos))
    assert not (tmp_path / "r" / harness.CONFIG).exists()


@pytest.fixture(scope="module")
def finished_run(tmp_path_factory, hopper_demos) -> Path:
    """A finished tiny learner run (300 interactions), made once for this module."""
    run_dir = tmp_path_factory.mktemp("finished") / "run"
    offpac_il.train(tiny_config(run_dir, hopper_demos))
    release(run_dir)
    return run_dir


def copy_of(run_dir: Path, tmp_path: Path) -> Path:
    copy = tmp_path / "run"
    shutil.copytree(run_dir, copy, ignore=shutil.ignore_patterns(harness.LOCK))
    config = json.loads((copy / harness.CONFIG).read_text())
    harness.write_config(copy, {**config, "run_dir": str(copy)})
    return copy


def test_resume_of_a_run_with_a_corrupted_checkpoint_is_refused(finished_run, tmp_path, capsys):
    run_dir = copy_of(finished_run, tmp_path)
    checkpoint = run_dir / harness.CHECKPOINT
    data = checkpoint.read_bytes()
    checkpoint.write_bytes(data[: len(data) // 2])
    files = {p.name: p.read_bytes() for p in run_dir.iterdir() if p.is_file()}
    assert offpac_il.main(["--resume", str(run_dir)]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and err.startswith(f"error: {checkpoint}: not a readable")
    after = {p.name: p.read_bytes() for p in run_dir.iterdir() if p.is_file()}
    assert after == {**files, harness.LOCK: after[harness.LOCK]}  # the checkpoint untouched


def test_resume_with_a_conflicting_setting_is_refused(finished_run, tmp_path, capsys):
    run_dir = copy_of(finished_run, tmp_path)
    progress = (run_dir / harness.PROGRESS).read_text()
    assert offpac_il.main(["--resume", str(run_dir), "--env", "Walker2d-v4"]) == 2
    err = capsys.readouterr().err
    assert err == (
        "error: --env conflicts with the saved run ('Hopper-v4'); a resume may change only:"
        " --total-steps, --eval-every, --checkpoint-every, --log-every\n"
    )
    assert (run_dir / harness.PROGRESS).read_text() == progress


def test_resume_with_a_new_budget_continues_the_run(finished_run, tmp_path):
    run_dir = copy_of(finished_run, tmp_path)
    before = read_rows(run_dir / harness.PROGRESS)
    result = run_script("offpac_il.py", "--resume", run_dir, "--total-steps", "450")
    assert f"resumed {run_dir} at {before[-1]['interactions']} interactions" in result.stdout
    after = read_rows(run_dir / harness.PROGRESS)
    assert after[: len(before)] == before and int(after[-1]["interactions"]) >= 450
