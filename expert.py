"""Experts for the imitation tasks: train them, ship them, evaluate them, and write demonstrations.

The paper (Sasaki et al., ICLR 2019, Sec. 5.1) trains its experts with TRPO and never ships
them. This project must run offline on a fresh machine, so it trains its own experts here with
Augmented Random Search (Mania, Guy & Recht, 2018, https://arxiv.org/abs/1803.07055),
Algorithm 2, variant V2-t, which needs no autodiff and runs its rollouts in parallel.

Symbols of the ARS paper and where they live:

    M          policy matrix, (dim A, dim S)             -> ``weights``
    mu, Sigma  running mean and diagonal covariance of   -> ``ObservationStatistics``
               the states visited during training (V2)
    alpha      step size                                 -> ``ARSConfig.step_size``
    N          directions sampled per iteration          -> ``ARSConfig.directions``
    b          top directions used in the update (V2-t)  -> ``ARSConfig.top``
    nu         exploration noise                         -> ``ARSConfig.noise``
    delta_k    direction, an i.i.d. N(0, 1) matrix       -> ``deltas[k]``
    sigma_R    std of the 2b rewards used in the update  -> ``reward_std``

Policy: ``a = clip(M @ ((s - mu) / sqrt(diag Sigma)), low, high)``, deterministic.

Files:
    experts/<env>.npz    a shipped expert: M, mu, std (ARS) or a policy network (SAC, sac.py),
                         action bounds, and a JSON ``metadata`` record of the training
                         commands, seed, env steps and wall time
    experts/table.json   Table 1 for the -v4 tasks (``python expert.py table``)
    demos/*.npz          demonstrations: ``observations``, ``actions`` (env units),
                         ``next_observations``, ``terminals`` (is s' terminal), ``env_id``,
                         ``returns`` (per trajectory), ``seed``, ``sampling``, ``trajectories``

Subcommands (``python expert.py -h``): ``train``, ``demos``, ``check-demos``,
``import-minari``, ``table``. Errors that a user can cause end in one line ``error: ...`` on
stderr and exit status 2.
"""

from __future__ import annotations

import argparse
import ast
import contextlib
import dataclasses
import inspect
import json
import math
import multiprocessing
import os
import shlex
import signal
import sys
import time
import warnings
import zipfile
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import gymnasium as gym
import numpy as np

import nets

REPO_DIR = Path(__file__).resolve().parent
EXPERTS_DIR = REPO_DIR / "experts"
CHECKPOINTS_DIR = EXPERTS_DIR / "checkpoints"
DEMOS_DIR = REPO_DIR / "demos"
TABLE_PATH = EXPERTS_DIR / "table.json"

# The paper's five tasks, on the MuJoCo versions gymnasium still ships (-v1 is long gone).
PAPER_TASKS = ("Hopper-v4", "HalfCheetah-v4", "Walker2d-v4", "Ant-v4", "Humanoid-v4")

# Sec. 5.1: expert trajectories are 1000 steps long; sparse sampling keeps 100 of each.
TRAJECTORY_STEPS = 1000
SPARSE_TRIPLETS_PER_TRAJECTORY = 100
SAMPLING_MODES = ("sparse", "dense")

# Demonstration actions may come from float32 files or other tools; accept tiny overshoots.
ACTION_BOUND_TOLERANCE = 1e-4


class UserError(Exception):
    """An error the user caused (bad flag, bad file, wrong environment): one line, exit 2."""


# ---------------------------------------------------------------------------------------------
# Environments
# ---------------------------------------------------------------------------------------------


