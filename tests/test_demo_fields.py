"""Demonstration fields the validator must refuse rather than misread (issue 46, items
6-9): string or NaN terminal flags, complex arrays, states whose squares overflow
float32, malformed optional records, and seeds beyond int64."""

from __future__ import annotations

import numpy as np
import pytest

import expert
import harness
import offpac_il
from harness import UserError


@pytest.fixture
def arrays(hopper_demos) -> dict:
    return harness.load_arrays(hopper_demos)


def refused(arrays: dict, tmp_path, **changes) -> str:
    path = tmp_path / "demos.npz"
    with pytest.raises(UserError) as error:
        expert.validate_demos({**arrays, **changes}, "Hopper-v4", path)
    assert str(error.value).startswith(f"{path}: ")
    return str(error.value)


def test_terminal_flags_must_be_booleans_or_0_and_1(arrays, tmp_path):
    n = len(arrays["observations"])
    assert "terminals must be booleans" in refused(
        arrays, tmp_path, terminals=np.array(["False"] * n)
    )
    assert "other values" in refused(arrays, tmp_path, terminals=np.full(n, np.nan))
    assert "other values" in refused(arrays, tmp_path, timeouts=np.full(n, 2.0))
    flags = np.zeros(n)
    flags[3] = 1
    demos = expert.validate_demos({**arrays, "terminals": flags}, "Hopper-v4", tmp_path)
    assert demos.terminals.dtype == bool and demos.terminals.sum() == 1


def test_complex_or_string_triplets_are_refused(arrays, tmp_path):
    complex_states = arrays["observations"] + 1j
    assert "not real numbers" in refused(arrays, tmp_path, observations=complex_states)
    strings = arrays["actions"].astype(str)
    assert "not real numbers" in refused(arrays, tmp_path, actions=strings)


def test_states_whose_squares_overflow_float32_are_refused(arrays, tmp_path):
    huge = arrays["observations"].copy()
    huge[0, 0] = 1e30
    assert "overflow float32" in refused(arrays, tmp_path, observations=huge)
    assert "overflow float32" in refused(arrays, tmp_path, next_observations=huge)


@pytest.mark.parametrize(
    "key, value",
    [
        ("seed", np.array("zero")),
        ("seed", np.array([1, 2])),
        ("seed", np.array(10**20)),  # an object array, as `--seed 1e20` once wrote
        ("seed", np.array(-1)),
        ("trajectories", np.array(3.7)),
        ("trajectories", np.array("3")),
        ("trajectories", np.array(0)),
        ("returns", np.array("high")),
        ("returns", np.array([np.nan])),
        ("returns", np.ones((2, 2))),
        ("sampling", np.array(5)),
        ("source", np.array(["a", "b"])),
    ],
)
def test_malformed_optional_records_are_refused(arrays, tmp_path, key, value):
    assert key in refused(arrays, tmp_path, **{key: value})


def test_well_formed_optional_records_are_read(arrays, tmp_path):
    demos = expert.validate_demos(arrays, "Hopper-v4", tmp_path)
    assert (demos.seed, demos.trajectories, demos.sampling) == (0, 1, "sparse")
    assert demos.returns.shape == (1,)


@pytest.mark.parametrize("seed", ["1e20", "-1", "9223372036854775808"])
def test_seeds_beyond_int64_or_negative_are_one_line(tmp_path, capsys, seed):
    assert (
        expert.main(
            ["demos", "--env", "Hopper-v4", "--seed", seed, "--out", str(tmp_path / "d.npz")]
        )
        == 2
    )
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "--seed" in err and "2**63 - 1" in err
    assert not any(tmp_path.iterdir())
    config = offpac_il.Config(demo_seed=10**30, run_dir=str(tmp_path / "r"))
    with pytest.raises(UserError, match="--demo-seed must lie in"):
        offpac_il.check_config(config)
    with pytest.raises(UserError, match="--seed must lie in"):
        offpac_il.check_config(offpac_il.Config(seed=2**63))


def test_check_demos_of_a_malformed_record_is_one_line(arrays, tmp_path, capsys):
    path = tmp_path / "demos.npz"
    harness.save_arrays(path, {**arrays, "trajectories": np.array(3.7)})
    assert expert.main(["check-demos", str(path), "--env", "Hopper-v4"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "trajectories must be one whole number" in err
