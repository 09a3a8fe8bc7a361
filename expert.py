"""Experts for the imitation tasks: the shipped experts and their demonstrations.

The paper (Sasaki et al., ICLR 2019, Sec. 5.1) trains its experts with TRPO and never ships
them. This project must run offline on a fresh machine, so it ships its own: linear
policies trained by ARS V2-t (Hopper, HalfCheetah, Humanoid; lab/ars.py) and SAC policy
networks (Walker2d, Ant; lab/sac.py). This file is what the learner needs of them: the
environments, the expert policy (load, act), demonstrations and Table 1's reference returns.

Files:
    experts/<env>.npz    a shipped expert (written by lab/shipping.py): M, mu, std (ARS) or
                         a policy network (SAC), action bounds, and a JSON ``metadata``
                         record of the training commands, seed, env steps and wall time
    experts/table.json   Table 1 (measured by ``python -m lab.table``): the -v4 tasks, and the
                         -v5 tasks a -v4 expert serves (SERVED_BY)
    demos/*.npz          demonstrations: ``observations``, ``actions`` (env units),
                         ``next_observations``, ``terminals`` (is s' terminal; also read as
                         ``terminations``; none: all False), ``env_id``, ``returns`` (per
                         trajectory), ``seed``, ``sampling``, ``trajectories``, ``source``,
                         ``ref_min_score`` and ``ref_max_score`` (a dataset's reference returns)

Subcommands (``python expert.py -h``): ``demos``, ``check-demos``, ``import-minari``.
"""

from __future__ import annotations

import argparse
import contextlib
import dataclasses
import hashlib
import itertools
import json
import math
import os
import sys
import warnings
import zipfile
from dataclasses import dataclass
from pathlib import Path

import gymnasium as gym
import numpy as np

import harness
import nets
from harness import UserError  # re-exported: `from expert import UserError` keeps working

REPO_DIR = Path(__file__).resolve().parent
# A checkout keeps experts/ beside this file; `pip install .` puts them under the prefix,
# and demonstrations are then cached in the working directory.
INSTALLED = not (REPO_DIR / "experts").is_dir()
EXPERTS_DIR = Path(sys.prefix) / "share/offpac-il/experts" if INSTALLED else REPO_DIR / "experts"
DEMOS_DIR = Path("demos") if INSTALLED else REPO_DIR / "demos"
TABLE_PATH = EXPERTS_DIR / "table.json"

# Sec. 5.1: expert trajectories are 1000 steps long; sparse sampling keeps 100 of each.
TRAJECTORY_STEPS = 1000
SPARSE_TRIPLETS_PER_TRAJECTORY = 100
SAMPLING_MODES = ("sparse", "dense")

# Demonstration actions may come from float32 files or other tools; accept tiny overshoots.
ACTION_BOUND_TOLERANCE = 1e-4


# === Environments ===


@contextlib.contextmanager
def _quiet_mujoco_compiler():
    """Drop MuJoCo's "settotalmass is deprecated" compiler warning while a model is built:
    gymnasium's HalfCheetah-v4 asset uses that attribute, and MuJoCo 3 writes the warning to
    stderr and to MUJOCO_LOG.TXT in the working directory on every make. Other MuJoCo
    warnings are passed on as Python warnings."""
    import mujoco  # here, not at the top: MUJOCO_GL is read on import (lab/render.py sets it)

    def forward(message: str) -> None:
        if "settotalmass" not in message:
            warnings.warn(f"MuJoCo: {message}", RuntimeWarning, stacklevel=2)

    previous = mujoco.get_mju_user_warning()
    mujoco.set_mju_user_warning(forward)
    try:
        yield
    finally:
        mujoco.set_mju_user_warning(previous)


def make_env(env_id: str, **kwargs) -> gym.Env:
    """``gym.make`` for continuous-control tasks, refusing what the method cannot handle: it
    needs a flat (1-D Box) state, and a Box action space with finite bounds because it maps
    ``tanh`` outputs in [-1, 1] onto ``[low, high]``."""
    with warnings.catch_warnings(), _quiet_mujoco_compiler():
        # gymnasium says "-v4 is out of date" on every make; the paper's tasks are -v4 on purpose.
        warnings.filterwarnings("ignore", message=".*is out of date.*")
        try:
            env = gym.make(env_id, **kwargs)
        except (gym.error.Error, ImportError, TypeError) as error:  # unknown, moved, bad kwargs
            first_line = str(error).splitlines()[0] if str(error) else type(error).__name__
            raise UserError(f"cannot make environment {env_id!r}: {first_line}") from None
    observation_space, action_space = env.observation_space, env.action_space
    if not (isinstance(observation_space, gym.spaces.Box) and len(observation_space.shape) == 1):
        env.close()
        raise UserError(
            f"{env_id} needs a flat (1-D Box) observation space; it has {observation_space}"
        )
    if not (
        isinstance(action_space, gym.spaces.Box)
        and len(action_space.shape) == 1
        and np.isfinite([action_space.low, action_space.high]).all()
    ):
        env.close()
        raise UserError(
            f"the method needs a continuous (Box) action space with finite bounds; "
            f"{env_id} has {action_space}"
        )
    return env