@contextlib.contextmanager
def _quiet_mujoco_compiler():
    """Drop MuJoCo's "settotalmass is deprecated" compiler warning while a model is built.

    gymnasium's HalfCheetah-v4 asset uses that attribute; MuJoCo 3 then writes the warning to
    stderr and to MUJOCO_LOG.TXT in the working directory on every make. Other MuJoCo
    warnings are passed on as Python warnings.
    """
    try:
        import mujoco
    except ImportError:
        yield
        return

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
    """``gym.make`` for continuous-control tasks, refusing what the method cannot handle.

    The learner needs a flat (1-D Box) state and a Box action space with finite bounds,
    because it maps ``tanh`` outputs in [-1, 1] onto ``[low, high]``.
    """
    with warnings.catch_warnings(), _quiet_mujoco_compiler():
        # gymnasium says "-v4 is out of date" on every make; the paper's tasks are -v4 on purpose.
        warnings.filterwarnings("ignore", message=".*is out of date.*")
        try:
            env = gym.make(env_id, **kwargs)
        except gym.error.Error as error:
            raise UserError(f"cannot make environment {env_id!r}: {error}") from None
    observation_space, action_space = env.observation_space, env.action_space
    if not (isinstance(observation_space, gym.spaces.Box) and len(observation_space.shape) == 1):
        env.close()
        raise UserError(
            f"{env_id} needs a flat (1-D Box) observation space; it has {observation_space}"
        )
    if not (
        isinstance(action_space, gym.spaces.Box)
        and len(action_space.shape) == 1
        and np.all(np.isfinite(action_space.low))
        and np.all(np.isfinite(action_space.high))
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


# ---------------------------------------------------------------------------------------------
# The expert policy: a linear map of normalised states (ARS V2), or a SAC policy network
# ---------------------------------------------------------------------------------------------

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
    - ``sac-mlp``: the mean action of a SAC policy (sac.py), ``a = low + (tanh(m(s)) + 1)
      (high - low)/2`` with ``m(s)`` the first dim A outputs of ``network`` (the others are
      its log std, unused here); ``weights``, ``obs_mean`` and ``obs_std`` are None.
    """

    env_id: str
    weights: np.ndarray | None  # M, (dim A, dim S)
    obs_mean: np.ndarray | None  # mu, (dim S,)
    obs_std: np.ndarray | None  # sqrt(diag Sigma), (dim S,)
    action_low: np.ndarray  # (dim A,)
    action_high: np.ndarray  # (dim A,)
    metadata: dict = dataclasses.field(default_factory=dict)
    network: nets.MLP | None = None  # SAC: state -> (mean, log std), (dim S) -> (2 dim A)

    @property
    def kind(self) -> str:
        return ARS_LINEAR if self.network is None else SAC_MLP

    def act(self, observation: np.ndarray) -> np.ndarray:
        """Deterministic action for one state, within the action bounds."""
        if self.network is None:
            normalised = (np.asarray(observation, dtype=np.float64) - self.obs_mean) / self.obs_std
            return np.clip(self.weights @ normalised, self.action_low, self.action_high)  # (dim A,)
        state = np.asarray(observation, dtype=self.network.dtype)[None]  # (1, dim S)
        mean = self.network.forward(state)[0][0, : len(self.action_low)]  # (dim A,)
        return tanh_to_bounds(np.tanh(mean).astype(np.float64), self.action_low, self.action_high)

    __call__ = act

    def save(self, path: Path, **metadata) -> None:
        """Write the policy and its provenance (command, seed, steps, wall time, ...).

        An ARS file holds ``weights``, ``obs_mean``, ``obs_std`` (the format of the first
        shipped experts, which has no ``kind``); a SAC file holds ``kind`` = "sac-mlp",
        the layer ``sizes`` and the network's ``policy/W0``, ``policy/b0``, ... .
        """
        record = {**self.metadata, **metadata}
        if self.network is None:
            arrays = dict(weights=self.weights, obs_mean=self.obs_mean, obs_std=self.obs_std)
        else:
            arrays = dict(
                kind=np.array(SAC_MLP),
                sizes=np.array(self.network.sizes),
                **self.network.state("policy"),
            )
        nets.save_arrays(
            path,
            dict(
                env_id=np.array(self.env_id),
                **arrays,
                action_low=self.action_low,
                action_high=self.action_high,
                metadata=np.array(json.dumps(record, sort_keys=True)),
            ),
        )


def default_expert_path(env_id: str) -> Path:
    """``<repo>/experts/<env_id>.npz``, found from this file, not from the working directory."""
    return EXPERTS_DIR / f"{env_id}.npz"


def load_expert(env_id: str, path: Path | None = None) -> ExpertPolicy:
    """Load the shipped expert for ``env_id`` (or the one at ``path``), checking it fits the env.

    Files without a ``kind`` are ARS linear policies (every file written before SAC).
    """
    path = Path(path) if path is not None else default_expert_path(env_id)
    if not path.exists():
        raise UserError(
            f"no expert for {env_id} at {path}; train one with "
            f"`python expert.py train --env {env_id}`"
        )
    try:
        with np.load(path, allow_pickle=False) as file:
            kind = str(file["kind"]) if "kind" in file.files else ARS_LINEAR
            common = dict(
                env_id=str(file["env_id"]),
                action_low=np.asarray(file["action_low"], dtype=np.float64),
                action_high=np.asarray(file["action_high"], dtype=np.float64),
                metadata=json.loads(str(file["metadata"])),
            )
            if kind == ARS_LINEAR:
                policy = ExpertPolicy(
                    weights=np.asarray(file["weights"], dtype=np.float64),
                    obs_mean=np.asarray(file["obs_mean"], dtype=np.float64),
                    obs_std=np.asarray(file["obs_std"], dtype=np.float64),
                    **common,
                )
            elif kind == SAC_MLP:
                sizes = [int(size) for size in file["sizes"]]
                params = {
                    key.removeprefix("policy/"): file[key]
                    for key in file.files
                    if key.startswith("policy/")
                }
                policy = ExpertPolicy(
                    weights=None,
                    obs_mean=None,
                    obs_std=None,
                    network=nets.MLP(sizes, "identity", params),
                    **common,
                )
            else:
                raise ValueError(f"unknown expert kind {kind!r}; expected one of {EXPERT_KINDS}")
    except (OSError, ValueError, KeyError, EOFError, zipfile.BadZipFile) as error:
        raise UserError(f"{path}: not a valid expert file ({error})") from None
    if policy.env_id != env_id:
        raise UserError(f"{path}: expert was trained on {policy.env_id}, not {env_id}")
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


# ---------------------------------------------------------------------------------------------
# Evaluation with the true environment reward
# ---------------------------------------------------------------------------------------------


def run_episode(env: gym.Env, policy_fn: Callable, seed: int) -> tuple[float, int]:
    """One episode from ``env.reset(seed=seed)``; returns (true return, steps)."""
    observation, _ = env.reset(seed=seed)
    episode_return, steps, done = 0.0, 0, False
    while not done:
        observation, reward, terminated, truncated, _ = env.step(policy_fn(observation))
        episode_return += float(reward)
        steps += 1
        done = terminated or truncated
    return episode_return, steps


def evaluate(env_id: str, policy_fn: Callable, episodes: int, seed: int) -> np.ndarray:
    """Returns of ``episodes`` seeded episodes (``env.reset(seed=seed + i)``), true reward."""
    env = make_env(env_id)
    try:
        return np.array([run_episode(env, policy_fn, seed + i)[0] for i in range(episodes)])
    finally:
        env.close()


def random_policy_returns(env_id: str, episodes: int, seed: int) -> np.ndarray:
    """Returns of uniform random actions; the action space is seeded like the resets."""
    env = make_env(env_id)
    try:
        returns = []
        for i in range(episodes):
            env.action_space.seed(seed + i)
            returns.append(run_episode(env, lambda _: env.action_space.sample(), seed + i)[0])
        return np.array(returns)
    finally:
        env.close()


# ---------------------------------------------------------------------------------------------
# Demonstrations: (s, a, s') triplets of 1000-step expert trajectories (Sec. 5.1)
# ---------------------------------------------------------------------------------------------

DEMO_ARRAY_KEYS = ("observations", "actions", "next_observations", "terminals")


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

    def __len__(self) -> int:
        return len(self.observations)


def default_demos_path(env_id: str, trajectories: int, sampling: str, seed: int) -> Path:
    """Cache location ``<repo>/demos/<env>-<sampling>-<n>traj-seed<seed>.npz`` (git-ignored)."""
    return DEMOS_DIR / f"{env_id}-{sampling}-{trajectories}traj-seed{seed}.npz"


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
    to `demo_return_floor` and an expert of the caller's to no floor. *sparse* keeps
    100 triplets per trajectory, drawn uniformly without replacement; *dense* keeps all 1000.
    Everything comes from one Generator seeded with ``seed``, split into one stream for the
    reset seeds and one for subsampling, so that sparse and dense demonstrations with the same
    seed come from the same trajectories (sparse is a subset of dense).
    """
    if sampling not in SAMPLING_MODES:
        raise UserError(f"--sampling must be one of {', '.join(SAMPLING_MODES)}, got {sampling!r}")
    if trajectories < 1:
        raise UserError(f"--trajectories must be at least 1, got {trajectories}")
    make_env(env_id).close()  # a wrong environment is reported as such, not as "no expert"
    if min_return is None:
        min_return = demo_return_floor(env_id) if expert is None else -math.inf
    expert = expert if expert is not None else load_expert(env_id)
    max_attempts = max_attempts if max_attempts is not None else 10 * trajectories
    episode_rng, subsample_rng = np.random.default_rng(seed).spawn(2)
    env = make_env(env_id)
    observations, actions, next_observations, returns = [], [], [], []
    used_seeds, dropped_seeds = [], []
    try:
        while len(returns) < trajectories:
            if len(used_seeds) + len(dropped_seeds) >= max_attempts:
                floor = (
                    f" with a return of at least {min_return:.0f}"
                    if math.isfinite(min_return)
                    else ""
                )
                raise UserError(
                    f"the {env_id} expert lasted {TRAJECTORY_STEPS} steps{floor} in only "
                    f"{len(returns)} of {max_attempts} episodes; it is not good enough for demos"
                )
            episode_seed = int(episode_rng.integers(0, 2**31 - 1))
            states, episode_actions, episode_return = [], [], 0.0
            observation, _ = env.reset(seed=episode_seed)
            for _ in range(TRAJECTORY_STEPS):
                action = np.asarray(expert.act(observation), dtype=np.float64)
                states.append(observation)
                episode_actions.append(action)
                observation, reward, terminated, truncated, _ = env.step(action)
                episode_return += float(reward)
                if terminated or truncated:
                    break
            states.append(observation)
            if len(episode_actions) < TRAJECTORY_STEPS or terminated or episode_return < min_return:
                dropped_seeds.append(episode_seed)
                continue
            states = np.asarray(states)  # (1001, dim S): s_0 .. s_1000
            if sampling == "sparse":
                keep = np.sort(
                    subsample_rng.choice(
                        TRAJECTORY_STEPS, SPARSE_TRIPLETS_PER_TRAJECTORY, replace=False
                    )
                )
            else:
                keep = np.arange(TRAJECTORY_STEPS)
            observations.append(states[:-1][keep])
            actions.append(np.asarray(episode_actions)[keep])
            next_observations.append(states[1:][keep])
            returns.append(episode_return)
            used_seeds.append(episode_seed)
    finally:
        env.close()
    count = sum(len(chunk) for chunk in observations)
    return dict(
        observations=np.concatenate(observations).astype(np.float32),
        actions=np.concatenate(actions).astype(np.float32),
        next_observations=np.concatenate(next_observations).astype(np.float32),
        # Every kept trajectory ran into the time limit, which is truncation, not termination.
        terminals=np.zeros(count, dtype=bool),
        env_id=np.array(env_id),
        returns=np.array(returns),
        seed=np.array(seed),
        sampling=np.array(sampling),
        trajectories=np.array(trajectories),
        episode_seeds=np.array(used_seeds, dtype=np.int64),
        dropped_episode_seeds=np.array(dropped_seeds, dtype=np.int64),
        min_return=np.array(min_return),
        expert=np.array(json.dumps(expert.metadata.get("commands", []))),
    )


def write_demos(path: Path, demos: dict) -> None:
    """Validate the triplets against their environment, then write them atomically."""
    validate_demos(demos, str(demos["env_id"]), Path(path))
    nets.save_arrays(path, demos)


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
    """The default demonstration file, made from the shipped expert the first time.

    A cached file with a trajectory below `demo_return_floor` (made before that rule) is
    made again."""
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


def validate_demos(arrays: dict, env_id: str, path: Path) -> Demos:
    """Check triplets against ``env_id``; any problem is one UserError naming the file."""

    def fail(problem: str) -> UserError:
        return UserError(f"{path}: {problem}")

    missing = [key for key in DEMO_ARRAY_KEYS if key not in arrays]
    if missing:
        raise fail(f"missing key(s) {', '.join(missing)}")
    recorded_env = str(arrays["env_id"]) if "env_id" in arrays else None
    if recorded_env is not None and recorded_env != env_id:
        raise fail(f"demonstrations are for {recorded_env}, not {env_id}")
    try:
        observations = np.asarray(arrays["observations"], dtype=np.float32)
        actions = np.asarray(arrays["actions"], dtype=np.float32)
        next_observations = np.asarray(arrays["next_observations"], dtype=np.float32)
        terminals = np.asarray(arrays["terminals"]).astype(bool)
    except (TypeError, ValueError) as error:
        raise fail(f"arrays are not numeric ({error})") from None
    env = make_env(env_id)
    dim_s, dim_a = env_dimensions(env)
    low, high = env.action_space.low, env.action_space.high
    env.close()
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
    lengths = {len(observations), len(actions), len(next_observations), len(terminals)}
    if len(lengths) != 1 or terminals.ndim != 1:
        raise fail(
            f"mismatched lengths: {len(observations)} observations, {len(actions)} "
            f"actions, {len(next_observations)} next_observations, "
            f"{len(terminals)} terminals"
        )
    tolerance = ACTION_BOUND_TOLERANCE * np.maximum(1.0, np.abs(np.stack([low, high])))
    if np.any(actions < low - tolerance[0]) or np.any(actions > high + tolerance[1]):
        raise fail(
            f"actions outside the action bounds [{low.min():g}, {high.max():g}] of "
            f"{env_id} (largest |a| = {np.abs(actions).max():g})"
        )

    def optional(key, convert):
        return convert(arrays[key]) if key in arrays else None

    return Demos(
        observations=observations,
        actions=actions,
        next_observations=next_observations,
        terminals=terminals,
        env_id=recorded_env,
        returns=optional("returns", np.asarray),
        seed=optional("seed", int),
        sampling=optional("sampling", str),
        trajectories=optional("trajectories", int),
        path=path,
    )


def load_demos(path: Path, env_id: str) -> Demos:
    """Load and validate a demonstration file for ``env_id`` (see :func:`validate_demos`)."""
    path = Path(path)
    if not path.exists():
        raise UserError(f"{path}: no such demonstration file")
    try:
        # Read every member now: a truncated file may open fine and fail on first access.
        with np.load(path, allow_pickle=False) as file:
            arrays = {key: file[key] for key in file.files}
    except (OSError, ValueError, EOFError, zipfile.BadZipFile, KeyError) as error:
        raise UserError(f"{path}: not a valid .npz file ({error})") from None
    return validate_demos(arrays, env_id, path)


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
    Episodes of any length are kept (the file's returns record how good they were).
    """
    try:
        import minari
    except ImportError:
        raise UserError(
            "import-minari needs the minari package: pip install 'minari[hdf5]'"
        ) from None
    if sampling not in SAMPLING_MODES:
        raise UserError(f"--sampling must be one of {', '.join(SAMPLING_MODES)}, got {sampling!r}")
    try:
        dataset = minari.load_dataset(dataset_id, download=False)
    except Exception as error:  # minari raises bare Exceptions/FileNotFoundError/ValueError
        raise UserError(
            f"cannot load Minari dataset {dataset_id!r} locally "
            f"(MINARI_DATASETS_PATH={os.environ.get('MINARI_DATASETS_PATH', '~')}): "
            f"{error}"
        ) from None
    rng = np.random.default_rng(seed)
    observations, actions, next_observations, terminals, returns = [], [], [], [], []
    for episode in dataset.iterate_episodes():
        if trajectories is not None and len(returns) >= trajectories:
            break
        episode_observations = np.asarray(episode.observations)
        if episode_observations.dtype == object or episode_observations.ndim != 2:
            raise UserError(f"{dataset_id}: observations are not flat arrays")
        steps = len(episode.actions)
        keep = np.arange(steps)
        if sampling == "sparse" and steps > SPARSE_TRIPLETS_PER_TRAJECTORY:
            keep = np.sort(rng.choice(steps, SPARSE_TRIPLETS_PER_TRAJECTORY, replace=False))
        observations.append(episode_observations[:-1][keep])
        actions.append(np.asarray(episode.actions)[keep])
        next_observations.append(episode_observations[1:][keep])
        terminals.append(np.asarray(episode.terminations, dtype=bool)[keep])
        returns.append(float(np.sum(episode.rewards)))
    if not returns:
        raise UserError(f"Minari dataset {dataset_id!r} has no episodes")

    def stack(chunks, dtype):
        return np.concatenate(chunks).astype(dtype)

    return dict(
        observations=stack(observations, np.float32),
        actions=stack(actions, np.float32),
        next_observations=stack(next_observations, np.float32),
        terminals=stack(terminals, bool),
        env_id=np.array(env_id),
        returns=np.array(returns),
        seed=np.array(seed),
        sampling=np.array(sampling),
        trajectories=np.array(len(returns)),
        source=np.array(f"minari:{dataset_id}"),
    )


# ---------------------------------------------------------------------------------------------
# Reference returns (Table 1): random policy and expert, the normalised score's two ends
# ---------------------------------------------------------------------------------------------


def numeric_platform() -> dict:
    """What decides the last bits of a return: library versions and the BLAS kernel in use.

    The returns of the SAC experts (float32 networks) on Ant-v4 change with the kernel that
    OpenBLAS picks for the CPU (for example 4932 with SkylakeX, 4454 with Haswell over
    the same 10 seeded episodes) because an episode ends when rounding tips the robot out of
    its healthy range; OPENBLAS_CORETYPE chooses the kernel.
    """
    import mujoco
    from threadpoolctl import threadpool_info

    blas = [pool for pool in threadpool_info() if pool["user_api"] == "blas"]
    return dict(
        numpy=np.__version__,
        mujoco=mujoco.__version__,
        gymnasium=gym.__version__,
        blas_kernel=blas[0].get("architecture", "unknown") if blas else "none",
    )


def measure_table(
    episodes: int = 10, seed: int = 0, tasks=PAPER_TASKS, log: Callable[[str], None] = print
) -> dict:
    """dim S, dim A, random and expert returns (mean, std over seeded episodes) per task."""
    table = {}
    for env_id in tasks:
        env = make_env(env_id)
        dim_s, dim_a = env_dimensions(env)
        env.close()
        random_returns = random_policy_returns(env_id, episodes, seed)
        row = dict(
            dim_s=dim_s,
            dim_a=dim_a,
            episodes=episodes,
            seed=seed,
            random_mean=float(random_returns.mean()),
            random_std=float(random_returns.std()),
            expert_mean=None,
            expert_std=None,
            measured_with=numeric_platform(),
        )
        if default_expert_path(env_id).exists():
            expert_returns = evaluate(env_id, load_expert(env_id).act, episodes, seed)
            row.update(
                expert_mean=float(expert_returns.mean()), expert_std=float(expert_returns.std())
            )
        log(f"{env_id}: random {row['random_mean']:.2f}, expert {row['expert_mean']}")
        table[env_id] = row
    return table


def table_markdown(table: dict) -> str:
    lines = ["| Task | dim S | dim A | Random policy | Expert |", "|---|---:|---:|---:|---:|"]
    for env_id, row in table.items():
        expert = (
            f"{row['expert_mean']:.2f} ± {row['expert_std']:.2f}"
            if row["expert_mean"] is not None
            else "missing (not trained yet)"
        )
        lines.append(
            f"| {env_id} | {row['dim_s']} | {row['dim_a']} | "
            f"{row['random_mean']:.2f} ± {row['random_std']:.2f} | {expert} |"
        )
    return "\n".join(lines)


def reference_returns(env_id: str, table_path: Path = TABLE_PATH) -> tuple[float, float]:
    """(R_random, R_expert) for the normalised score (R - R_random) / (R_expert - R_random)."""
    try:
        table = json.loads(Path(table_path).read_text())
    except FileNotFoundError:
        raise UserError(f"{table_path} is missing; run `python expert.py table`") from None
    except (OSError, ValueError) as error:
        raise UserError(f"{table_path}: not a valid table ({error})") from None
    row = table.get(env_id)
    if row is None or row.get("expert_mean") is None:
        raise UserError(
            f"{table_path} has no expert return for {env_id}; "
            f"run `python expert.py table` once its expert exists"
        )
    return float(row["random_mean"]), float(row["expert_mean"])


def references_or_nan(env_id: str) -> tuple[float, float]:
    """reference_returns, or (NaN, NaN) with a note: any Box task can be learned, a task
    without an expert just has no normalised score."""
    try:
        return reference_returns(env_id)
    except UserError as missing:
        print(f"note: no normalised score ({missing})", flush=True)
        return math.nan, math.nan


def normalized_score(value: float, references: tuple[float, float]) -> float:
    """The paper's normalised score (R - R_random) / (R_expert - R_random)."""
    random_return, expert_return = references
    return (value - random_return) / (expert_return - random_return)


# ---------------------------------------------------------------------------------------------
# ARS V2-t trainer (Mania, Guy & Recht 2018, Algorithm 2)
# ---------------------------------------------------------------------------------------------


@dataclass
class ARSConfig:
    """Hyperparameters of ARS V2-t; per-task defaults in ``ARS_DEFAULTS`` (rl-zoo ``ars.yml``)."""

    step_size: float = 0.02
    """alpha: step size of the update of M."""
    directions: int = 8
    """N: directions delta_k sampled per iteration (2N rollouts: M + nu delta, M - nu delta)."""
    top: int = 4
    """b: best directions, ranked by max(r+, r-), that enter the update (V2-t)."""
    noise: float = 0.03
    """nu: scale of the exploration perturbations."""
    survival_bonus: float = 0.0
    """Subtracted from every training reward, so that merely staying alive earns nothing."""
    steps: int = 10_000_000
    """Training budget in environment steps (perturbed rollouts only, not evaluations)."""
    eval_every: int = 10
    """Evaluate the unperturbed policy every this many iterations."""
    eval_episodes: int = 5
    """Episodes per evaluation; the best evaluated policy is the one shipped."""


# rl-baselines3-zoo ars.yml, "closest to the original paper", plus budgets.
ARS_DEFAULTS = {
    "Hopper-v4": dict(
        step_size=0.01, directions=8, top=4, noise=0.025, survival_bonus=1.0, steps=7_000_000
    ),
    "HalfCheetah-v4": dict(
        step_size=0.02, directions=32, top=4, noise=0.03, survival_bonus=0.0, steps=12_000_000
    ),
    "Walker2d-v4": dict(
        step_size=0.03, directions=40, top=30, noise=0.025, survival_bonus=1.0, steps=75_000_000
    ),
    "Ant-v4": dict(
        step_size=0.015, directions=60, top=20, noise=0.025, survival_bonus=1.0, steps=75_000_000
    ),
    "Humanoid-v4": dict(
        step_size=0.02, directions=256, top=256, noise=0.0075, survival_bonus=5.0, steps=25_000_000
    ),
}


def ars_config_for(env_id: str, **overrides) -> ARSConfig:
    """Task defaults, then any explicit overrides (``None`` means "not given")."""
    values = {**ARS_DEFAULTS.get(env_id, {})}
    values.update({key: value for key, value in overrides.items() if value is not None})
    return ARSConfig(**values)


class ObservationStatistics:
    """Running mu and diag(Sigma) of all states visited in training (ARS V2).

    Kept as (count, mean, sum of squared deviations) and merged with Chan et al.'s parallel
    formula, so that merging per-rollout statistics in a fixed order is exact and deterministic.
    """

    def __init__(self, dim: int):
        self.count = 0
        self.mean = np.zeros(dim)
        self.squared_deviations = np.zeros(dim)

    def merge(self, count: int, mean: np.ndarray, squared_deviations: np.ndarray) -> None:
        if count == 0:
            return
        total = self.count + count
        delta = mean - self.mean
        self.mean = self.mean + delta * count / total
        self.squared_deviations = (
            self.squared_deviations + squared_deviations + delta**2 * self.count * count / total
        )
        self.count = total

    def std(self) -> np.ndarray:
        """sqrt(diag Sigma); 1 where a coordinate has not varied yet (so it stays unscaled)."""
        if self.count < 2:
            return np.ones_like(self.mean)
        variance = self.squared_deviations / (self.count - 1)
        return np.where(variance > 1e-8, np.sqrt(variance), 1.0)


# Each worker process keeps its own environment between tasks (made once by the initializer).
_worker_env: gym.Env | None = None


def _init_worker(env_id: str) -> None:
    global _worker_env
    # Ctrl-C reaches the whole process group; only the parent acts on it (it checkpoints
    # and then closes the pool), so a worker is never cut off mid-task.
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    _worker_env = make_env(env_id)


def _rollout_task(task: tuple) -> tuple:
    return rollout(_worker_env, *task)


def rollout(
    env: gym.Env,
    weights: np.ndarray,
    obs_mean: np.ndarray,
    obs_std: np.ndarray,
    seed: int,
    survival_bonus: float,
    collect_states: bool,
) -> tuple:
    """One episode of the linear policy from ``reset(seed=seed)``.

    Returns (return minus survival bonus per step, steps, true return, state statistics) where
    the statistics are (count, mean, squared deviations) of the states acted upon, or None.
    """
    low, high = env.action_space.low, env.action_space.high
    observation, _ = env.reset(seed=seed)
    states, true_return, steps, done = [], 0.0, 0, False
    while not done:
        if collect_states:
            states.append(observation)
        action = np.clip(weights @ ((observation - obs_mean) / obs_std), low, high)  # (dim A,)
        observation, reward, terminated, truncated, _ = env.step(action)
        true_return += float(reward)
        steps += 1
        done = terminated or truncated
    statistics = None
    if collect_states:
        visited = np.asarray(states, dtype=np.float64)  # (T, dim S)
        mean = visited.mean(axis=0)  # (dim S,)
        statistics = (len(visited), mean, ((visited - mean) ** 2).sum(axis=0))
    return true_return - survival_bonus * steps, steps, true_return, statistics


class RolloutRunner:
    """Runs rollout tasks in ``workers`` processes (or in this process when workers == 1)."""

    def __init__(self, env_id: str, workers: int):
        self.pool = None
        if workers > 1:
            # spawn: a clean interpreter per worker, safe whatever threads the parent holds.
            context = multiprocessing.get_context("spawn")
            self.pool = context.Pool(workers, initializer=_init_worker, initargs=(env_id,))
        else:
            self.env = make_env(env_id)

    def run(self, tasks: list[tuple]) -> list[tuple]:
        if self.pool is not None:
            return self.pool.map(_rollout_task, tasks, chunksize=1)
        return [rollout(self.env, *task) for task in tasks]

    def close(self) -> None:
        if self.pool is not None:
            self.pool.close()
            self.pool.join()
        else:
            self.env.close()

    def __enter__(self) -> RolloutRunner:
        return self

    def __exit__(self, error_type, error, traceback) -> None:
        if self.pool is not None and error_type is not None:
            self.pool.terminate()  # e.g. Ctrl-C: do not wait for workers that were interrupted
        self.close()


@dataclass
class ARSState:
    """Everything needed to continue a run exactly: the checkpoint's contents."""

    env_id: str
    seed: int
    config: ARSConfig
    weights: np.ndarray  # M, (dim A, dim S)
    statistics: ObservationStatistics
    rng: np.random.Generator
    iteration: int = 0
    env_steps: int = 0
    wall_seconds: float = 0.0
    best_return: float = -np.inf
    best_return_std: float = 0.0
    best_weights: np.ndarray | None = None
    best_obs_mean: np.ndarray | None = None
    best_obs_std: np.ndarray | None = None
    best_env_steps: int = 0
    commands: tuple[str, ...] = ()

    def save(self, path: Path) -> None:
        best = self.best_weights is not None
        nets.save_arrays(
            path,
            dict(
                env_id=np.array(self.env_id),
                seed=np.array(self.seed),
                config=np.array(json.dumps(dataclasses.asdict(self.config))),
                weights=self.weights,
                stat_count=np.array(self.statistics.count),
                stat_mean=self.statistics.mean,
                stat_squared_deviations=self.statistics.squared_deviations,
                rng_state=np.array(json.dumps(self.rng.bit_generator.state)),
                iteration=np.array(self.iteration),
                env_steps=np.array(self.env_steps),
                wall_seconds=np.array(self.wall_seconds),
                best_return=np.array(self.best_return),
                best_return_std=np.array(self.best_return_std),
                best_weights=self.best_weights if best else np.zeros(0),
                best_obs_mean=self.best_obs_mean if best else np.zeros(0),
                best_obs_std=self.best_obs_std if best else np.zeros(0),
                best_env_steps=np.array(self.best_env_steps),
                commands=np.array(json.dumps(list(self.commands))),
            ),
        )

    @classmethod
    def load(cls, path: Path) -> ARSState:
        try:
            with np.load(path, allow_pickle=False) as file:
                statistics = ObservationStatistics(file["stat_mean"].shape[0])
                statistics.count = int(file["stat_count"])
                statistics.mean = file["stat_mean"]
                statistics.squared_deviations = file["stat_squared_deviations"]
                rng = np.random.default_rng()
                rng.bit_generator.state = json.loads(str(file["rng_state"]))
                best = file["best_weights"].size > 0
                return cls(
                    env_id=str(file["env_id"]),
                    seed=int(file["seed"]),
                    config=ARSConfig(**json.loads(str(file["config"]))),
                    weights=file["weights"],
                    statistics=statistics,
                    rng=rng,
                    iteration=int(file["iteration"]),
                    env_steps=int(file["env_steps"]),
                    wall_seconds=float(file["wall_seconds"]),
                    best_return=float(file["best_return"]),
                    best_return_std=float(file["best_return_std"]),
                    best_weights=file["best_weights"] if best else None,
                    best_obs_mean=file["best_obs_mean"] if best else None,
                    best_obs_std=file["best_obs_std"] if best else None,
                    best_env_steps=int(file["best_env_steps"]),
                    commands=tuple(json.loads(str(file["commands"]))),
                )
        except (OSError, ValueError, KeyError, EOFError, zipfile.BadZipFile) as error:
            raise UserError(f"{path}: not a valid ARS checkpoint ({error})") from None


def ars_iteration(state: ARSState, runner: RolloutRunner) -> None:
    """One iteration of Algorithm 2 (V2-t), updating M and (mu, Sigma) in place."""
    config, rng = state.config, state.rng
    # mu and Sigma are frozen for the whole iteration (line 5 uses those of iteration j).
    obs_mean, obs_std = state.statistics.mean.copy(), state.statistics.std()
    # Line 4: delta_1..delta_N with i.i.d. standard normal entries, each (dim A, dim S).
    deltas = rng.standard_normal((config.directions, *state.weights.shape))  # (N, dim A, dim S)
    # Every rollout gets its own reset seed from the one Generator, so that results do not
    # depend on which worker runs which rollout, and a resumed run continues exactly.
    reset_seeds = rng.integers(0, 2**31 - 1, size=(config.directions, 2))
    tasks = []
    for k in range(config.directions):
        for sign_index, sign in enumerate((+1.0, -1.0)):
            # Line 5: pi_{j,k,+/-}(s) = (M_j +/- nu delta_k) diag(Sigma_j)^(-1/2) (s - mu_j).
            perturbed = state.weights + sign * config.noise * deltas[k]
            tasks.append(
                (
                    perturbed,
                    obs_mean,
                    obs_std,
                    int(reset_seeds[k, sign_index]),
                    config.survival_bonus,
                    True,
                )
            )
    results = runner.run(tasks)
    rewards = np.array([result[0] for result in results]).reshape(config.directions, 2)  # (N, 2)
    state.env_steps += sum(result[1] for result in results)
    # Line 8 (V2): update mu and Sigma with every state visited in this iteration, in task order.
    for result in results:
        state.statistics.merge(*result[3])
    # Line 6 (V2-t): keep the b directions with the largest max(r+, r-).
    top = np.argsort(-rewards.max(axis=1), kind="stable")[: config.top]
    # Line 7: M += alpha / (b sigma_R) sum_k (r+ - r-) delta_k, sigma_R over the 2b rewards.
    reward_std = rewards[top].std()
    if reward_std < 1e-8:
        reward_std = 1.0  # all b directions scored alike: no signal, and no division by zero
    differences = rewards[top, 0] - rewards[top, 1]  # (b,)
    step = np.tensordot(differences, deltas[top], axes=1)  # (dim A, dim S)
    state.weights = state.weights + config.step_size / (config.top * reward_std) * step
    state.iteration += 1


def evaluate_linear(state: ARSState, runner: RolloutRunner) -> np.ndarray:
    """True returns of the unperturbed policy M over ``eval_episodes`` fresh seeds.

    The seeds come from their own Generator, derived from (seed, iteration), so that how
    often one evaluates does not change the training run, and the shipped policy is not
    chosen on the fixed seeds that ``table`` reports.
    """
    obs_mean, obs_std = state.statistics.mean.copy(), state.statistics.std()
    eval_rng = np.random.default_rng([state.seed, state.iteration])
    seeds = eval_rng.integers(2**20, 2**31 - 1, size=state.config.eval_episodes)
    tasks = [(state.weights, obs_mean, obs_std, int(seed), 0.0, False) for seed in seeds]
    return np.array([result[2] for result in runner.run(tasks)])


def train(
    env_id: str,
    seed: int,
    config: ARSConfig,
    workers: int,
    checkpoint_path: Path,
    expert_path: Path,
    resume: bool = False,
    command: str = "",
    checkpoint_seconds: float = 10.0,
    log: Callable[[str], None] = print,
) -> ARSState:
    """Run ARS V2-t until ``config.steps`` environment steps; keep the best evaluated policy."""
    env = make_env(env_id)
    dim_s, dim_a = env_dimensions(env)
    action_low = env.action_space.low.astype(np.float64)
    action_high = env.action_space.high.astype(np.float64)
    env.close()
    if resume:
        if not checkpoint_path.exists():
            raise UserError(f"--resume: no checkpoint at {checkpoint_path}")
        state = ARSState.load(checkpoint_path)
        if state.env_id != env_id:
            raise UserError(f"{checkpoint_path}: checkpoint is for {state.env_id}, not {env_id}")
        # Only the budget may change on resume; anything else would not be the same run.
        state.config = dataclasses.replace(state.config, steps=config.steps)
        log(f"resumed {env_id} at iteration {state.iteration}, {state.env_steps} env steps")
    else:
        state = ARSState(
            env_id=env_id,
            seed=seed,
            config=config,
            weights=np.zeros((dim_a, dim_s)),  # M_0 = 0 (Algorithm 2, line 2)
            statistics=ObservationStatistics(dim_s),
            rng=np.random.default_rng(seed),
        )
    state.commands = (*state.commands, command)
    log(
        f"ARS V2-t on {env_id}: seed {state.seed}, {workers} workers, "
        f"{json.dumps(dataclasses.asdict(state.config))}"
    )

    def write_expert() -> None:
        policy = ExpertPolicy(
            env_id,
            state.best_weights,
            state.best_obs_mean,
            state.best_obs_std,
            action_low,
            action_high,
        )
        policy.save(
            expert_path,
            trainer="ARS V2-t (Mania, Guy & Recht 2018, Algorithm 2)",
            commands=list(state.commands),
            seed=state.seed,
            hyperparameters=dataclasses.asdict(state.config),
            env_steps=state.best_env_steps,
            wall_seconds=round(state.wall_seconds, 1),
            eval_return_mean=state.best_return,
            eval_return_std=state.best_return_std,
            eval_episodes=state.config.eval_episodes,
        )

    # A fresh run must not replace a shipped expert with a worse one: it writes only when it
    # beats the evaluation recorded in the existing file (a resumed run carries its own best).
    if not resume and expert_path.exists():
        try:
            existing = load_expert(env_id, expert_path)
            state.best_return = float(existing.metadata.get("eval_return_mean", -np.inf))
            log(
                f"{expert_path} exists (eval return {state.best_return:.1f}); "
                f"it is replaced only by a better evaluation"
            )
        except UserError:
            pass
    started, last_checkpoint = time.monotonic(), time.monotonic()
    wall_at_start = state.wall_seconds
    with RolloutRunner(env_id, workers) as runner:
        while state.env_steps < state.config.steps:
            ars_iteration(state, runner)
            finished = state.env_steps >= state.config.steps
            if state.iteration % state.config.eval_every == 0 or finished:
                returns = evaluate_linear(state, runner)
                state.wall_seconds = wall_at_start + time.monotonic() - started
                improved = returns.mean() > state.best_return
                if improved:
                    state.best_return, state.best_return_std = returns.mean(), returns.std()
                    state.best_weights = state.weights.copy()
                    state.best_obs_mean = state.statistics.mean.copy()
                    state.best_obs_std = state.statistics.std()
                    state.best_env_steps = state.env_steps
                    write_expert()
                log(
                    f"iteration {state.iteration:5d}  env steps {state.env_steps:10d}  "
                    f"wall {state.wall_seconds:8.1f} s  eval return {returns.mean():9.1f} "
                    f"± {returns.std():6.1f}" + ("  (best, saved)" if improved else "")
                )
            state.wall_seconds = wall_at_start + time.monotonic() - started
            if nets.checkpoint_due(time.monotonic() - last_checkpoint, checkpoint_seconds):
                state.save(checkpoint_path)
                last_checkpoint = time.monotonic()
                nets.stop_if_requested()  # Ctrl-C or kill, with the checkpoint written
        state.save(checkpoint_path)
    if state.best_weights is None:
        log(
            f"done: no evaluation beat the existing {expert_path} (eval return "
            f"{state.best_return:.1f}); left it unchanged"
        )
    else:
        log(
            f"done: best eval return {state.best_return:.1f} ± {state.best_return_std:.1f} at "
            f"{state.best_env_steps} env steps; expert in {expert_path}"
        )
    return state


def positive_int(text: str) -> int:
    """A count such as ``8`` or a budget such as ``7e6``."""
    value = float(text)
    if value != int(value):
        raise argparse.ArgumentTypeError(f"must be a whole number, got {text}")
    value = int(value)
    if value < 1:
        raise argparse.ArgumentTypeError(f"must be at least 1, got {value}")
    return value


def positive_number(text: str) -> float:
    """A finite number above 0, such as a time constant ``1e4`` (NaN and inf refused)."""
    value = float(text)
    if not 0 < value < float("inf"):
        raise argparse.ArgumentTypeError(f"must be a finite number above 0, got {text}")
    return value


def add_config_flags(parser: argparse.ArgumentParser) -> None:
    """One flag per ARSConfig and sac.SACConfig field, help from the fields' docstrings.

    A field both have (the budget, the evaluations) is one flag; every default is None,
    "not given", so that each method can apply its own and refuse the other's flags.
    """
    import sac

    ars_fields = {field.name: field for field in dataclasses.fields(ARSConfig)}
    sac_fields = {field.name: field for field in dataclasses.fields(sac.SACConfig)}
    ars_docs, sac_docs = field_docstrings(ARSConfig), field_docstrings(sac.SACConfig)
    for name in [*ars_fields, *(name for name in sac_fields if name not in ars_fields)]:
        field = ars_fields.get(name) or sac_fields[name]
        helps = []
        if name in ars_fields:
            helps.append(f"ARS: {ars_docs[name]} (default: per task, else {field.default})")
        if name in sac_fields:
            helps.append(f"SAC: {sac_docs[name]} (default: {sac_fields[name].default})")
        options = dict(type=float if field.type in ("float", float) else positive_int)
        if name not in ars_fields and "tuple" in str(field.type):
            options["nargs"] = "+"
        parser.add_argument(
            "--" + name.replace("_", "-"), default=None, help=" | ".join(helps), **options
        )


def field_docstrings(cls) -> dict[str, str]:
    """The string literal under each dataclass field (the CleanRL/Spinning Up convention)."""
    tree = ast.parse(inspect.getsource(cls))
    body = tree.body[0].body
    docs = {}
    for previous, node in zip(body, body[1:], strict=False):
        if (
            isinstance(previous, ast.AnnAssign)
            and isinstance(node, ast.Expr)
            and isinstance(node.value, ast.Constant)
            and isinstance(node.value.value, str)
        ):
            docs[previous.target.id] = node.value.value
    return docs


def add_dataclass_flags(parser: argparse.ArgumentParser, cls) -> None:
    """One --flag per dataclass field, its help text the field's docstring (inherited
    fields' too): the command lines of expert.py, offpac_il.py and baselines.py."""
    docs = {}
    for klass in reversed(cls.__mro__):
        if dataclasses.is_dataclass(klass):
            docs.update(field_docstrings(klass))
    for f in dataclasses.fields(cls):
        flag, default = "--" + f.name.replace("_", "-"), f.default
        if isinstance(default, bool):
            parser.add_argument(
                flag, action=argparse.BooleanOptionalAction, default=default, help=docs[f.name]
            )
        elif isinstance(default, tuple):
            parser.add_argument(flag, type=int, nargs="+", default=default, help=docs[f.name])
        else:
            parser.add_argument(flag, type=type(default), default=default, help=docs[f.name])


class CommandLineParser(argparse.ArgumentParser):
    """argparse, but a bad flag ends in one line on stderr and exit status 2 (no usage
    dump), like every other error a user can cause."""

    def error(self, message: str):
        print(f"error: {message} (see {self.prog} --help)", file=sys.stderr)
        sys.exit(2)


def command_line(argv: list[str]) -> str:
    return shlex.join(["python", "expert.py", *argv])


def given_flags(args, names) -> list[str]:
    """The flags among ``names`` (dataclass field names) given on the command line."""
    return ["--" + name.replace("_", "-") for name in names if getattr(args, name) is not None]


def cli_train(args, argv) -> None:
    import sac

    ars_only = {f.name for f in dataclasses.fields(ARSConfig)} - {
        f.name for f in dataclasses.fields(sac.SACConfig)
    }
    sac_only = {f.name for f in dataclasses.fields(sac.SACConfig)} - {
        f.name for f in dataclasses.fields(ARSConfig)
    }
    wrong = given_flags(args, sorted(sac_only | {"run_dir"} if args.method == "ars" else ars_only))
    if args.method == "sac" and args.checkpoint is not None:
        wrong.append("--checkpoint")
    if wrong:
        raise UserError(f"{', '.join(wrong)}: not a setting of --method {args.method}")
    if args.method == "sac":
        cli_train_sac(args, argv)
        return
    overrides = {field.name: getattr(args, field.name) for field in dataclasses.fields(ARSConfig)}
    config = ars_config_for(args.env, **overrides)
    if args.resume:
        given = {
            name: value
            for name, value in overrides.items()
            if value is not None and name != "steps"
        }
        if given:
            raise UserError(
                f"--resume continues the checkpoint's settings; only --steps may "
                f"change (got {', '.join('--' + n.replace('_', '-') for n in given)})"
            )
    checkpoint = (
        Path(args.checkpoint) if args.checkpoint else CHECKPOINTS_DIR / f"{args.env}.ckpt.npz"
    )
    out = Path(args.out) if args.out else default_expert_path(args.env)
    with nets.stop_at_next_checkpoint():
        train(
            args.env,
            args.seed,
            config,
            args.workers,
            checkpoint,
            out,
            resume=args.resume,
            command=command_line(argv),
            log=lambda line: print(line, flush=True),
        )


def cli_train_sac(args, argv) -> None:
    """``train --method sac``: a SAC run in ``--run-dir``, its best policy to ``--out``."""
    import sac

    run_dir = Path(args.run_dir) if args.run_dir else sac.default_run_dir(args.env, args.seed)
    names = [field.name for field in dataclasses.fields(sac.SACConfig)]
    if args.resume:
        given = [flag for flag in given_flags(args, names) if flag != "--steps"]
        if given:
            raise UserError(
                f"--resume continues the run's settings; only --steps may change "
                f"(got {', '.join(given)})"
            )
        saved = sac.saved_run(run_dir)
        config = dataclasses.replace(saved["config"], steps=args.steps or saved["config"].steps)
        seed, out = saved["seed"], Path(args.out or saved["expert_path"])
    else:
        values = {name: getattr(args, name) for name in names if getattr(args, name) is not None}
        if "hidden" in values:
            values["hidden"] = tuple(values["hidden"])
        config = sac.SACConfig(**values)
        seed, out = args.seed, Path(args.out) if args.out else default_expert_path(args.env)
    with nets.stop_at_next_checkpoint():
        sac.train(
            args.env,
            seed,
            config,
            run_dir,
            out,
            resume=args.resume,
            command=command_line(argv),
            log=lambda line: print(line, flush=True),
        )


def cli_demos(args, argv) -> None:
    expert = load_expert(args.env, Path(args.expert)) if args.expert else None
    out = (
        Path(args.out)
        if args.out
        else default_demos_path(args.env, args.trajectories, args.sampling, args.seed)
    )
    demos = make_demos(args.env, args.trajectories, args.sampling, args.seed, expert=expert)
    write_demos(out, demos)
    print(
        f"{out}: {len(demos['observations'])} triplets from {args.trajectories} "
        f"{args.sampling} trajectories, expert returns {np.round(demos['returns'], 1).tolist()}"
        f", dropped episodes (expert fell or scored below {float(demos['min_return']):.0f}): "
        f"{len(demos['dropped_episode_seeds'])}"
    )


def cli_import_minari(args, argv) -> None:
    demos = import_minari(args.dataset_id, args.env, args.trajectories, args.sampling, args.seed)
    write_demos(Path(args.out), demos)
    print(
        f"{args.out}: {len(demos['observations'])} triplets from {len(demos['returns'])} "
        f"episodes of {args.dataset_id}"
    )


def cli_check_demos(args, argv) -> None:
    demos = load_demos(Path(args.file), args.env)
    returns = (
        "unknown"
        if demos.returns is None
        else f"{demos.returns.mean():.1f} ± {demos.returns.std():.1f}"
    )
    print(
        f"{args.file}: {len(demos)} valid triplets for {args.env} "
        f"({demos.sampling or 'unknown'} sampling, {demos.trajectories or '?'} trajectories, "
        f"expert return {returns}, {int(demos.terminals.sum())} terminal)"
    )


def cli_table(args, argv) -> None:
    table = measure_table(args.episodes, args.seed, log=lambda line: print(line, flush=True))
    nets.write_text(Path(args.out), json.dumps(table, indent=2) + "\n")
    print(f"wrote {args.out}\n")
    print(table_markdown(table))


def build_parser() -> argparse.ArgumentParser:
    parser = CommandLineParser(prog="expert.py", description=__doc__.splitlines()[0])
    commands = parser.add_subparsers(dest="command", required=True)

    train_parser = commands.add_parser(
        "train", help="train an expert: ARS V2-t (default) or SAC (--method sac)"
    )
    train_parser.add_argument("--env", required=True, help="gymnasium id, e.g. Hopper-v4")
    train_parser.add_argument(
        "--method",
        choices=("ars", "sac"),
        default="ars",
        help="ARS V2-t (Hopper, HalfCheetah, Humanoid) or Soft Actor-Critic, sac.py "
        "(Walker2d, Ant)",
    )
    train_parser.add_argument("--seed", type=int, default=0)
    train_parser.add_argument(
        "--workers",
        type=positive_int,
        default=os.cpu_count() or 1,
        help="ARS: rollout processes (default: CPU count)",
    )
    train_parser.add_argument(
        "--resume",
        action="store_true",
        help="continue exactly from the checkpoint (ARS: --checkpoint; SAC: --run-dir)",
    )
    train_parser.add_argument(
        "--checkpoint", help="ARS: default experts/checkpoints/<env>.ckpt.npz"
    )
    train_parser.add_argument(
        "--run-dir",
        help="SAC: run directory with checkpoint.npz and progress.csv "
        "(default: runs/sac-<env>-seed<seed>, git-ignored)",
    )
    train_parser.add_argument("--out", help="expert file (default: experts/<env>.npz)")
    add_config_flags(train_parser)
    train_parser.set_defaults(handler=cli_train)

    demos_parser = commands.add_parser("demos", help="write expert (s, a, s') demonstrations")
    demos_parser.add_argument("--env", required=True)
    demos_parser.add_argument("--trajectories", type=positive_int, default=4)
    demos_parser.add_argument(
        "--sampling",
        choices=SAMPLING_MODES,
        default="sparse",
        help="sparse: 100 random triplets per trajectory; dense: all 1000",
    )
    demos_parser.add_argument("--seed", type=int, default=0)
    demos_parser.add_argument("--expert", help="expert file (default: experts/<env>.npz)")
    demos_parser.add_argument(
        "--out", help="default: demos/<env>-<sampling>-<n>traj-seed<seed>.npz"
    )
    demos_parser.set_defaults(handler=cli_demos)

    minari_parser = commands.add_parser(
        "import-minari", help="convert a locally stored Minari dataset to a demonstration file"
    )
    minari_parser.add_argument("dataset_id", help="e.g. mujoco/hopper/expert-v0")
    minari_parser.add_argument("--env", required=True, help="environment the triplets are for")
    minari_parser.add_argument("--out", required=True)
    minari_parser.add_argument(
        "--trajectories",
        type=positive_int,
        default=None,
        help="use the first N episodes (default: all)",
    )
    minari_parser.add_argument("--sampling", choices=SAMPLING_MODES, default="dense")
    minari_parser.add_argument("--seed", type=int, default=0)
    minari_parser.set_defaults(handler=cli_import_minari)

    check_parser = commands.add_parser("check-demos", help="validate a demonstration file")
    check_parser.add_argument("file")
    check_parser.add_argument("--env", required=True)
    check_parser.set_defaults(handler=cli_check_demos)

    table_parser = commands.add_parser("table", help="measure Table 1 for the -v4 tasks")
    table_parser.add_argument("--episodes", type=positive_int, default=10)
    table_parser.add_argument(
        "--seed", type=int, default=0, help="episode i is reset with seed + i"
    )
    table_parser.add_argument("--out", default=str(TABLE_PATH))
    table_parser.set_defaults(handler=cli_table)
    return parser


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    args = build_parser().parse_args(argv)
    try:
        args.handler(args, argv)
    except UserError as error:
        print(f"error: {error}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        resumable = "; continue with --resume" if args.command == "train" else ""
        print(f"interrupted{resumable}", file=sys.stderr)
        return 130
    return 0


if __name__ == "__main__":
    # Run as the module `expert`, the one sac.py imports, so that both share one UserError
    # (a script's own classes live in __main__, a second copy of this file).
    import expert

    sys.exit(expert.main())
