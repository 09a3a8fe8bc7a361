"""Tests for expert.py: demonstrations, their validation, the CLI's errors, Minari import,
the shipped experts and reading Table 1 (measuring it: tests/test_table.py; training
experts: tests/test_ars.py, tests/test_sac.py).

Tests that need an expert use a hand-made linear controller for InvertedPendulum-v4 (it
balances the pole for the full 1000 steps), so they never wait for a long training run; only
``test_shipped_hopper_expert_loads_and_acts`` touches a shipped expert.
"""

import json
import subprocess
import sys
import warnings
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest

import expert
from expert import UserError
from lab import shipping

REPO_DIR = Path(expert.__file__).resolve().parent
PENDULUM = "InvertedPendulum-v4"  # obs (x, theta, x', theta'), one force in [-3, 3]


@pytest.fixture(autouse=True)
def _quiet_gymnasium():
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", DeprecationWarning)
        yield


@pytest.fixture
def pendulum_expert() -> expert.ExpertPolicy:
    """Push the cart towards the side the pole leans to: a PD controller that never falls."""
    return expert.ExpertPolicy(
        env_id=PENDULUM,
        weights=np.array([[1.0, 10.0, 1.0, 1.0]]),  # (dim A, dim S)
        obs_mean=np.zeros(4),
        obs_std=np.ones(4),
        action_low=np.array([-3.0]),
        action_high=np.array([3.0]),
        metadata={"commands": ["hand-made test controller"]},
    )


@pytest.fixture
def demo_file(tmp_path, pendulum_expert) -> Path:
    path = tmp_path / "pendulum-demos.npz"
    expert.write_demos(path, expert.make_demos(PENDULUM, 2, "sparse", 0, expert=pendulum_expert))
    return path


def rewrite(path: Path, **changes) -> Path:
    """A copy of a demo file with some arrays replaced (``None`` deletes the key)."""
    with np.load(path) as file:
        arrays = {key: file[key] for key in file.files}
    for key, value in changes.items():
        if value is None:
            arrays.pop(key)
        else:
            arrays[key] = value
    broken = path.with_name("broken-" + path.name)
    np.savez(broken, **arrays)
    return broken


# --- demonstrations ---------------------------------------------------------------------------


def test_demo_round_trip(demo_file, pendulum_expert):
    demos = expert.load_demos(demo_file, PENDULUM)
    assert len(demos) == 200
    assert demos.observations.dtype == np.float32 and demos.observations.shape == (200, 4)
    assert demos.actions.shape == (200, 1) and demos.next_observations.shape == (200, 4)
    assert demos.terminals.dtype == bool and not demos.terminals.any()
    assert demos.env_id == PENDULUM and demos.sampling == "sparse"
    assert demos.trajectories == 2 and demos.seed == 0
    np.testing.assert_array_equal(demos.returns, [1000.0, 1000.0])
    # The recorded action is the expert's action at the recorded state (float32 round trip).
    recomputed = np.array([pendulum_expert.act(s) for s in demos.observations.astype(np.float64)])
    np.testing.assert_allclose(demos.actions, recomputed, atol=1e-4)


def test_sparse_and_dense_counts(pendulum_expert):
    sparse = expert.make_demos(PENDULUM, 2, "sparse", 1, expert=pendulum_expert)
    dense = expert.make_demos(PENDULUM, 2, "dense", 1, expert=pendulum_expert)
    assert len(sparse["observations"]) == 2 * 100
    assert len(dense["observations"]) == 2 * 1000
    # Dense triplets chain: s' of step t is s of step t + 1 within a trajectory.
    np.testing.assert_array_equal(dense["next_observations"][:999], dense["observations"][1:1000])
    # Sparse triplets are a subset of the same trajectories (same reset seeds).
    dense_rows = {row.tobytes() for row in dense["observations"]}
    assert all(row.tobytes() in dense_rows for row in sparse["observations"])
    assert len({row.tobytes() for row in sparse["observations"]}) == 200  # without replacement