def env_dimensions(env: gym.Env) -> tuple[int, int]:
    """(dim S, dim A) of an environment made by :func:`make_env`."""
    return env.observation_space.shape[0], env.action_space.shape[0]


# === The expert policy: a linear map of normalised states (ARS V2), or a SAC policy network ===

ARS_LINEAR, SAC_MLP = "ars-linear", "sac-mlp"
EXPERT_KINDS = (ARS_LINEAR, SAC_MLP)


def tanh_to_bounds(action: np.ndarray, low: np.ndarray, high: np.ndarray) -> np.ndarray:
    """[-1, 1] -> [low, high]: low + (a + 1)(high - low)/2 (the networks act in [-1, 1])."""
    return low + (action + 1.0) * (high - low) / 2.0


@dataclass
class ExpertPolicy:
    """A deterministic expert in raw env units, of one of two kinds:

    - ``ars-linear``: ARS V2 ``a = clip(M @ ((s - mu) / std), low, high)``; ``weights``,
      ``obs_mean`` and ``obs_std`` hold M, mu and std, and ``network`` is None.
    - ``sac-mlp``: the mean action of a SAC policy (lab/sac.py), ``a = low + (tanh(m(s)) + 1)
      (high - low)/2`` with ``m(s)`` the first dim A outputs of ``network`` (the others are
      its log std, unused here); ``weights``, ``obs_mean`` and ``obs_std`` are None.
    """

    env_id: str
    action_low: np.ndarray  # (dim A,)
    action_high: np.ndarray  # (dim A,)
    weights: np.ndarray | None = None  # M, (dim A, dim S)
    obs_mean: np.ndarray | None = None  # mu, (dim S,)
    obs_std: np.ndarray | None = None  # sqrt(diag Sigma), (dim S,)
    network: nets.MLP | None = None  # SAC: state -> (mean, log std), (dim S) -> (2 dim A)
    metadata: dict = dataclasses.field(default_factory=dict)
    serves: str | None = None  # a -v5 task it acts on through as_trained_observation

    def act(self, observation: np.ndarray) -> np.ndarray:
        """Deterministic action for one state, within the action bounds."""
        observation = as_trained_observation(self.serves, observation)
        if self.network is None:
            normalised = (np.asarray(observation, dtype=np.float64) - self.obs_mean) / self.obs_std
            return np.clip(self.weights @ normalised, self.action_low, self.action_high)  # (dim A,)
        state = np.asarray(observation, dtype=self.network.dtype)[None]  # (1, dim S)
        mean = self.network.forward(state)[0][0, : len(self.action_low)]  # (dim A,)
        return tanh_to_bounds(np.tanh(mean).astype(np.float64), self.action_low, self.action_high)


# -v5 tasks a -v4 expert serves: same dynamics, and the -v5 observation holds the -v4 one,
# in the same layout or as in V4_LAYOUT (-v4 dims, where the leading -v5 columns go; the
# rest always 0): Ant-v5 appends contact forces; Humanoid-v5 drops the world body's and the
# free joint's always-0 columns (tests/test_expert.py checks both).
SERVED_BY = {f"{t}-v5": f"{t}-v4" for t in ("Hopper", "HalfCheetah", "Walker2d", "Ant", "Humanoid")}
V4_LAYOUT = {
    "Ant-v5": (27, np.arange(27)),
    "Humanoid-v5": (376, np.r_[0:45, 55:185, 191:269, 275:292, 298:376]),
}


def as_trained_observation(serves: str | None, observation: np.ndarray) -> np.ndarray:
    """A -v5 observation as the -v4 expert serving that task was trained to read it."""
    if serves not in V4_LAYOUT:
        return observation
    dim, columns = V4_LAYOUT[serves]
    trained = np.zeros(dim, np.asarray(observation).dtype)
    trained[columns] = observation[: len(columns)]
    return trained


def default_expert_path(env_id: str) -> Path:
    """Where the expert trained for ``env_id`` is written: ``EXPERTS_DIR/<env_id>.npz``."""
    return EXPERTS_DIR / f"{env_id}.npz"


def serving_expert_path(env_id: str) -> Path:
    """The expert file that serves ``env_id``: its own if one was trained, else, for the
    -v5 tasks of SERVED_BY, the -v4 expert's (Table 1 has its return on each of them)."""
    own = default_expert_path(env_id)
    if own.exists() or env_id not in SERVED_BY:
        return own
    return default_expert_path(SERVED_BY[env_id])


