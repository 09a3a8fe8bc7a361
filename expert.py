"""Experts for the imitation tasks: the shipped experts and their demonstrations.

The paper (Sasaki et al., ICLR 2019, Sec. 5.1) trains its experts with TRPO and never ships
them. This project must run offline on a fresh machine, so it ships its own: linear
policies trained by ARS V2-t (Hopper, HalfCheetah, Humanoid; lab/ars.py) and SAC policy
networks (Walker2d, Ant; lab/sac.py). This file is what the learner needs of them: the
environments, the expert policy (load, act), demonstrations and Table 1's reference returns.

Files:
    experts/<env>.npz    a shipped expert: M, mu, std (ARS) or a policy network (SAC),
                         action bounds, and a JSON ``metadata`` record of the training
                         commands, seed, env steps and wall time
    experts/table.json   Table 1 for the -v4 tasks (measured by ``python -m lab.table``)
    demos/*.npz          demonstrations: ``observations``, ``actions`` (env units),
                         ``next_observations``, ``terminals`` (is s' terminal), ``env_id``,
                         ``returns`` (per trajectory), ``seed``, ``sampling``, ``trajectories``

Subcommands (``python expert.py -h``): ``demos``, ``check-demos``, ``import-minari``.
"""

from __future__ import annotations

import argparse
import contextlib
import dataclasses
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
EXPERTS_DIR = REPO_DIR / "experts"
DEMOS_DIR = REPO_DIR / "demos"
TABLE_PATH = EXPERTS_DIR / "table.json"

# Sec. 5.1: expert trajectories are 1000 steps long; sparse sampling keeps 100 of each.
TRAJECTORY_STEPS = 1000
SPARSE_TRIPLETS_PER_TRAJECTORY = 100
SAMPLING_MODES = ("sparse", "dense")

