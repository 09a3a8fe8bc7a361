"""lab/optim.py: Adam against Kingma & Ba's Algorithm 1 written out literally (the check is
shown to fail without the bias corrections), in float32, and across a save and restore."""

from __future__ import annotations

import numpy as np
import pytest
from gradcheck import assert_gradient_close
from hypothesis import given
from hypothesis import strategies as st

from lab import optim

TOL = 1e-6
EXACT_TOL = 1e-12  # comparisons with a closed form: only rounding separates the two
seeds = st.integers(0, 2**32 - 1)
batches = st.integers(1, 5)
widths = st.integers(1, 6)


def adam_reference(gradients, lr, beta1=0.9, beta2=0.999, eps=1e-8):
    """Kingma & Ba (2015), Algorithm 1, literally: bias-corrected moments, from 0."""
    param = m = v = 0.0
    for t, g in enumerate(gradients, start=1):
        m = beta1 * m + (1 - beta1) * g
        v = beta2 * v + (1 - beta2) * g * g
        m_hat, v_hat = m / (1 - beta1**t), v / (1 - beta2**t)
        param = param - lr * m_hat / (np.sqrt(v_hat) + eps)
    return param


@given(
    shape=st.tuples(batches, widths),
    lr=st.floats(1e-5, 1e-1),
    beta1=st.floats(0.0, 0.99),
    beta2=st.floats(0.5, 0.9999),
    seed=seeds,
)
def test_adam_against_algorithm_1(shape, lr, beta1, beta2, seed):
    """Three steps with different gradients and learning rate against the literal
    Algorithm 1; the first step is lr g / (|g| + eps), about lr sign(g), whatever g's
    scale. Parameters start at 0, so they hold the steps themselves."""
    g1, g2, g3 = np.random.default_rng(seed).normal(size=(3, *shape))
    params = {"W": np.zeros(shape)}
    opt = optim.Adam(beta1=beta1, beta2=beta2)
    opt.step(params, {"W": g1}, lr)
    assert_gradient_close(params["W"], -lr * g1 / (np.abs(g1) + 1e-8), EXACT_TOL, "adam/one")
    opt.step(params, {"W": g2}, lr)
    opt.step(params, {"W": g3}, lr)
    expected = adam_reference([g1, g2, g3], lr, beta1, beta2)
    # Steps of opposite sign can cancel: compare to 1e-12 of the step scale lr there.
    assert_gradient_close(params["W"], expected, EXACT_TOL, "adam/three_steps", floor=lr)
    assert opt.t == 3


def test_adam_check_catches_a_missing_bias_correction(monkeypatch):
    """The same check fails for Adam without its bias corrections (the first step would
    be lr (1 - beta1) g / (sqrt(1 - beta2) |g|), about 3.2 lr sign(g))."""
    g = np.random.default_rng(0).normal(size=(3, 2))
    expected = adam_reference([g, 0.5 * g], 1e-3)
    params, opt = {"W": np.zeros((3, 2))}, optim.Adam()
    opt.step(params, {"W": g}, 1e-3)
    opt.step(params, {"W": 0.5 * g}, 1e-3)
    assert_gradient_close(params["W"], expected, EXACT_TOL, "adam/right", floor=1e-3)
    monkeypatch.setattr(optim.Adam, "step", _adam_without_bias_correction)
    params, uncorrected = {"W": np.zeros((3, 2))}, optim.Adam()
    uncorrected.step(params, {"W": g}, 1e-3)
    uncorrected.step(params, {"W": 0.5 * g}, 1e-3)
    with pytest.raises(AssertionError, match="relative error"):
        assert_gradient_close(params["W"], expected, TOL, "adam/wrong", floor=1e-3)


def _adam_without_bias_correction(self, params, grads, lr):
    for name, grad in grads.items():
        m = self.first_moment.setdefault(name, np.zeros_like(params[name]))
        v = self.second_moment.setdefault(name, np.zeros_like(params[name]))
        m[...] = self.beta1 * m + (1 - self.beta1) * grad
        v[...] = self.beta2 * v + (1 - self.beta2) * grad * grad
        params[name] -= lr * m / (np.sqrt(v) + self.eps)


def test_adam_keeps_float32_and_round_trips_its_state():
    params = {"W": np.ones((3, 2), np.float32), "b": np.zeros(2, np.float32)}
    grads = {"W": np.full((3, 2), 0.5), "b": np.ones(2, np.float32)}  # W's gradient float64
    opt = optim.Adam()
    opt.step(params, grads, 1e-3)
    for key in params:
        assert params[key].dtype == np.float32
        assert opt.first_moment[key].dtype == opt.second_moment[key].dtype == np.float32
    # A copy restored from the saved state takes the same next step as the original.
    restored, copy = optim.Adam(), {k: v.copy() for k, v in params.items()}
    restored.load_state(opt.state("adam"), "adam")
    assert restored.t == 1
    opt.step(params, grads, 1e-3)
    restored.step(copy, grads, 1e-3)
    for key in params:
        np.testing.assert_array_equal(params[key], copy[key])