def load_expert(env_id: str, path: Path | None = None) -> ExpertPolicy:
    """Load the expert that serves ``env_id`` (or the one at ``path``), checking it fits. A
    file without a ``kind`` is an ARS linear policy (every file written before SAC)."""
    path = Path(path) if path is not None else serving_expert_path(env_id)
    if not path.exists():
        raise UserError(
            f"no expert for {env_id} at {path}; train one with "
            f"`python -m lab.ars --env {env_id}` (or lab.sac)"
        )
    try:
        with np.load(path, allow_pickle=False) as file:
            kind = str(file["kind"]) if "kind" in file.files else ARS_LINEAR
            if kind not in EXPERT_KINDS:
                raise ValueError(f"unknown expert kind {kind!r}; expected one of {EXPERT_KINDS}")
            low, high = (np.asarray(file[k], np.float64) for k in ("action_low", "action_high"))
            policy = ExpertPolicy(str(file["env_id"]), low, high)
            policy.metadata = json.loads(str(file["metadata"]))
            if kind == ARS_LINEAR:
                policy.weights, policy.obs_mean, policy.obs_std = (
                    np.asarray(file[k], np.float64) for k in ("weights", "obs_mean", "obs_std")
                )
            else:
                names = [key for key in file.files if key.startswith("policy/")]
                params = {key.removeprefix("policy/"): file[key] for key in names}
                policy.network = nets.MLP([int(n) for n in file["sizes"]], "identity", params)
    except (OSError, ValueError, KeyError, EOFError, TypeError, zipfile.BadZipFile) as error:
        raise UserError(f"{path}: not a valid expert file ({error})") from None
    if policy.env_id not in (env_id, SERVED_BY.get(env_id)):
        raise UserError(f"{path}: expert was trained on {policy.env_id}, not {env_id}")
    policy.serves = env_id if policy.env_id != env_id else None
    if policy.network is None:
        dim_a, dim_s = policy.weights.shape
        consistent = policy.obs_mean.shape == (dim_s,)
    else:
        sizes = policy.network.sizes
        dim_a = sizes[-1] // 2  # mean and log std per action dimension
        layers = list(zip(sizes[:-1], sizes[1:], strict=True))
        expected = {f"W{i}": shape for i, shape in enumerate(layers)}
        expected |= {f"b{i}": (fan_out,) for i, (_, fan_out) in enumerate(layers)}
        actual = {key: value.shape for key, value in policy.network.params.items()}
        consistent = sizes[-1] == 2 * dim_a and actual == expected
    if not consistent or policy.action_low.shape != (dim_a,):
        raise UserError(f"{path}: inconsistent array shapes in expert file")
    return policy


# === Demonstrations: (s, a, s') triplets of 1000-step expert trajectories (Sec. 5.1) ===

DEMO_ARRAY_KEYS = ("observations", "actions", "next_observations")  # and terminal flags
# Other tools' names for the flags (D4RL: terminals, timeouts; Minari: terminations,
# truncations); the first one present is read. A file without either terminal key holds the
# paper's plain (s, a, s') triplets: no s' is terminal. A timeout (truncation) needs nothing
# of the learner, which bootstraps through it as through any non-terminal s'; its array is
# only checked. `rewards` are ignored: the method learns without them.
TERMINAL_KEYS, TIMEOUT_KEYS = ("terminals", "terminations"), ("timeouts", "truncations")
MINARI = "minari:"  # --demos minari:<dataset id>: a Minari dataset in the local cache
ASSUMED = "; no terminal flags in the file: every s' taken as non-terminal"
REFERENCE_KEYS = ("ref_min_score", "ref_max_score")  # a dataset's own reference returns


@dataclass
class Demos:
    """Validated expert triplets; arrays are float32 (terminals bool), actions in env units."""

    observations: np.ndarray  # s, (n, dim S)
    actions: np.ndarray  # a, (n, dim A)
    next_observations: np.ndarray  # s', (n, dim S)
    terminals: np.ndarray  # whether s' is terminal, (n,)
    env_id: str | None = None
    returns: np.ndarray | None = None  # expert return of each source trajectory
    seed: int | None = None
    sampling: str | None = None
    trajectories: int | None = None
    path: Path | None = None
    source: str | None = None  # where a converted file came from, e.g. minari:<dataset id>
    terminals_assumed: bool = False  # the file had no terminal flags: all taken as False
    reference_returns: tuple[float, float] | None = None  # (ref_min_score, ref_max_score)
    sha256: str | None = None  # of the file's bytes: a resume checks it is the same file

    def __len__(self) -> int:
        return len(self.observations)

    def describe(self) -> str:
        """A run's first line about its demonstrations: where from, how many, what was assumed."""
        source = f" from {self.source}" if self.source else ""
        assumed = ASSUMED * self.terminals_assumed
        return f"demonstrations: {self.path} ({len(self)} triplets{source}){assumed}"