# Demonstration actions may come from float32 files or other tools; accept tiny overshoots.
ACTION_BOUND_TOLERANCE = 1e-4


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
        if self.network is None:
            arrays = dict(weights=self.weights, obs_mean=self.obs_mean, obs_std=self.obs_std)
        else:
            arrays = dict(kind=np.array(SAC_MLP), sizes=np.array(self.network.sizes))
            arrays |= self.network.state("policy")
        arrays |= dict(action_low=self.action_low, action_high=self.action_high)
        record = json.dumps({**self.metadata, **metadata}, sort_keys=True)
        harness.save_arrays(
            path, {"env_id": np.array(self.env_id), **arrays, "metadata": np.array(record)}
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
            keep = kept_steps(TRAJECTORY_STEPS, sampling, subsample_rng)
            actions = np.asarray(episode_actions)
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
    states, actions, next_states, terminals = map(np.concatenate, zip(*chunks, strict=True))
    return dict(
        observations=states.astype(np.float32),
        actions=actions.astype(np.float32),
        next_observations=next_states.astype(np.float32),
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


def demo_path(settings, make: bool = True) -> Path:
    """The demonstrations a run's settings name (offpac_il.RunConfig's demos, env,
    trajectories, sampling, demo_seed): the file `demos`, else the shipped expert's default
    demonstrations, made the first time unless `make` is False."""
    if settings.demos:
        return Path(settings.demos)
    default = (settings.env, settings.trajectories, settings.sampling, settings.demo_seed)
    return ensure_demos(*default) if make else default_demos_path(*default)


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
        observations, actions, next_observations = (
            np.asarray(arrays[key], dtype=np.float32) for key in DEMO_ARRAY_KEYS[:3]
        )
        terminals = np.asarray(arrays["terminals"]).astype(bool)
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
    lengths = {len(observations), len(actions), len(next_observations), len(terminals)}
    if len(lengths) != 1 or terminals.ndim != 1:
        raise fail(
            f"mismatched lengths: {len(observations)} observations, {len(actions)} "
            f"actions, {len(next_observations)} next_observations, {len(terminals)} terminals"
        )
    tolerance = ACTION_BOUND_TOLERANCE * np.maximum(1.0, np.abs(np.stack([low, high])))
    if np.any(actions < low - tolerance[0]) or np.any(actions > high + tolerance[1]):
        raise fail(
            f"actions outside the action bounds [{low.min():g}, {high.max():g}] of "
            f"{env_id} (largest |a| = {np.abs(actions).max():g})"
        )

    recorded = (("returns", np.asarray), ("seed", int), ("sampling", str), ("trajectories", int))
    optional = {key: convert(arrays[key]) for key, convert in recorded if key in arrays}
    triplets = (observations, actions, next_observations, terminals)
    return Demos(*triplets, env_id=recorded_env, path=path, **optional)


def load_demos(path: Path, env_id: str) -> Demos:
    """Load and validate a demonstration file for ``env_id`` (see :func:`validate_demos`)."""
    path = Path(path)
    if not path.exists():
        raise UserError(f"{path}: no such demonstration file")
    return validate_demos(harness.load_arrays(path), env_id, path)


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
    check_sampling(sampling)
    try:
        dataset = minari.load_dataset(dataset_id, download=False)
    except Exception as error:  # minari raises bare Exceptions/FileNotFoundError/ValueError
        raise UserError(
            f"cannot load Minari dataset {dataset_id!r} locally "
            f"(MINARI_DATASETS_PATH={os.environ.get('MINARI_DATASETS_PATH', '~')}): "
            f"{error}"
        ) from None
    rng = np.random.default_rng(seed)
    chunks, returns = [], []
    for episode in dataset.iterate_episodes():
        if trajectories is not None and len(returns) >= trajectories:
            break
        observations = np.asarray(episode.observations)  # (T + 1, dim S)
        if observations.dtype == object or observations.ndim != 2:
            raise UserError(f"{dataset_id}: observations are not flat arrays")
        keep = kept_steps(len(episode.actions), sampling, rng)
        triplet = (observations[:-1], np.asarray(episode.actions), observations[1:])
        terminals = np.asarray(episode.terminations, dtype=bool)
        chunks.append(tuple(a[keep] for a in (*triplet, terminals)))
        returns.append(float(np.sum(episode.rewards)))
    if not returns:
        raise UserError(f"Minari dataset {dataset_id!r} has no episodes")
    return demo_arrays(
        chunks, env_id, returns, seed, sampling, source=np.array(f"minari:{dataset_id}")
    )


# ---------------------------------------------------------------------------------------------
# Reference returns (Table 1, measured by lab/table.py): the normalised score's two ends
# ---------------------------------------------------------------------------------------------


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
# Command line: python expert.py {demos,import-minari,check-demos}
# ---------------------------------------------------------------------------------------------


def cli_demos(args) -> None:
    expert = load_expert(args.env, Path(args.expert)) if args.expert else None
    default = default_demos_path(args.env, args.trajectories, args.sampling, args.seed)
    out = Path(args.out) if args.out else default
    demos = make_demos(args.env, args.trajectories, args.sampling, args.seed, expert=expert)
    write_demos(out, demos)
    print(
        f"{out}: {len(demos['observations'])} triplets from {args.trajectories} "
        f"{args.sampling} trajectories, expert returns {np.round(demos['returns'], 1).tolist()}"
        f", dropped episodes (expert fell or scored below {float(demos['min_return']):.0f}): "
        f"{len(demos['dropped_episode_seeds'])}"
    )


def cli_import_minari(args) -> None:
    demos = import_minari(args.dataset_id, args.env, args.trajectories, args.sampling, args.seed)
    write_demos(Path(args.out), demos)
    print(
        f"{args.out}: {len(demos['observations'])} triplets from {len(demos['returns'])} "
        f"episodes of {args.dataset_id}"
    )


def cli_check_demos(args) -> None:
    demos = load_demos(Path(args.file), args.env)
    r = demos.returns
    returns = "unknown" if r is None else f"{r.mean():.1f} ± {r.std():.1f}"
    print(
        f"{args.file}: {len(demos)} valid triplets for {args.env} "
        f"({demos.sampling or 'unknown'} sampling, {demos.trajectories or '?'} trajectories, "
        f"expert return {returns}, {int(demos.terminals.sum())} terminal)"
    )


def parse(argv: list[str]) -> argparse.Namespace:
    parser = harness.CommandLineParser(prog="expert.py", description=__doc__.splitlines()[0])
    commands = parser.add_subparsers(dest="command", required=True)
    count = harness.positive_int

    demos = commands.add_parser("demos", help="write expert (s, a, s') demonstrations")
    demos.add_argument("--env", required=True)
    demos.add_argument("--trajectories", type=count, default=4)
    demos.add_argument(
        "--sampling",
        choices=SAMPLING_MODES,
        default="sparse",
        help="sparse: 100 random triplets per trajectory; dense: all 1000",
    )
    demos.add_argument("--seed", type=int, default=0)
    demos.add_argument("--expert", help="expert file (default: experts/<env>.npz)")
    demos.add_argument("--out", help="default: demos/<env>-<sampling>-<n>traj-seed<seed>.npz")
    demos.set_defaults(handler=cli_demos)

    minari = commands.add_parser(
        "import-minari", help="convert a locally stored Minari dataset to a demonstration file"
    )
    minari.add_argument("dataset_id", help="e.g. mujoco/hopper/expert-v0")
    minari.add_argument("--env", required=True, help="environment the triplets are for")
    minari.add_argument("--out", required=True)
    minari.add_argument("--trajectories", type=count, help="the first N episodes (default: all)")
    minari.add_argument("--sampling", choices=SAMPLING_MODES, default="dense")
    minari.add_argument("--seed", type=int, default=0)
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
