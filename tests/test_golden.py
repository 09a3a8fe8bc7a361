"""The default learner reproduces tests/golden/hopper-v4-default-600.csv draw for draw.

The file was written by the code before the redesign (commit 54ada0e) with the same
command as below: the default settings on Hopper-v4, 600 interactions, evaluations
every 300 with 2 episodes, and the default demonstrations (4 sparse trajectories of the
shipped expert, seed 0; made the first time they are needed). Every column but
wall_seconds must match to the last printed digit: a refactoring that changes one draw
of the Generator, the order of a sum or a dtype shows up here.

BLAS kernels: matrix products may sum in a different order on another CPU (another
SIMD width) or another BLAS build, and the rows then differ in their last digits. The
rows are reproducible on one machine kind; after moving to another, regenerate the file
with the command below from commit 54ada0e, not from the code under test.
"""

from __future__ import annotations

from helpers import ROOT, read_rows, run_script

GOLDEN = ROOT / "tests" / "golden" / "hopper-v4-default-600.csv"
COMMAND = ("--env", "Hopper-v4", "--total-steps", "600", "--eval-every", "300")
COMMAND += ("--eval-episodes", "2")


def test_the_default_learner_reproduces_the_golden_run(tmp_path):
    run_dir = tmp_path / "run"
    run_script("offpac_il.py", *COMMAND, "--run-dir", run_dir)
    golden, rows = read_rows(GOLDEN), read_rows(run_dir / "progress.csv")
    assert [int(row["interactions"]) for row in golden] == [0, 301, 601]
    # The golden columns, in the same order; columns added since (handover, handover_score)
    # come after them and are checked by their own tests.
    assert list(rows[0])[: len(golden[0])] == list(golden[0])
    for expected, row in zip(golden, rows, strict=True):
        differing = {k: (expected[k], row[k]) for k in expected if expected[k] != row[k]}
        assert not differing, f"at {expected['interactions']} interactions: {differing}"