def default_demos_path(env_id: str, trajectories: int, sampling: str, seed: int) -> Path:
    """Cache location ``<repo>/demos/<env>-<sampling>-<n>traj-seed<seed>.npz`` (git-ignored)."""
    return DEMOS_DIR / f"{env_id}-{sampling}-{trajectories}traj-seed{seed}.npz"


def expert_episode(env: gym.Env, expert: ExpertPolicy, seed: int, steps: int = TRAJECTORY_STEPS):
    """One episode of `expert` from reset(seed=seed), at most `steps` steps: the states
    s_0 .. s_T, (T + 1, dim S); the actions a_0 .. a_{T-1} in the environment's units,
    (T, dim A); the return; and whether it ended by termination."""
    states, actions, episode_return, terminated = [], [], 0.0, False
    observation, _ = env.reset(seed=seed)
    for _ in range(steps):
        action = np.asarray(expert.act(observation), dtype=np.float64)
        states.append(observation)
        actions.append(action)
        observation, reward, terminated, truncated, _ = env.step(action)
        episode_return += float(reward)
        if terminated or truncated:
            break
    states.append(observation)
    return np.asarray(states), np.asarray(actions), episode_return, terminated


def make_demos(
    env_id: str,
    trajectories: int,
    sampling: str,
    seed: int,
    expert: ExpertPolicy | None = None,
    max_attempts: int | None = None,
    min_return: float | None = None,
) -> dict:
    """Roll out the expert and keep (s, a, s') triplets as in Sec. 5.1 of the paper.

    Only trajectories that last the full 1000 steps with a return of at least `min_return`
    are used: otherwise the episode is dropped and the next reset seed is tried (the dropped
    seeds and the floor are recorded). By default the shipped expert (`expert` None) is held
    to `demo_return_floor` and an expert of the caller's to no floor. Everything comes from
    one Generator seeded with ``seed``, split into one stream for the reset seeds and one for
    subsampling (`kept_steps`), so that sparse and dense demonstrations with the same seed
    come from the same trajectories (sparse is a subset of dense).
    """
    check_sampling(sampling)
    if trajectories < 1:
        raise UserError(f"--trajectories must be at least 1, got {trajectories}")
    make_env(env_id).close()  # a wrong environment is reported as such, not as "no expert"
    if min_return is None:
        min_return = demo_return_floor(env_id) if expert is None else -math.inf
    expert = expert if expert is not None else load_expert(env_id)
    max_attempts = max_attempts if max_attempts is not None else 10 * trajectories
    episode_rng, subsample_rng = np.random.default_rng(seed).spawn(2)
    chunks, returns, used_seeds, dropped_seeds = [], [], [], []
    with make_env(env_id) as env:
        while len(returns) < trajectories:
            if len(used_seeds) + len(dropped_seeds) >= max_attempts:
                at_least = f" with a return of at least {min_return:.0f}"
                floor = at_least if math.isfinite(min_return) else ""
                raise UserError(
                    f"the {env_id} expert lasted {TRAJECTORY_STEPS} steps{floor} in only "
                    f"{len(returns)} of {max_attempts} episodes; it is not good enough for demos"
                )
            # A signal to a trainer making its default demonstrations: nothing is written yet.
            harness.stop_if_requested(started=False)
            episode_seed = int(episode_rng.integers(0, 2**31 - 1))
            states, actions, episode_return, terminated = expert_episode(env, expert, episode_seed)
            if len(actions) < TRAJECTORY_STEPS or terminated or episode_return < min_return:
                dropped_seeds.append(episode_seed)
                continue
            keep = kept_steps(TRAJECTORY_STEPS, sampling, subsample_rng)
            # Every kept trajectory ran into the time limit: truncation, not termination.
            terminals = np.zeros(TRAJECTORY_STEPS, bool)
            chunks.append(tuple(a[keep] for a in (states[:-1], actions, states[1:], terminals)))
            returns.append(episode_return)
            used_seeds.append(episode_seed)
    return demo_arrays(
        chunks,
        env_id,
        returns,
        seed,
        sampling,
        episode_seeds=np.array(used_seeds, dtype=np.int64),
        dropped_episode_seeds=np.array(dropped_seeds, dtype=np.int64),
        min_return=np.array(min_return),
        expert=np.array(json.dumps(expert.metadata.get("commands", []))),
    )


def check_sampling(sampling: str) -> None:
    if sampling not in SAMPLING_MODES:
        raise UserError(f"--sampling must be one of {', '.join(SAMPLING_MODES)}, got {sampling!r}")


def kept_steps(steps: int, sampling: str, rng: np.random.Generator) -> np.ndarray:
    """The steps of a trajectory whose triplets are kept: sparse, 100 drawn uniformly
    without replacement (all of a shorter trajectory); dense, all of them."""
    if sampling == "sparse" and steps > SPARSE_TRIPLETS_PER_TRAJECTORY:
        return np.sort(rng.choice(steps, SPARSE_TRIPLETS_PER_TRAJECTORY, replace=False))
    return np.arange(steps)