def test_demos_are_deterministic_for_a_seed(pendulum_expert):
    first = expert.make_demos(PENDULUM, 2, "sparse", 7, expert=pendulum_expert)
    second = expert.make_demos(PENDULUM, 2, "sparse", 7, expert=pendulum_expert)
    other = expert.make_demos(PENDULUM, 2, "sparse", 8, expert=pendulum_expert)
    for key in ("observations", "actions", "next_observations", "terminals"):
        assert first[key].tobytes() == second[key].tobytes()
    assert first["observations"].tobytes() != other["observations"].tobytes()


def test_expert_that_falls_is_refused(pendulum_expert):
    pendulum_expert.weights = np.zeros((1, 4))  # no control: the pole falls every time
    with pytest.raises(UserError, match="lasted 1000 steps in only 0 of 3"):
        expert.make_demos(PENDULUM, 1, "sparse", 0, expert=pendulum_expert, max_attempts=3)


class FlipFirstCheetah:
    """A stand-in HalfCheetah expert that fails its first episode without ending it:
    full torque (control cost 0.6 a step, return about -600), then no torque (about 0)."""

    metadata = {"commands": ["hand-made test controller"]}

    def __init__(self):
        self.calls = 0

    def act(self, observation):
        self.calls += 1
        return np.full(6, 1.0 if self.calls <= expert.TRAJECTORY_STEPS else 0.0)


def test_trajectory_below_the_return_floor_is_dropped():
    demos = expert.make_demos(
        "HalfCheetah-v4", 2, "sparse", 0, expert=FlipFirstCheetah(), min_return=-300.0
    )
    assert len(demos["dropped_episode_seeds"]) == 1
    assert len(demos["episode_seeds"]) == 2 and np.all(demos["returns"] >= -300.0)
    kept_all = expert.make_demos("HalfCheetah-v4", 2, "sparse", 0, expert=FlipFirstCheetah())
    assert len(kept_all["dropped_episode_seeds"]) == 0 and kept_all["returns"][0] < -300.0


def test_return_floor_is_half_way_from_random_to_expert():
    table = json.loads((REPO_DIR / "experts" / "table.json").read_text())["Hopper-v4"]
    midpoint = (table["random_mean"] + table["expert_mean"]) / 2
    assert expert.demo_return_floor("Hopper-v4") == pytest.approx(midpoint)
    assert expert.demo_return_floor(PENDULUM) == -np.inf  # no table row: no floor


def test_ensure_demos_remakes_a_cached_file_with_a_failed_trajectory(
    tmp_path, monkeypatch, pendulum_expert
):
    monkeypatch.setattr(expert, "DEMOS_DIR", tmp_path)
    monkeypatch.setattr(expert, "load_expert", lambda env_id: pendulum_expert)
    monkeypatch.setattr(expert, "demo_return_floor", lambda env_id: 500.0)
    path = expert.ensure_demos(PENDULUM, trajectories=1, sampling="sparse", seed=3)
    rewrite(path, returns=np.array([-400.0])).replace(path)  # as an older version kept it
    assert expert.ensure_demos(PENDULUM, trajectories=1, sampling="sparse", seed=3) == path
    with np.load(path) as remade:
        assert remade["returns"].tolist() == [1000.0]
        assert float(remade["min_return"]) == 500.0  # the shipped expert's floor, by default


def test_ensure_demos_uses_the_cache(tmp_path, monkeypatch, pendulum_expert):
    monkeypatch.setattr(expert, "DEMOS_DIR", tmp_path)
    monkeypatch.setattr(expert, "load_expert", lambda env_id: pendulum_expert)
    path = expert.ensure_demos(PENDULUM, trajectories=1, sampling="sparse", seed=3)
    assert path == tmp_path / f"{PENDULUM}-sparse-1traj-seed3.npz"
    assert expert.default_demos_path(PENDULUM, 1, "sparse", 3) == path
    modified = path.stat().st_mtime_ns
    assert expert.ensure_demos(PENDULUM, trajectories=1, sampling="sparse", seed=3) == path
    assert path.stat().st_mtime_ns == modified


