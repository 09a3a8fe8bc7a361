"""A GIF of a learner run's saved policy acting, beside the shipped expert if asked.

    python -m lab.render RUN_DIR [--policy average] [--beside-expert] [--out hopper.gif]

MuJoCo renders offscreen through EGL (MUJOCO_GL=egl, the default here) or OSMesa
(MUJOCO_GL=osmesa). On Debian or Ubuntu EGL comes with `apt install libegl1
libgl1-mesa-dri`, OSMesa with `apt install libosmesa6`. The tests do not need either:
they skip the rendering where it is unavailable.

Both players start from the same reset seed; the learner's noise z comes from a
Generator seeded by it, so a command draws the same GIF every time.
"""

from __future__ import annotations

import argparse
import gc
import os
import sys
from pathlib import Path

import gymnasium as gym
import numpy as np

import harness
from harness import UserError

os.environ.setdefault("MUJOCO_GL", "egl")  # before MuJoCo's GL context is first imported
RENDER_PACKAGES = (
    "Debian/Ubuntu: apt install libegl1 libgl1-mesa-dri (or libosmesa6 with MUJOCO_GL=osmesa)"
)


def render_env(env_id: str, width: int, height: int, **kwargs):
    """The task with offscreen rendering (kwargs: gym.make's), or one UserError naming the
    system package it needs."""
    import expert

    env, message = None, None
    # A gymnasium viewer whose __init__ failed frees, in its __del__, a GL context it never
    # made: six lines of "Exception ignored" when the failure's traceback is dropped.
    hook, sys.unraisablehook = sys.unraisablehook, lambda unraisable: None
    try:
        import mujoco  # it loads the GL back end MUJOCO_GL names

        env = expert.make_env(env_id, render_mode="rgb_array", width=width, height=height, **kwargs)
        env.reset(seed=0)
        env.render()
        # gymnasium's -v4 cameras name a body to track but stay free, so a runner leaves
        # the picture within a second: follow the torso (body 1 in every paper task).
        renderer = env.unwrapped.mujoco_renderer
        camera = renderer._get_viewer("rgb_array").cam
        camera.type, camera.trackbodyid = mujoco.mjtCamera.mjCAMERA_TRACKING, 1
        renderer.camera_id = None  # else each render() sets the camera free again
    except UserError:
        raise
    except Exception as error:  # the GL back ends fail with several unrelated types
        gl = os.environ.get("MUJOCO_GL")
        message = f"MuJoCo cannot render offscreen (MUJOCO_GL={gl}: {error}); {RENDER_PACKAGES}"
    finally:
        if message is not None and env is not None:
            env.close()
        gc.collect()
        sys.unraisablehook = hook
    if message is not None:
        raise UserError(message)
    return env


class FrameRecorder(gym.Wrapper):
    """Keeps the rendered frame after each reset and after every `every`-th step, so that
    the project's own rollout loops (offpac_il.run_episode for a learner's policy,
    lab.table.run_episode for the expert) act in the GIF as they act anywhere else."""

    def __init__(self, env: gym.Env, every: int):
        super().__init__(env)
        self.every, self.frames, self.steps = every, [], 0

    def reset(self, **kwargs):
        result = self.env.reset(**kwargs)
        self.frames, self.steps = [self.env.render().copy()], 0  # the renderer reuses its buffer
        return result

    def step(self, action):
        result = self.env.step(action)
        self.steps += 1
        if self.steps % self.every == 0:
            self.frames.append(self.env.render().copy())
        return result


def side_by_side(*players: list[np.ndarray]) -> list[np.ndarray]:
    """Frames of several players joined left to right; a shorter one holds its last frame."""
    length = max(len(frames) for frames in players)
    padded = [frames + [frames[-1]] * (length - len(frames)) for frames in players]
    return [np.concatenate(row, axis=1) for row in zip(*padded, strict=True)]


def write_gif(path, frames: list[np.ndarray], fps: float) -> None:
    """An animated GIF (Pillow, which matplotlib already needs), written atomically."""
    from PIL import Image

    images = [Image.fromarray(np.asarray(frame, np.uint8)) for frame in frames]
    # One palette for all frames (no flicker), from up to 8 of them stacked; 32 colours
    # keep a 60-frame GIF of two players under 1 MB.
    sample = np.concatenate([np.asarray(f, np.uint8) for f in frames[:: -(-len(frames) // 8)]])
    palette = Image.fromarray(sample).quantize(colors=32)
    images = [image.quantize(palette=palette, dither=Image.Dither.NONE) for image in images]
    harness.write_atomically(
        path,
        lambda f: images[0].save(
            f,
            format="GIF",
            save_all=True,
            append_images=images[1:],
            duration=round(1000 / fps),
            loop=0,
        ),
    )


def render(args) -> None:
    from lab import experiments, table

    run_dir = Path(args.run_dir)
    env_id = str(harness.read_config(run_dir).get("env", ""))  # a run at all, before anything
    env = render_env(env_id, args.width, args.height, max_episode_steps=args.steps)
    with FrameRecorder(env, args.every) as recorder:
        play = experiments.policy_player(run_dir, recorder)
        (row,) = play(experiments.policy_file(run_dir, args.policy), 1, args.seed)
        frames, line = recorder.frames, f"{args.policy} policy: return {row['return']:.1f}"
        if args.beside_expert:
            import expert

            expert_return, _ = table.run_episode(
                recorder, expert.load_expert(env_id).act, args.seed
            )
            frames = side_by_side(frames, recorder.frames)
            line += f"; expert (right): return {expert_return:.1f}"
        fps = 1.0 / (env.unwrapped.dt * args.every)  # real time
    write_gif(args.out, frames, fps)
    print(f"{args.out}: {len(frames)} frames of {args.steps} steps at most; {line}")


def parse(argv: list[str]) -> argparse.Namespace:
    parser = harness.CommandLineParser(
        prog="python -m lab.render", description=__doc__.splitlines()[0]
    )
    parser.add_argument("run_dir", help="a learner run directory (offpac_il.py or lab.ablations)")
    parser.add_argument(
        "--policy", default="average", help="average, final, best or a snapshot's interactions"
    )
    parser.add_argument(
        "--beside-expert", action="store_true", help="the shipped expert on the right"
    )
    parser.add_argument("--out", default="policy.gif", help="the GIF to write")
    parser.add_argument(
        "--seed", type=harness.seed_number, default=0, help="reset seed of the episode"
    )
    parser.add_argument("--steps", type=harness.positive_int, default=400, help="steps at most")
    parser.add_argument(
        "--every", type=harness.positive_int, default=4, help="a frame every N steps"
    )
    parser.add_argument("--width", type=harness.positive_int, default=240)
    parser.add_argument("--height", type=harness.positive_int, default=180)
    return parser.parse_args(argv)


def main(argv: list[str] | None = None) -> int:
    return harness.cli_main(argv, parse, lambda args, _: render(args), checkpoints=False)


if __name__ == "__main__":
    sys.exit(main())