def demo_arrays(chunks: list[tuple], env_id: str, returns, seed, sampling, **extra) -> dict:
    """A demonstration file's arrays from (s, a, s', terminal) chunks, one per trajectory."""
    *triplets, terminals = map(np.concatenate, zip(*chunks, strict=True))
    triplets = [array.astype(np.float32) for array in triplets]  # s, a, s'
    return dict(zip(DEMO_ARRAY_KEYS, triplets, strict=True)) | dict(
        terminals=terminals.astype(bool),
        env_id=np.array(env_id),
        returns=np.array(returns),
        seed=np.array(seed),
        sampling=np.array(sampling),
        trajectories=np.array(len(returns)),
        **extra,
    )


def write_demos(path: Path, demos: dict) -> None:
    """Validate the triplets against their environment, then write them atomically."""
    validate_demos(demos, str(demos["env_id"]), Path(path))
    harness.save_arrays(path, demos)


def demo_return_floor(env_id: str) -> float:
    """The least return of a demonstration trajectory from the shipped expert: half-way
    from the random policy's return to the expert's (Table 1); -inf without a table row.

    Ending early is not the only way for an expert to fail. HalfCheetah never terminates,
    and its shipped expert flips onto its back in 7 of 200 episodes (reset seeds 0-199;
    returns -400 to -480, below the random policy's): such a trajectory demonstrates lying
    on one's back.
    """
    try:
        random_return, expert_return = reference_returns(env_id)
    except UserError:
        return -math.inf
    return (random_return + expert_return) / 2


def ensure_demos(
    env_id: str, trajectories: int = 4, sampling: str = "sparse", seed: int = 0
) -> Path:
    """The default demonstration file, made from the shipped expert the first time. A cached
    file with a trajectory below `demo_return_floor` (made before that rule) is made again."""
    path = default_demos_path(env_id, trajectories, sampling, seed)
    if path.exists():
        try:
            with np.load(path) as cached:
                if np.all(cached["returns"] >= demo_return_floor(env_id)):
                    return path
        except (OSError, ValueError, KeyError, EOFError, zipfile.BadZipFile):
            return path  # a damaged file: load_demos names its problem
        print(f"note: {path} holds a failed expert trajectory; making it again", flush=True)
    write_demos(path, make_demos(env_id, trajectories, sampling, seed))
    return path


def demo_path(settings, make: bool = True) -> Path:
    """The demonstrations a run's settings name (offpac_il.RunConfig's demos, env,
    trajectories, sampling, demo_seed): the file `demos`; for `demos` minari:<dataset id>,
    that many trajectories of the locally cached Minari dataset, subsampled as `sampling`
    says, converted once to a file in demos/; else the shipped expert's default
    demonstrations. Either is made the first time unless `make` is False."""
    if settings.demos and not settings.demos.startswith(MINARI):
        return Path(settings.demos)
    default = (settings.env, settings.trajectories, settings.sampling, settings.demo_seed)
    if settings.demos:
        dataset_id = settings.demos.removeprefix(MINARI)
        name = f"{settings.env}-minari-{dataset_id.replace('/', '-')}"
        path = default_demos_path(name, *default[1:])
        if make and not path.exists():
            write_demos(path, import_minari(dataset_id, *default))
        return path
    return ensure_demos(*default) if make else default_demos_path(*default)