# --- validation: each failure is a UserError naming the file ---------------------------------


BROKEN_FILES = {
    "wrong obs dim": (dict(observations=np.zeros((200, 5), np.float32)), "observations"),
    "wrong act dim": (dict(actions=np.zeros((200, 2), np.float32)), "actions"),
    "NaN": (dict(next_observations=np.full((200, 4), np.nan, np.float32)), "non-finite"),
    "out of bounds": (dict(actions=np.full((200, 1), 3.5, np.float32)), "action bounds"),
    "missing key": (dict(actions=None), "missing key"),
    "mismatched lengths": (dict(terminals=np.zeros(10, bool)), "mismatched lengths"),
    "wrong env": (dict(env_id=np.array("Hopper-v4")), "Hopper-v4"),
}


@pytest.mark.parametrize("case", BROKEN_FILES)
def test_load_demos_rejects(demo_file, case):
    changes, expected = BROKEN_FILES[case]
    broken = rewrite(demo_file, **changes)
    with pytest.raises(UserError, match=expected) as error:
        expert.load_demos(broken, PENDULUM)
    assert broken.name in str(error.value)


def test_load_demos_rejects_zero_triplets(demo_file):
    empty = {key: np.zeros((0, 4), np.float32) for key in ("observations", "next_observations")}
    broken = rewrite(
        demo_file, actions=np.zeros((0, 1), np.float32), terminals=np.zeros(0, bool), **empty
    )
    with pytest.raises(UserError, match="zero triplets") as error:
        expert.load_demos(broken, PENDULUM)
    assert broken.name in str(error.value)


