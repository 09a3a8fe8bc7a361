"""lab/table.py: measuring Table 1 (the random policy's and the shipped expert's returns),
its Markdown, and its command line (a SAC-format expert's row: tests/test_sac.py)."""

from __future__ import annotations

import json

import numpy as np
from helpers import run_module

import expert
from lab import table

PENDULUM = "InvertedPendulum-v4"  # obs (x, theta, x', theta'), one force in [-3, 3]


def test_shipped_hopper_expert_earns_its_return():
    returns = table.evaluate("Hopper-v4", expert.load_expert("Hopper-v4").act, episodes=1, seed=0)
    assert returns.shape == (1,) and returns[0] > 3000


def test_random_policy_returns_are_seeded():
    first = table.random_policy_returns(PENDULUM, episodes=3, seed=5)
    again = table.random_policy_returns(PENDULUM, episodes=3, seed=5)
    np.testing.assert_array_equal(first, again)
    assert first.shape == (3,) and np.all(first >= 1)  # each episode lasts a step at least


def test_measured_row_and_markdown(tmp_path, monkeypatch):
    monkeypatch.setattr(expert, "EXPERTS_DIR", tmp_path)  # no expert for the pendulum
    measured = table.measure_table(episodes=2, seed=0, tasks=(PENDULUM,), log=lambda _: None)
    row = measured[PENDULUM]
    assert (row["dim_s"], row["dim_a"], row["episodes"]) == (4, 1, 2)
    assert row["expert_mean"] is None and np.isfinite(row["random_mean"])
    markdown = table.table_markdown(measured)
    assert f"| {PENDULUM} | 4 | 1 |" in markdown and "missing (not trained yet)" in markdown


def test_command_line_writes_the_table(tmp_path):
    out = tmp_path / "table.json"
    result = run_module("lab.table", "--episodes", "1", "--out", out, check=False)
    # The five -v4 tasks, from the shipped experts: every row has an expert return.
    assert result.returncode == 0, result.stderr
    rows = json.loads(out.read_text())
    assert list(rows) == list(table.PAPER_TASKS)
    assert all(row["expert_mean"] is not None and row["episodes"] == 1 for row in rows.values())
    assert "| Hopper-v4 | 11 | 3 |" in result.stdout


def test_bad_flag_is_one_line_and_exit_2(tmp_path):
    result = run_module("lab.table", "--episodes", "0", "--out", tmp_path / "t.json", check=False)
    assert result.returncode == 2 and result.stderr.count("\n") == 1
    assert "--episodes" in result.stderr and list(tmp_path.iterdir()) == []