def validate_demos(arrays: dict, env_id: str, path: Path) -> Demos:
    """Check triplets against ``env_id``; any problem is one UserError naming the file."""

    def fail(problem: str) -> UserError:
        return UserError(f"{path}: {problem}")

    missing = [key for key in DEMO_ARRAY_KEYS if key not in arrays]
    if missing:
        raise fail(f"missing key(s) {', '.join(missing)}")
    terminal_key = next((key for key in TERMINAL_KEYS if key in arrays), None)
    timeout_key = next((key for key in TIMEOUT_KEYS if key in arrays), None)
    recorded_env = str(arrays["env_id"]) if "env_id" in arrays else None
    if recorded_env is not None and recorded_env != env_id:
        raise fail(f"demonstrations are for {recorded_env}, not {env_id}")
    for key in DEMO_ARRAY_KEYS:  # complex parts would be dropped, strings parsed
        if np.asarray(arrays[key]).dtype.kind not in "biuf":
            raise fail(f"{key} are not real numbers (dtype {np.asarray(arrays[key]).dtype})")
    try:
        observations, actions, next_observations = (
            np.asarray(arrays[key], dtype=np.float32) for key in DEMO_ARRAY_KEYS
        )
        flag_keys = [key for key in (terminal_key, timeout_key) if key]
        flags = {key: flag_array(arrays[key], key, fail) for key in flag_keys}
        scores = [float(arrays[key]) for key in REFERENCE_KEYS if key in arrays]
    except (TypeError, ValueError) as error:
        raise fail(f"arrays are not numeric ({error})") from None
    with make_env(env_id) as env:
        (dim_s, dim_a), low, high = env_dimensions(env), env.action_space.low, env.action_space.high
    if len(observations) == 0:
        raise fail("contains zero triplets")
    for name, array, dim in (
        ("observations", observations, dim_s),
        ("next_observations", next_observations, dim_s),
        ("actions", actions, dim_a),
    ):
        if array.ndim != 2 or array.shape[1] != dim:
            raise fail(f"{name} have shape {array.shape}; {env_id} needs (n, {dim})")
        if not np.all(np.isfinite(array)):
            raise fail(f"{name} contain non-finite values (NaN or inf)")
        if name != "actions" and np.abs(array).max() > LARGEST_STATE_VALUE:
            raise fail(
                f"{name} reach {np.abs(array).max():g}; beyond {LARGEST_STATE_VALUE:.3g} their"
                " squares overflow float32 and the standardisation is lost"
            )
    n, columns = len(observations), {"actions": actions, "next_observations": next_observations}
    for name, array in (columns | flags).items():
        if array.shape[:1] != (n,) or (name in flags and array.ndim != 1):
            raise fail(f"mismatched lengths: {n} observations, {name} of shape {array.shape}")
    tolerance = ACTION_BOUND_TOLERANCE * np.maximum(1.0, np.abs(np.stack([low, high])))
    if np.any(actions < low - tolerance[0]) or np.any(actions > high + tolerance[1]):
        raise fail(
            f"actions outside the action bounds [{low.min():g}, {high.max():g}] of "
            f"{env_id} (largest |a| = {np.abs(actions).max():g})"
        )

    optional = recorded_fields(arrays, fail)
    if len(scores) == 2:
        if not (np.all(np.isfinite(scores)) and scores[0] < scores[1]):
            raise fail(f"ref_min_score {scores[0]} and ref_max_score {scores[1]} are not ordered")
        optional |= {"reference_returns": tuple(scores)}
    terminals = flags[terminal_key] if terminal_key else np.zeros(n, bool)
    triplets = (observations, actions, next_observations, terminals)
    return Demos(*triplets, recorded_env, path=path, terminals_assumed=not terminal_key, **optional)


# States are squared by the standardisation (their std); float32 overflows beyond this.
LARGEST_STATE_VALUE = math.sqrt(np.finfo(np.float32).max)


def flag_array(values, key: str, fail) -> np.ndarray:
    """Terminal or timeout flags as booleans: booleans, or numbers that are 0 or 1 (a
    string "False" would otherwise count as True, and so would NaN)."""
    values = np.asarray(values)
    if values.dtype.kind not in "biuf":
        raise fail(f"{key} must be booleans or 0/1, not dtype {values.dtype}")
    if values.dtype.kind != "b" and not np.isin(values, (0, 1)).all():
        raise fail(f"{key} must be booleans or 0/1; they hold other values (such as NaN)")
    return values.astype(bool)


def recorded_fields(arrays: dict, fail) -> dict:
    """The optional records of a demonstration file, each checked: `returns` (finite
    numbers, one per trajectory), `seed` (a whole number in [0, 2**63 - 1]),
    `trajectories` (a whole number of at least 1), `sampling` and `source` (strings)."""
    optional = {}
    for key in ("seed", "trajectories"):
        if key in arrays:
            value = np.asarray(arrays[key])
            low = 1 if key == "trajectories" else 0
            if (
                value.shape != ()
                or value.dtype.kind not in "iu"
                or not low <= value <= harness.MAX_SEED
            ):
                raise fail(
                    f"{key} must be one whole number of at least {low}, got {briefly(value)}"
                )
            optional[key] = int(value)
    if "returns" in arrays:
        returns = np.asarray(arrays["returns"])
        if returns.ndim != 1 or returns.dtype.kind not in "iuf" or not np.isfinite(returns).all():
            raise fail(
                f"returns must be finite numbers, one per trajectory, got {briefly(returns)}"
            )
        optional["returns"] = returns.astype(np.float64)
    for key in ("sampling", "source"):
        if key in arrays:
            value = np.asarray(arrays[key])
            if value.shape != () or value.dtype.kind != "U":
                raise fail(f"{key} must be one string, got {briefly(value)}")
            optional[key] = str(value)
    return optional


def briefly(value: np.ndarray) -> str:
    """A value of a file for a one-line error: itself, or an array's dtype and shape."""
    return repr(value.item()) if value.shape == () else f"{value.dtype} array {value.shape}"


