"""lab/render.py: the GIF of a saved policy acting. The frame handling is tested on
synthetic frames; the rendering itself only where MuJoCo can render offscreen (CI may
not), and its absence must be one clear line naming the system package."""

from __future__ import annotations

import os

import numpy as np
import pytest
from PIL import Image

from harness import UserError
from lab import render
from tests.helpers import ROOT, assert_one_line_error, run_module

RUN = ROOT / "results" / "hopper-plr2.3e-5-seed0"  # a finished learner run the docs cite


def frames(n: int, value: int, shape=(6, 8, 3)) -> list[np.ndarray]:
    return [np.full(shape, value + 10 * i, np.uint8) for i in range(n)]


def test_side_by_side_holds_the_last_frame_of_the_shorter_player():
    joined = render.side_by_side(frames(3, 0), frames(5, 100))
    assert len(joined) == 5 and joined[0].shape == (6, 16, 3)
    assert (joined[4][:, :8] == joined[2][:, :8]).all()  # left player stopped after 3
    assert (joined[4][:, 8:] == 140).all()


def test_gif_holds_every_frame_in_order(tmp_path):
    path = tmp_path / "out.gif"
    render.write_gif(path, frames(4, 0, (12, 16, 3)), fps=25)
    with Image.open(path) as gif:
        assert gif.n_frames == 4 and gif.size == (16, 12)
        assert gif.info["duration"] == 40
        levels = []
        for i in range(4):
            gif.seek(i)
            levels.append(int(np.asarray(gif.convert("L")).mean()))
    assert levels == sorted(levels) and len(set(levels)) == 4


def can_render() -> bool:
    try:
        render.render_env("Hopper-v4", 16, 12).close()
    except UserError:
        return False
    return True


@pytest.mark.skipif(not can_render(), reason="MuJoCo cannot render offscreen on this machine")
def test_renders_a_run_beside_the_expert(tmp_path):
    out = tmp_path / "hopper.gif"
    result = run_module(
        "lab.render", RUN, "--beside-expert", "--steps", 12, "--every", 4,
        "--width", 32, "--height", 24, "--out", out,
    )  # fmt: skip
    assert "expert (right)" in result.stdout
    with Image.open(out) as gif:
        assert gif.n_frames == 4 and gif.size == (64, 24)  # steps 0, 4, 8, 12; two players


def test_no_offscreen_rendering_is_one_line_naming_the_package(tmp_path):
    out = tmp_path / "x.gif"
    env = {**os.environ, "MUJOCO_GL": "no-such-backend"}
    import subprocess
    import sys

    result = subprocess.run(
        [sys.executable, "-m", "lab.render", str(RUN), "--out", str(out)],
        capture_output=True, text=True, cwd=ROOT, env=env, timeout=300,
    )  # fmt: skip
    assert_one_line_error(result, "cannot render offscreen", "apt install")
    assert not out.exists()


def test_refuses_what_is_not_a_learner_run(tmp_path):
    assert_one_line_error(run_module("lab.render", tmp_path, check=False), "holds no run")
    gail = ROOT / "results" / "hopper-gail-seed0"
    result = run_module("lab.render", gail, "--out", tmp_path / "x.gif", check=False)
    assert_one_line_error(result, "gail run", "not a learner run")
    assert not (tmp_path / "x.gif").exists()