def test_load_demos_rejects_truncated_and_missing_files(demo_file, tmp_path):
    truncated = tmp_path / "truncated.npz"
    truncated.write_bytes(demo_file.read_bytes()[: demo_file.stat().st_size // 2])
    with pytest.raises(UserError, match="truncated.npz"):
        expert.load_demos(truncated, PENDULUM)
    with pytest.raises(UserError, match="absent.npz"):
        expert.load_demos(tmp_path / "absent.npz", PENDULUM)


def test_load_demos_accepts_files_without_env_id(demo_file):
    assert len(expert.load_demos(rewrite(demo_file, env_id=None), PENDULUM)) == 200


# --- demonstrations as people have them: plain triplets, D4RL's and Minari's names ------------


def test_plain_triplets_are_accepted_with_no_terminal_and_the_run_is_told(demo_file):
    triplets = rewrite(demo_file, terminals=None)
    demos = expert.load_demos(triplets, PENDULUM)
    assert len(demos) == 200 and demos.terminals.dtype == bool and not demos.terminals.any()
    assert demos.terminals_assumed and "every s' taken as non-terminal" in demos.describe()
    assert str(triplets) in demos.describe() and "200 triplets" in demos.describe()
    assert not expert.load_demos(demo_file, PENDULUM).terminals_assumed
    assert "non-terminal" not in expert.load_demos(demo_file, PENDULUM).describe()
    result = run_cli("check-demos", str(triplets), "--env", PENDULUM)
    assert result.returncode == 0 and "every s' taken as non-terminal" in result.stdout


@pytest.mark.parametrize(
    "terminal_key, timeout_key", [("terminals", "timeouts"), ("terminations", "truncations")]
)
def test_d4rl_and_minari_key_names_are_read(demo_file, terminal_key, timeout_key):
    flags = np.zeros(200, bool)
    flags[[99, 199]] = True
    named = {terminal_key: flags, timeout_key: ~flags, "rewards": np.ones(200, np.float32)}
    demos = expert.load_demos(rewrite(demo_file, **{"terminals": None} | named), PENDULUM)
    np.testing.assert_array_equal(demos.terminals, flags)  # the timeouts are no terminals
    assert not demos.terminals_assumed
    short = rewrite(demo_file, **{"terminals": None} | named | {timeout_key: np.zeros(7, bool)})
    with pytest.raises(UserError, match=f"mismatched lengths.*{timeout_key}"):
        expert.load_demos(short, PENDULUM)


def test_reference_returns_in_a_file_serve_a_task_without_table_row(demo_file, capsys):
    scored = rewrite(demo_file, ref_min_score=np.array(5.0), ref_max_score=np.array(1000.0))
    demos = expert.load_demos(scored, PENDULUM)
    assert demos.reference_returns == (5.0, 1000.0)
    assert expert.references_or_nan(PENDULUM, demos) == (5.0, 1000.0)
    assert "reference returns" in capsys.readouterr().out
    assert np.isnan(
        expert.references_or_nan(PENDULUM, expert.load_demos(demo_file, PENDULUM))
    ).all()
    assert "no normalised score" in capsys.readouterr().out
    # A task with a Table 1 row keeps its own reference returns.
    assert expert.references_or_nan("Hopper-v4", demos) == expert.reference_returns("Hopper-v4")
    backwards = rewrite(demo_file, ref_min_score=np.array(9.0), ref_max_score=np.array(1.0))
    with pytest.raises(UserError, match="ref_min_score"):
        expert.load_demos(backwards, PENDULUM)


# --- environments and the command line ---------------------------------------------------------


def test_make_env_refuses_discrete_and_unknown_envs():
    with pytest.raises(UserError, match=r"continuous \(Box\) action space.*Discrete\(2\)"):
        expert.make_env("CartPole-v1")
    with pytest.raises(UserError, match="NoSuchTask-v0"):
        expert.make_env("NoSuchTask-v0")
    # A version gymnasium moved out (ImportError), a module that is missing, bad kwargs.
    with pytest.raises(UserError, match="'Hopper-v3'.*gymnasium-robotics"):
        expert.make_env("Hopper-v3")
    with pytest.raises(UserError, match="No module named 'no_such_module'"):
        expert.make_env("no_such_module:Task-v0")
    with pytest.raises(UserError, match="unexpected keyword argument 'no_such_kwarg'"):
        expert.make_env("Hopper-v4", no_such_kwarg=1)
    env = expert.make_env(PENDULUM)
    assert expert.env_dimensions(env) == (4, 1)
    env.close()


def test_make_env_is_quiet(capfd, tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    expert.make_env("HalfCheetah-v4").close()  # its -v4 asset triggers a MuJoCo deprecation
    assert capfd.readouterr().err == ""
    assert not (tmp_path / "MUJOCO_LOG.TXT").exists()


def run_cli(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run(
        [sys.executable, str(REPO_DIR / "expert.py"), *args],
        capture_output=True,
        text=True,
        cwd=REPO_DIR,
        timeout=120,
    )


def test_cli_bad_demo_file_is_one_line_and_exit_2(tmp_path):
    bad = tmp_path / "bad.npz"
    bad.write_bytes(b"not a zip file")
    result = run_cli("check-demos", str(bad), "--env", PENDULUM)
    assert result.returncode == 2
    assert result.stderr.count("\n") == 1 and result.stderr.startswith("error: ")
    assert "bad.npz" in result.stderr


def test_cli_discrete_env_is_one_line_and_exit_2(tmp_path):
    result = run_cli("demos", "--env", "CartPole-v1", "--out", str(tmp_path / "d.npz"))
    assert result.returncode == 2
    assert result.stderr.count("\n") == 1 and "Discrete(2)" in result.stderr
    assert list(tmp_path.iterdir()) == []  # nothing half-written


def test_cli_has_no_training_commands():
    result = run_cli("--help")
    assert result.returncode == 0 and "demos" in result.stdout and "check-demos" in result.stdout
    assert "train" not in result.stdout  # the expert trainers are lab/ars.py and lab/sac.py
    assert "table" not in result.stdout  # measuring Table 1 is lab/table.py's


@pytest.fixture
def pendulum_expert_file(tmp_path, pendulum_expert) -> Path:
    path = tmp_path / "pendulum-expert.npz"
    shipping.save_expert(pendulum_expert, path)
    return path


def test_cli_demos_out_is_checked_before_the_rollouts(tmp_path, pendulum_expert_file, capsys):
    demos = ["demos", "--env", PENDULUM, "--expert", str(pendulum_expert_file), "--out"]
    (tmp_path / "a-file").write_text("mine")
    for out, says in (
        (tmp_path, "is a directory"),
        (tmp_path / "a-file" / "d.npz", "under a file"),
    ):
        assert expert.main([*demos, str(out)]) == 2
        error = capsys.readouterr().err
        assert error.count("\n") == 1 and f"--out {out} " in error and says in error
    # An existing file is replaced only with --force.
    out = tmp_path / "d.npz"
    out.write_bytes(b"someone's file")
    assert expert.main([*demos, str(out), "--trajectories", "1"]) == 2
    error = capsys.readouterr().err
    assert error.count("\n") == 1 and "exists; give --force" in error
    assert out.read_bytes() == b"someone's file"
    assert expert.main([*demos, str(out), "--trajectories", "1", "--force"]) == 0
    assert len(expert.load_demos(out, PENDULUM)) == 100
    minari = ["import-minari", "test/any-v0", "--env", PENDULUM, "--out", str(out)]
    assert expert.main(minari) == 2 and "exists; give --force" in capsys.readouterr().err


def test_cli_bad_flag_is_one_line_and_exit_2(capsys):
    assert expert.main(["demos", "--env", PENDULUM, "--trajectories", "0"]) == 2
    error = capsys.readouterr().err
    assert error.count("\n") == 1 and "--trajectories" in error and "at least 1" in error


# --- Minari import -----------------------------------------------------------------------------


def make_minari_dataset(
    dataset_id, controller, episodes=((20, 1.0), (15, 1.0), (40, 0.0)), **scores
):
    """A Minari dataset (minari 0.5 API) in MINARI_DATASETS_PATH, of real InvertedPendulum-v4
    episodes of the given (steps, controller gain); a gain 0 episode falls (terminal s').
    Returns the episodes."""
    minari = pytest.importorskip("minari")
    pytest.importorskip("h5py")
    from minari.data_collector import EpisodeBuffer

    env = expert.make_env(PENDULUM)
    buffers = []
    for episode, (steps, gain) in enumerate(episodes):
        observation, _ = env.reset(seed=episode)
        observations, actions, rewards, terminations, truncations = [observation], [], [], [], []
        for t in range(steps):
            action = np.clip(gain * controller.act(observation), -3, 3).astype(np.float32)
            observation, reward, terminated, _, _ = env.step(action)
            observations.append(observation)
            actions.append(action)
            rewards.append(reward)
            terminations.append(terminated)
            truncations.append(not terminated and t == steps - 1)
            if terminated:
                break
        buffers.append(
            EpisodeBuffer(
                id=episode,
                seed=episode,
                observations=np.array(observations),
                actions=np.array(actions),
                rewards=rewards,
                terminations=terminations,
                truncations=truncations,
                infos={},
            )
        )
    minari.create_dataset_from_buffers(
        dataset_id,
        buffers,
        env=env,
        algorithm_name="hand-made",
        author="tests",
        author_email="tests@example.org",
        code_permalink="-",
        eval_env=PENDULUM,
        description="test episodes",
        **scores,
    )
    env.close()
    return buffers


def test_minari_import_round_trip(tmp_path, monkeypatch, pendulum_expert):
    monkeypatch.setenv("MINARI_DATASETS_PATH", str(tmp_path / "datasets"))
    # Three short episodes of a real environment; the last one ends in a fall (terminal s').
    episodes = make_minari_dataset("test/pendulum/tiny-v0", pendulum_expert)
    out = tmp_path / "imported.npz"
    result = expert.main(
        ["import-minari", "test/pendulum/tiny-v0", "--env", PENDULUM, "--out", str(out)]
    )
    assert result == 0
    demos = expert.load_demos(out, PENDULUM)
    total = sum(len(episode.actions) for episode in episodes)
    assert len(demos) == total
    np.testing.assert_allclose(demos.observations[:20], episodes[0].observations[:-1], rtol=1e-6)
    np.testing.assert_allclose(
        demos.next_observations[:20], episodes[0].observations[1:], rtol=1e-6
    )
    assert demos.terminals[-1] and demos.terminals.sum() == 1  # only the fall is terminal
    np.testing.assert_allclose(demos.returns, [sum(e.rewards) for e in episodes])
    assert demos.source == "minari:test/pendulum/tiny-v0" and demos.reference_returns is None

    absent = ["import-minari", "test/absent/none-v0", "--env", PENDULUM, "--out"]
    assert expert.main([*absent, str(tmp_path / "none.npz")]) == 2
    assert not (tmp_path / "none.npz").exists()


def test_minari_dataset_by_id(tmp_path, monkeypatch, pendulum_expert, capsys):
    """--demos minari:<id>: the first --trajectories episodes, subsampled as --sampling
    says, converted once to demos/; the dataset's reference returns give the score."""
    monkeypatch.setenv("MINARI_DATASETS_PATH", str(tmp_path / "datasets"))
    monkeypatch.setattr(expert, "DEMOS_DIR", tmp_path / "demos")
    lengths = ((150, 1.0), (120, 1.0), (40, 0.0))
    episodes = make_minari_dataset(
        "test/pendulum/long-v0", pendulum_expert, lengths, ref_min_score=5.0, ref_max_score=150.0
    )

    def settings(**changes):
        chosen = dict(demos="minari:test/pendulum/long-v0", env=PENDULUM, trajectories=2)
        return SimpleNamespace(**chosen | dict(sampling="sparse", demo_seed=0) | changes)

    path = expert.demo_path(settings(), make=False)
    assert path.parent == tmp_path / "demos" and not path.exists()
    assert expert.demo_path(settings()) == path and path.exists()
    sparse = expert.load_demos(path, PENDULUM)
    assert len(sparse) == 2 * 100 and sparse.trajectories == 2 and sparse.sampling == "sparse"
    assert sparse.source == "minari:test/pendulum/long-v0"
    assert "from minari:test/pendulum/long-v0" in sparse.describe()
    first = {row.tobytes() for row in episodes[0].observations[:-1].astype(np.float32)}
    assert sum(row.tobytes() in first for row in sparse.observations) == 100
    dense = expert.load_demos(
        expert.demo_path(settings(sampling="dense", trajectories=3)), PENDULUM
    )
    assert len(dense) == 150 + 120 + len(episodes[2].actions) and dense.terminals.sum() == 1
    # No expert and no Table 1 row for the task: the dataset's reference returns score it.
    assert expert.references_or_nan(PENDULUM, sparse) == (5.0, 150.0)
    assert "minari:test/pendulum/long-v0's reference returns" in capsys.readouterr().out
    with pytest.raises(UserError, match="fewer than 4 episodes"):
        expert.demo_path(settings(trajectories=4))
    with pytest.raises(UserError, match="recorded on InvertedPendulum-v4, not InvertedPendulum-v5"):
        expert.demo_path(settings(env="InvertedPendulum-v5"))
    with pytest.raises(UserError, match="cannot load Minari dataset 'test/absent/none-v0'"):
        expert.demo_path(settings(demos="minari:test/absent/none-v0"))


# --- shipped experts and the reference table -----------------------------------------------------


def test_v5_tasks_are_served_by_the_v4_experts():
    for task in ("Hopper", "HalfCheetah", "Walker2d", "Ant", "Humanoid"):
        policy = expert.load_expert(f"{task}-v5")
        assert policy.env_id == f"{task}-v4" and policy.serves == f"{task}-v5"
        assert expert.serving_expert_path(f"{task}-v5") == expert.default_expert_path(f"{task}-v4")
        # A trainer writes a -v5 expert of its own, never over the -v4 one.
        assert expert.default_expert_path(f"{task}-v5").name == f"{task}-v5.npz"
        random_return, expert_return = expert.reference_returns(f"{task}-v5")
        assert expert_return > 10 * abs(random_return)
    with pytest.raises(UserError, match="trained on Hopper-v4, not Walker2d-v5"):
        expert.load_expert("Walker2d-v5", expert.default_expert_path("Hopper-v4"))


@pytest.mark.parametrize("task", ["Ant", "Humanoid"])
def test_a_served_expert_acts_on_v5_as_on_v4(task):
    """Ant-v5 and Humanoid-v5 hold Ant-v4's and Humanoid-v4's observations (the columns
    as_trained_observation reads; Humanoid-v4's others are always 0) under the same
    dynamics: the served expert, stepped on both versions from one reset seed, takes the
    same actions and sees the same -v4 observations."""
    v4, v5 = expert.load_expert(f"{task}-v4"), expert.load_expert(f"{task}-v5")
    with expert.make_env(f"{task}-v4") as env4, expert.make_env(f"{task}-v5") as env5:
        (o4, _), (o5, _) = env4.reset(seed=5), env5.reset(seed=5)
        for _ in range(30):
            np.testing.assert_allclose(expert.as_trained_observation(v5.serves, o5), o4, atol=1e-9)
            a4, a5 = v4.act(o4), v5.act(o5)
            np.testing.assert_allclose(a5, a4, atol=1e-9)
            (o4, *_), (o5, *_) = env4.step(a4), env5.step(a5)


def test_shipped_hopper_expert_loads_and_acts():
    policy = expert.load_expert("Hopper-v4")
    assert policy.weights.shape == (3, 11)
    action = policy.act(np.zeros(11))
    assert action.shape == (3,) and np.all(np.abs(action) <= 1.0)
    assert "train --env Hopper-v4" in policy.metadata["commands"][0]


def test_reference_returns(tmp_path):
    table = {
        "Hopper-v4": dict(
            dim_s=11, dim_a=3, random_mean=18.0, random_std=1.0, expert_mean=3300.0, expert_std=5.0
        ),
        "Ant-v4": dict(
            dim_s=27, dim_a=8, random_mean=-50.0, random_std=1.0, expert_mean=None, expert_std=None
        ),
    }
    path = tmp_path / "table.json"
    path.write_text(json.dumps(table))
    assert expert.reference_returns("Hopper-v4", path) == (18.0, 3300.0)
    with pytest.raises(UserError, match="Ant-v4"):
        expert.reference_returns("Ant-v4", path)
    with pytest.raises(UserError, match="Walker2d-v4"):
        expert.reference_returns("Walker2d-v4", path)
    with pytest.raises(UserError, match="python -m lab.table"):
        expert.reference_returns("Hopper-v4", tmp_path / "absent.json")


def test_demo_path_is_the_given_file_or_the_default_demonstrations(tmp_path, monkeypatch):
    monkeypatch.setattr(expert, "DEMOS_DIR", tmp_path)
    settings = SimpleNamespace(
        demos="", env=PENDULUM, trajectories=1, sampling="dense", demo_seed=2
    )
    default = tmp_path / f"{PENDULUM}-dense-1traj-seed2.npz"
    assert expert.demo_path(settings, make=False) == default and not default.exists()
    assert expert.demo_path(SimpleNamespace(demos="my.npz")) == Path("my.npz")