def load_demos(path: Path, env_id: str) -> Demos:
    """Load and validate a demonstration file for ``env_id`` (see :func:`validate_demos`)."""
    path = Path(path)
    if not path.exists():
        raise UserError(f"{path}: no such demonstration file")
    try:
        sha256 = hashlib.sha256(path.read_bytes()).hexdigest()
    except OSError as error:
        raise UserError(f"{path}: cannot read ({error.strerror})") from None
    return dataclasses.replace(
        validate_demos(harness.load_arrays(path), env_id, path), sha256=sha256
    )


DEMOS_SHA256 = "demos_sha256"  # config.json's record of the demonstrations a run started on


def run_demos(settings, resume: bool) -> Demos:
    """The demonstrations of a run's settings (demo_path); on a resume, refused unless
    they are the very file the run started on (its config.json's sha256): a resume on
    other data would silently continue another run."""
    demos = load_demos(demo_path(settings), settings.env)
    if resume:
        recorded = harness.read_config(settings.run_dir).get(DEMOS_SHA256)
        if recorded is not None and recorded != demos.sha256:
            raise UserError(
                f"{demos.path} is not the demonstration file {settings.run_dir} started on"
                " (its content differs); a resume must continue on the same demonstrations"
            )
    return demos


def import_minari(
    dataset_id: str,
    env_id: str,
    trajectories: int | None = None,
    sampling: str = "dense",
    seed: int = 0,
) -> dict:
    """Triplets from a Minari dataset already on this machine (never downloads).

    Minari stores each episode as observations (T+1, dim S), actions (T, dim A) and
    terminations (T,); the triplets are (obs[t], act[t], obs[t+1]) with terminal = terminations[t].
    Episodes of any length are kept (the file's returns record how good they were), with
    the dataset's reference returns (ref_min_score, ref_max_score) where its metadata has them.
    """
    try:
        import minari
    except ImportError:
        raise UserError(
            "import-minari needs the minari package: pip install 'minari[hdf5]'"
        ) from None
    check_sampling(sampling)
    try:
        dataset = minari.load_dataset(dataset_id, download=False)
    except Exception as error:  # minari raises bare Exceptions/FileNotFoundError/ValueError
        where = f"MINARI_DATASETS_PATH={os.environ.get('MINARI_DATASETS_PATH', '~')}"
        message = f"cannot load Minari dataset {dataset_id!r} locally ({where}): {error}"
        raise UserError(message) from None
    recorded_on = getattr(dataset.env_spec, "id", env_id)
    if recorded_on != env_id:
        raise UserError(
            f"Minari dataset {dataset_id!r} was recorded on {recorded_on}, not {env_id}"
        )
    rng = np.random.default_rng(seed)
    chunks, returns = [], []
    for episode in itertools.islice(dataset.iterate_episodes(), trajectories):
        observations = np.asarray(episode.observations)  # (T + 1, dim S)
        if observations.dtype == object or observations.ndim != 2:
            raise UserError(f"{dataset_id}: observations are not flat arrays")
        keep = kept_steps(len(episode.actions), sampling, rng)
        triplet = (observations[:-1], np.asarray(episode.actions), observations[1:])
        terminals = np.asarray(episode.terminations, dtype=bool)
        chunks.append(tuple(a[keep] for a in (*triplet, terminals)))
        returns.append(float(np.sum(episode.rewards)))
    if len(returns) < (trajectories or 1):
        raise UserError(
            f"Minari dataset {dataset_id!r} has fewer than {trajectories or 1} episodes"
        )
    metadata = dataset.storage.metadata
    scores = {k: np.array(metadata[k]) for k in REFERENCE_KEYS if metadata.get(k) is not None}
    return demo_arrays(
        chunks, env_id, returns, seed, sampling, source=np.array(f"{MINARI}{dataset_id}"), **scores
    )


# === Reference returns (Table 1, measured by lab/table.py): the normalised score's two ends ===


def reference_returns(env_id: str, table_path: Path = TABLE_PATH) -> tuple[float, float]:
    """(R_random, R_expert) for the normalised score (R - R_random) / (R_expert - R_random)."""
    try:
        table = json.loads(Path(table_path).read_text())
    except FileNotFoundError:
        raise UserError(f"{table_path} is missing; run `python -m lab.table`") from None
    except (OSError, ValueError) as error:
        raise UserError(f"{table_path}: not a valid table ({error})") from None
    row = table.get(env_id)
    if row is None or row.get("expert_mean") is None:
        raise UserError(
            f"{table_path} has no expert return for {env_id}; "
            f"run `python -m lab.table` once its expert exists"
        )
    return float(row["random_mean"]), float(row["expert_mean"])


def references_or_nan(env_id: str, demos: Demos | None = None) -> tuple[float, float]:
    """reference_returns; for a task without a Table 1 row, the reference returns that the
    demonstrations carry (a Minari dataset's), with a note; else (NaN, NaN) with a note: any
    Box task can be learned, a task without an expert just has no normalised score."""
    try:
        return reference_returns(env_id)
    except UserError as missing:
        if demos is not None and demos.reference_returns is not None:
            source = demos.source or demos.path
            print(f"note: normalised score from {source}'s reference returns", flush=True)
            return demos.reference_returns
        print(f"note: no normalised score ({missing})", flush=True)
        return math.nan, math.nan


def normalized_score(value: float, references: tuple[float, float]) -> float:
    """The paper's normalised score (R - R_random) / (R_expert - R_random)."""
    random_return, expert_return = references
    return (value - random_return) / (expert_return - random_return)


# === Command line: python expert.py {demos,import-minari,check-demos} ===


def writable_out(path, force: bool) -> Path:
    """--out, checked before any work: a file name under directories, and an existing file
    only with --force (demonstrations are not replaced without a word)."""
    path = Path(path)
    if path.is_dir():
        raise UserError(f"--out {path} is a directory; give a file name")
    if any(parent.exists() and not parent.is_dir() for parent in path.parents):
        raise UserError(f"--out {path} lies under a file")
    if path.exists() and not force:
        raise UserError(f"--out {path} exists; give --force to replace it")
    return path


def cli_demos(args) -> None:
    default = default_demos_path(args.env, args.trajectories, args.sampling, args.seed)
    out = writable_out(args.out or default, args.force)
    expert = load_expert(args.env, Path(args.expert)) if args.expert else None
    demos = make_demos(args.env, args.trajectories, args.sampling, args.seed, expert=expert)
    write_demos(out, demos)
    print(
        f"{out}: {len(demos['observations'])} triplets from {args.trajectories} "
        f"{args.sampling} trajectories, expert returns {np.round(demos['returns'], 1).tolist()}"
        f", dropped episodes (expert fell or scored below {float(demos['min_return']):.0f}): "
        f"{len(demos['dropped_episode_seeds'])}"
    )


def cli_import_minari(args) -> None:
    out = writable_out(args.out, args.force)
    demos = import_minari(args.dataset_id, args.env, args.trajectories, args.sampling, args.seed)
    write_demos(out, demos)
    print(
        f"{args.out}: {len(demos['observations'])} triplets from {len(demos['returns'])} "
        f"episodes of {args.dataset_id}"
    )


def cli_check_demos(args) -> None:
    demos = load_demos(Path(args.file), args.env)
    r, assumed = demos.returns, ASSUMED * demos.terminals_assumed
    returns = "unknown" if r is None else f"{r.mean():.1f} ± {r.std():.1f}"
    print(
        f"{args.file}: {len(demos)} valid triplets for {args.env} "
        f"({demos.sampling or 'unknown'} sampling, {demos.trajectories or '?'} trajectories, "
        f"expert return {returns}, {int(demos.terminals.sum())} terminal){assumed}"
    )


def parse(argv: list[str]) -> argparse.Namespace:
    parser = harness.CommandLineParser(prog="expert.py", description=__doc__.splitlines()[0])
    commands = parser.add_subparsers(dest="command", required=True)
    count = harness.positive_int

    demos = commands.add_parser("demos", help="write expert (s, a, s') demonstrations")
    demos.add_argument("--env", required=True)
    demos.add_argument("--trajectories", type=count, default=4)
    sparse_or_dense = "sparse: 100 random triplets per trajectory; dense: all 1000"
    demos.add_argument("--sampling", choices=SAMPLING_MODES, default="sparse", help=sparse_or_dense)
    demos.add_argument("--seed", type=harness.seed_number, default=0)
    demos.add_argument("--expert", help="expert file (default: experts/<env>.npz)")
    demos.add_argument("--out", help="default: demos/<env>-<sampling>-<n>traj-seed<seed>.npz")
    demos.add_argument("--force", action="store_true", help="replace an existing --out file")
    demos.set_defaults(handler=cli_demos)

    converts = "convert a locally stored Minari dataset to a demonstration file"
    minari = commands.add_parser("import-minari", help=converts)
    minari.add_argument("dataset_id", help="e.g. mujoco/hopper/expert-v0")
    minari.add_argument("--env", required=True, help="environment the triplets are for")
    minari.add_argument("--out", required=True)
    minari.add_argument("--trajectories", type=count, help="the first N episodes (default: all)")
    minari.add_argument("--sampling", choices=SAMPLING_MODES, default="dense")
    minari.add_argument("--seed", type=harness.seed_number, default=0)
    minari.add_argument("--force", action="store_true", help="replace an existing --out file")
    minari.set_defaults(handler=cli_import_minari)

    check = commands.add_parser("check-demos", help="validate a demonstration file")
    check.add_argument("file")
    check.add_argument("--env", required=True)
    check.set_defaults(handler=cli_check_demos)
    return parser.parse_args(argv)


def main(argv: list[str] | None = None) -> int:
    return harness.cli_main(argv, parse, lambda args, _: args.handler(args), checkpoints=False)


if __name__ == "__main__":
    sys.exit(main())
