"""Property tests for nets.py: every derivative against centered finite differences.

All gradient checks run in float64 with eps = 1e-6 and the relative error
|x - y| / max(1e-8, |x| + |y|) (tests/gradcheck.py). Hypothesis draws the shapes (batch
sizes from 1, layer and input widths) and a seed from which NumPy draws the values; the
"ci" profile (tests/conftest.py) makes the draws reproducible.

Conventions: a scalar loss L = sum(output * R) with a random R, so dL/d(output) = R;
samples whose leaky-ReLU pre-activations come within 1e-3 of the kink are rejected, since
a finite difference across the kink measures neither slope. Element-wise pieces are
differentiated element by element, so each element's rounding error scales with its own
value. The tolerance is 1e-6 throughout; the one exception, for the tiny gradient
elements of MLP losses, is explained at FD_FLOOR.
"""

from __future__ import annotations

import warnings
from decimal import Decimal, localcontext

import numpy as np
import pytest
from gradcheck import (
    assert_gradient_close,
    numerical_derivative_elementwise,
    numerical_gradient,
    relative_error,
    relative_errors,
)
from hypothesis import assume, given
from hypothesis import strategies as st

import nets
from lab import ablations

TOL = 1e-6  # finite differences in float64 with eps = 1e-6
EXACT_TOL = 1e-12  # comparisons with a closed form: only rounding separates the two
KINK_MARGIN = 1e-3
# MLP losses: the finite difference of these O(1)-O(10) losses carries rounding noise up
# to ~2e-9 absolute (measured with the identity head, where the difference is otherwise
# exact), while a gradient element can be ~1e-9 itself: behind one or two leaky-ReLU
# units that are off (scaled by 0.01 or 1e-4), or the product of a near-zero input and
# a near-zero R. No eps resolves such an element to 1e-6 relative error (the dev profile
# found 2e-2 with the plain 1e-8 floor). So elements below 1e-2 are held to
# tol * 1e-2 = 1e-8 absolute instead (any slope, transpose or factor mistake is far
# larger), all others to 1e-6 relative.
FD_FLOOR = 1e-2

seeds = st.integers(0, 2**32 - 1)
batches = st.integers(1, 5)
widths = st.integers(1, 6)


# ----------------------------------------------------------------------------------------
# Helpers.
# ----------------------------------------------------------------------------------------


def min_abs_preactivation(cache: nets.Cache) -> float:
    """Smallest |pre-activation| over all hidden units, recovered from the activations
    (a = pre where pre > 0, else 0.01 pre)."""
    smallest = np.inf
    for a in cache.activations:
        pre = np.where(a > 0, a, a / nets.LEAKY_SLOPE)
        smallest = min(smallest, float(np.abs(pre).min()))
    return smallest


def away_from_kink(mlp: nets.MLP, x) -> nets.Cache:
    _, cache = mlp.forward(x)
    assume(min_abs_preactivation(cache) > KINK_MARGIN)
    return cache


def linear_loss(mlp: nets.MLP, x, weights: np.ndarray, *, of_logits: bool = False):
    """f() = sum(output * weights) (or of the logits), read afresh from x and the params."""

    def f():
        output, cache = mlp.forward(x)
        return np.sum((cache.logits if of_logits else output) * weights)

    return f


def check_all_gradients(mlp, x, weights, d_x, grads, name, *, of_logits=False, floor=FD_FLOOR):
    """Every input block's and every parameter's gradient against finite differences."""
    f = linear_loss(mlp, x, weights, of_logits=of_logits)
    blocks = x if isinstance(x, tuple) else (x,)
    d_blocks = d_x if isinstance(x, tuple) else (d_x,)
    assert len(d_blocks) == len(blocks)
    for i, (block, d_block) in enumerate(zip(blocks, d_blocks, strict=True)):
        assert d_block.shape == block.shape
        numeric = numerical_gradient(f, block)
        assert_gradient_close(d_block, numeric, TOL, f"{name}/d_input{i}", floor=floor)
    assert set(grads) == set(mlp.params)
    for key, value in mlp.params.items():
        assert grads[key].shape == value.shape
        numeric = numerical_gradient(f, value)
        assert_gradient_close(grads[key], numeric, TOL, f"{name}/{key}", floor=floor)


def logit(p):
    return np.log(p) - np.log1p(-p)


# ----------------------------------------------------------------------------------------
# Dense layer, leaky ReLU, heads.
# ----------------------------------------------------------------------------------------


@given(batch=batches, d_in=widths, d_out=widths, seed=seeds)
def test_dense_layer(batch, d_in, d_out, seed):
    """A one-layer identity-head MLP is x W0 + b0; gradients for input, weight, bias."""
    rng = np.random.default_rng(seed)
    mlp = nets.MLP.create([d_in, d_out], "identity", rng, dtype=np.float64)
    mlp.params["b0"][...] = rng.normal(size=d_out)  # zero at init; make it count
    x, weights = rng.normal(size=(batch, d_in)), rng.normal(size=(batch, d_out))
    out, cache = mlp.forward(x)
    assert_gradient_close(out, x @ mlp.params["W0"] + mlp.params["b0"], EXACT_TOL, "dense/fwd")
    d_x, grads = mlp.backward(weights, cache)
    check_all_gradients(mlp, x, weights, d_x, grads, "dense")


@given(rows=batches, cols=widths, seed=seeds)
def test_leaky_relu_forward_and_backward(rows, cols, seed):
    rng = np.random.default_rng(seed)
    x = rng.normal(size=(rows, cols))
    assume(np.abs(x).min() > KINK_MARGIN)
    weights = rng.normal(size=x.shape)
    h = nets.leaky_relu_(x.copy(), np.empty_like(x))
    np.testing.assert_array_equal(h, np.where(x > 0, x, 0.01 * x))

    d_out = weights.copy()
    activation = h.copy()
    d_x = nets.leaky_relu_backward_(d_out, activation, np.empty_like(x))
    np.testing.assert_array_equal(activation, h)  # the activation is read, not written

    def g(x):
        return nets.leaky_relu_(x.copy(), np.empty_like(x)) * weights

    assert_gradient_close(d_x, numerical_derivative_elementwise(g, x), TOL, "leaky_relu")


@pytest.mark.parametrize("head", ["tanh", "sigmoid", "identity"])
@given(rows=batches, cols=widths, seed=seeds)
def test_head_backward(head, rows, cols, seed):
    rng = np.random.default_rng(seed)
    logits = rng.uniform(-5.0, 5.0, size=(rows, cols))
    weights = rng.normal(size=logits.shape)
    out = nets.head_forward(head, logits)
    d_logits = nets.head_backward(head, weights, out)

    def g(logits):
        return nets.head_forward(head, logits) * weights

    numeric = numerical_derivative_elementwise(g, logits)
    assert_gradient_close(d_logits, numeric, TOL, f"head/{head}")


@pytest.mark.parametrize("head", ["tanh", "sigmoid"])
@given(batch=batches, d_in=widths, d_out=widths, seed=seeds)
def test_head_through_mlp(head, batch, d_in, d_out, seed):
    """through_head=True differentiates the head's output, through_head=False its logits."""
    rng = np.random.default_rng(seed)
    mlp = nets.MLP.create([d_in, d_out], head, rng, dtype=np.float64)
    x, weights = rng.normal(size=(batch, d_in)), rng.normal(size=(batch, d_out))
    _, cache = mlp.forward(x)
    d_x, grads = mlp.backward(weights, cache, through_head=True)
    check_all_gradients(mlp, x, weights, d_x, grads, f"head_mlp/{head}")
    d_x, grads = mlp.backward(weights, cache, through_head=False)
    check_all_gradients(mlp, x, weights, d_x, grads, f"logits_mlp/{head}", of_logits=True)


def test_unknown_head_is_rejected():
    with pytest.raises(ValueError, match="unknown head"):
        nets.MLP.create([2, 3], "relu", np.random.default_rng(0))


# ----------------------------------------------------------------------------------------
# The whole MLP.
# ----------------------------------------------------------------------------------------


@pytest.mark.parametrize("head", nets.HEADS)
@given(
    batch=batches,
    d_in=widths,
    hidden=st.lists(widths, min_size=1, max_size=3),
    d_out=st.integers(1, 4),
    seed=seeds,
)
def test_mlp_gradients(head, batch, d_in, hidden, d_out, seed):
    rng = np.random.default_rng(seed)
    sizes = [d_in, *hidden, d_out]
    mlp = nets.MLP.create(sizes, head, rng, dtype=np.float64)
    for i in range(mlp.n_layers):  # biases start at zero; nonzero ones test more
        mlp.params[f"b{i}"][...] = rng.normal(scale=0.5, size=sizes[i + 1])
    x, weights = rng.normal(size=(batch, d_in)), rng.normal(size=(batch, d_out))
    cache = away_from_kink(mlp, x)
    d_x, grads = mlp.backward(weights, cache)
    check_all_gradients(mlp, x, weights, d_x, grads, f"mlp/{head}")

    d_x_only, no_grads = mlp.backward(weights, cache, param_grads=False)
    assert no_grads == {}
    np.testing.assert_array_equal(d_x_only, d_x)


def input_gradient_by_finite_differences(mlp: nets.MLP, x: np.ndarray) -> np.ndarray:
    """dx_n/du_n (batch, in): centered differences of the sum of the logits in the input.
    Rows do not interact, so the derivative of the sum in u_n is row n's own gradient."""
    return numerical_gradient(lambda: mlp.forward(x)[1].logits.sum(), x)


@given(
    batch=batches,
    blocks=st.lists(widths, min_size=1, max_size=2),
    hidden=st.lists(widths, min_size=1, max_size=3),
    seed=seeds,
)
def test_input_gradient_sq_norm(batch, blocks, hidden, seed):
    """1/2 mean_n ||dx_n/du_n||^2 (the progress column critic_input_grad): the same
    number as the input gradients of `backward` give (d_logits = 1), and those agree
    with finite differences of the logit in the input."""
    rng = np.random.default_rng(seed)
    mlp = nets.MLP.create([sum(blocks), *hidden, 1], "sigmoid", rng, dtype=np.float64)
    for i in range(mlp.n_layers):
        mlp.params[f"b{i}"][...] = rng.normal(scale=0.5, size=mlp.sizes[i + 1])
    x = tuple(rng.normal(size=(batch, width)) for width in blocks)
    cache = away_from_kink(mlp, x)
    value = mlp.input_gradient_sq_norm(cache)

    d_x, _ = mlp.backward(np.ones((batch, 1)), cache, through_head=False, param_grads=False)
    input_gradient = np.concatenate(d_x, axis=1) if isinstance(d_x, tuple) else d_x
    assert value == pytest.approx(0.5 * (input_gradient**2).sum() / batch, rel=1e-12)

    numeric = input_gradient_by_finite_differences(mlp, np.concatenate(x, axis=1))
    assert_gradient_close(input_gradient, numeric, TOL, "dx/du", floor=FD_FLOOR)
    assert value == pytest.approx(0.5 * (numeric**2).sum() / batch, rel=1e-6, abs=1e-12)


def test_input_gradient_sq_norm_check_catches_ignored_slopes(monkeypatch):
    """The check above fails for a norm that forgets the leaky-ReLU slopes (every unit
    taken as on)."""
    rng = np.random.default_rng(3)
    mlp = nets.MLP.create([3, 5, 4, 1], "sigmoid", rng, dtype=np.float64)
    x = rng.normal(size=(6, 3))
    _, cache = mlp.forward(x)
    assert min_abs_preactivation(cache) > KINK_MARGIN  # this seed's sample is clean
    assert any((a < 0).any() for a in cache.activations)  # some units are off
    numeric = input_gradient_by_finite_differences(mlp, x)
    expected = 0.5 * (numeric**2).sum() / len(x)
    assert mlp.input_gradient_sq_norm(cache) == pytest.approx(expected, rel=1e-6)
    monkeypatch.setattr(nets, "LEAKY_SLOPE", 1.0)
    assert mlp.input_gradient_sq_norm(cache) != pytest.approx(expected, rel=1e-2)


def test_input_gradient_sq_norm_needs_one_logit_and_a_hidden_layer():
    rng = np.random.default_rng(0)
    for sizes in ([3, 4, 2], [3, 1]):
        mlp = nets.MLP.create(sizes, "sigmoid", rng, dtype=np.float64)
        with pytest.raises(ValueError, match="one output and a hidden layer"):
            mlp.input_gradient_sq_norm(mlp.forward(np.zeros((2, 3)))[1])


@st.composite
def block_inputs(draw):
    """Input blocks for an MLP: G shared rows serving N = G * K rows, as in the policy
    step's (states, noise) and the critic's (next states, sampled actions)."""
    groups, per_group = draw(st.integers(1, 3)), draw(st.integers(1, 3))
    n_blocks = draw(st.integers(2, 3))
    block_widths = draw(st.lists(widths, min_size=n_blocks, max_size=n_blocks))
    shared = draw(st.lists(st.booleans(), min_size=n_blocks, max_size=n_blocks))
    if all(shared):  # at least one full block fixes the batch size N
        shared[draw(st.integers(0, n_blocks - 1))] = False
    return groups, per_group, block_widths, shared


@pytest.mark.parametrize("head", nets.HEADS)
@given(case=block_inputs(), hidden=st.lists(widths, min_size=1, max_size=2), seed=seeds)
def test_mlp_gradients_with_blocks(head, case, hidden, seed):
    groups, per_group, block_widths, shared = case
    rng = np.random.default_rng(seed)
    batch = groups * per_group
    sizes = [sum(block_widths), *hidden, 2]
    mlp = nets.MLP.create(sizes, head, rng, dtype=np.float64)
    mlp.params["b0"][...] = rng.normal(scale=0.5, size=sizes[1])
    blocks = tuple(
        rng.normal(size=(groups if is_shared else batch, width))
        for width, is_shared in zip(block_widths, shared, strict=True)
    )
    weights = rng.normal(size=(batch, 2))
    cache = away_from_kink(mlp, blocks)

    # The block form computes the same function as the concatenated, repeated input.
    full = np.concatenate(
        [np.repeat(b, per_group, axis=0) if s else b for b, s in zip(blocks, shared, strict=True)],
        axis=1,
    )
    out_full, _ = mlp.forward(full)
    assert_gradient_close(cache.output, out_full, EXACT_TOL, "blocks/fwd")

    d_blocks, grads = mlp.backward(weights, cache)
    assert isinstance(d_blocks, tuple)
    check_all_gradients(mlp, blocks, weights, d_blocks, grads, f"blocks/{head}")

    d_blocks_only, no_grads = mlp.backward(weights, cache, param_grads=False)
    assert no_grads == {}
    for a, b in zip(d_blocks_only, d_blocks, strict=True):
        np.testing.assert_array_equal(a, b)


def test_blocks_of_wrong_width_are_rejected():
    mlp = nets.MLP.create([3, 4, 1], "sigmoid", np.random.default_rng(0), dtype=np.float64)
    with pytest.raises(ValueError, match="do not add up"):
        mlp.forward((np.zeros((2, 1)), np.zeros((2, 1))))


@pytest.mark.parametrize("head", nets.HEADS)
@given(batch=batches, d_in=widths, hidden=st.lists(widths, min_size=1, max_size=2), seed=seeds)
def test_backward_twice_gives_the_same_answer(head, batch, d_in, hidden, seed):
    """No hidden accumulation; and backward, whose leaky-ReLU step works in place on a
    fresh array, leaves the cache and d_out untouched."""
    rng = np.random.default_rng(seed)
    mlp = nets.MLP.create([d_in, *hidden, 3], head, rng, dtype=np.float64)
    x, weights = rng.normal(size=(batch, d_in)), rng.normal(size=(batch, 3))
    _, cache = mlp.forward(x)
    snapshot = [a.copy() for a in (*cache.blocks, *cache.activations, cache.logits, cache.output)]
    weights_before = weights.copy()
    for through_head in (True, False):
        d_x1, grads1 = mlp.backward(weights, cache, through_head=through_head)
        d_x2, grads2 = mlp.backward(weights, cache, through_head=through_head)
        np.testing.assert_array_equal(d_x1, d_x2)
        assert set(grads1) == set(grads2) == set(mlp.params)
        for key in grads1:
            np.testing.assert_array_equal(grads1[key], grads2[key])
    after = [*cache.blocks, *cache.activations, cache.logits, cache.output]
    for before, now in zip(snapshot, after, strict=True):
        np.testing.assert_array_equal(before, now)
    np.testing.assert_array_equal(weights, weights_before)


# ----------------------------------------------------------------------------------------
# The Bernoulli Jensen-Shannon divergence (objective 18).
# ----------------------------------------------------------------------------------------

# t over (0, 1) with its ends: values within 1e-6 of 0 and 1, and 0 and 1 exactly.
targets = st.one_of(
    st.floats(1e-6, 1.0 - 1e-6),
    st.sampled_from([0.0, 1.0, 1e-6, 1.0 - 1e-6]),
)


@given(x=st.lists(st.floats(-6.0, 6.0), min_size=1, max_size=8), data=st.data())
def test_js_divergence_grad_against_finite_differences(x, data):
    """dD_JS/dx = 1/2 p(1-p)(logit p - logit m) against centered differences of D_JS.

    The logits stay within +/-6 (p in [0.0025, 0.9975]): beyond, p(1-p) makes the
    gradient so small that the finite difference's rounding noise (~1e-10 absolute, from
    the O(1) terms that make up D) dominates the relative error; saturated logits are
    checked against a 60-digit reference instead (next test). Likewise where
    x ~ logit m (t ~ p) the gradient vanishes, so we ask |x - logit m| > 0.1 here and
    check t = p separately.
    """
    x = np.array(x)
    t = np.array(data.draw(st.lists(targets, min_size=len(x), max_size=len(x))))
    with np.errstate(divide="ignore"):
        logit_m = logit((nets.sigmoid(x) + t) / 2)
    assume(np.all(np.abs(x - logit_m) > 0.1))

    numeric = numerical_derivative_elementwise(lambda x: nets.js_divergence(x, t), x)
    assert_gradient_close(nets.js_divergence_grad(x, t), numeric, TOL, "js_grad/fd")


def js_reference(x: float, t: float) -> tuple[float, float]:
    """D_JS and its gradient in the logit, in 60-digit decimal arithmetic."""
    with localcontext() as ctx:
        ctx.prec = 60
        x_, t_ = Decimal(x), Decimal(t)
        p, one_minus_p = 1 / (1 + (-x_).exp()), 1 / (1 + x_.exp())
        m, one_minus_m = (p + t_) / 2, (one_minus_p + (1 - t_)) / 2

        def xlogy(a, b):  # a log(a / b), with 0 log 0 = 0
            return Decimal(0) if a == 0 else a * (a / b).ln()

        divergence = (
            xlogy(p, m) + xlogy(one_minus_p, one_minus_m) + xlogy(t_, m)
            + xlogy(1 - t_, one_minus_m)
        ) / 2  # fmt: skip
        grad = p * one_minus_p * (x_ - (m / one_minus_m).ln()) / 2
        return float(divergence), float(grad)


@given(
    x=st.one_of(
        st.floats(-100.0, 100.0), st.sampled_from([-100.0, -50.0, -20.0, 20.0, 50.0, 100.0])
    ),
    t=targets,
)
def test_js_divergence_against_high_precision_reference(x, t):
    """Values and gradients far into saturation, where finite differences cannot reach."""
    divergence_ref, grad_ref = js_reference(x, t)
    divergence = nets.js_divergence(np.array([x]), np.array([t]))
    grad = nets.js_divergence_grad(np.array([x]), np.array([t]))
    assert_gradient_close(divergence, [divergence_ref], TOL, "js/reference")
    assert_gradient_close(grad, [grad_ref], TOL, "js_grad/reference")
    # The floor 1e-8 in the relative error lets tiny gradients pass; ask for true relative
    # accuracy too, away from the gradient's zero at x = logit m (cancellation there).
    p = 1.0 / (1.0 + np.exp(-x))
    if abs(p - t) > 1e-3 and grad_ref != 0.0:
        assert abs(grad[0] - grad_ref) <= 1e-9 * abs(grad_ref), (x, t, grad[0], grad_ref)


@given(
    p=st.lists(st.floats(0.01, 0.99), min_size=1, max_size=8),
    data=st.data(),
)
def test_js_divergence_against_direct_formula(p, data):
    """D_JS = 1/2 KL(p || m) + 1/2 KL(t || m), computed naively for moderate p and t."""
    p = np.array(p)
    t = np.array(data.draw(st.lists(st.floats(0.01, 0.99), min_size=len(p), max_size=len(p))))
    m = (p + t) / 2

    def kl(a, b):
        return a * np.log(a / b) + (1 - a) * np.log((1 - a) / (1 - b))

    direct = 0.5 * kl(p, m) + 0.5 * kl(t, m)
    assert_gradient_close(nets.js_divergence(logit(p), t), direct, TOL, "js/direct")


@given(x=st.floats(-30.0, 30.0), t=targets)
def test_js_divergence_bounds(x, t):
    """0 <= D_JS <= log 2, = 0 at t = p (up to rounding), with a zero gradient there."""
    divergence = float(nets.js_divergence(np.array(x), np.array(t)))
    rounding = 8 * np.finfo(np.float64).eps  # D is a sum of O(1) terms that cancel
    assert -rounding <= divergence <= np.log(2.0) + rounding
    p = nets.sigmoid(np.array(x))
    assert abs(float(nets.js_divergence(np.array(x), p))) <= rounding
    assert abs(float(nets.js_divergence_grad(np.array(x), p))) <= 1e-12


def test_js_divergence_extremes():
    """log 2 when p and t are certain and opposite; 0 when both are certain and agree."""
    x = np.array([-1000.0, 1000.0, -1000.0, 1000.0])
    t = np.array([1.0, 0.0, 0.0, 1.0])
    np.testing.assert_allclose(nets.js_divergence(x, t), [np.log(2)] * 2 + [0.0] * 2, atol=1e-15)


# ----------------------------------------------------------------------------------------
# Stability far into saturation, in both dtypes.
# ----------------------------------------------------------------------------------------

EXTREME_LOGITS = [-1000.0, -100.0, -50.0, 0.0, 50.0, 100.0, 1000.0]
EXTREME_TARGETS = [0.0, 1e-6, 0.3, 1.0 - 1e-6, 1.0]


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_saturated_logits_are_finite_and_silent(dtype):
    x = np.repeat(np.array(EXTREME_LOGITS, dtype=dtype), len(EXTREME_TARGETS))
    t = np.tile(np.array(EXTREME_TARGETS, dtype=dtype), len(EXTREME_LOGITS))
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        results = {
            "js_divergence": nets.js_divergence(x, t),
            "js_divergence_grad": nets.js_divergence_grad(x, t),
            "log_sigmoid": nets.log_sigmoid(x),
            "log_sigmoid_grad": nets.log_sigmoid_grad(x),
            "sigmoid": nets.sigmoid(x),
        }
    for name, value in results.items():
        assert value.dtype == dtype, name
        assert np.all(np.isfinite(value)), (name, value)
    rounding = 8 * float(np.finfo(dtype).eps)
    divergence = results["js_divergence"]
    assert np.all(divergence >= -rounding) and np.all(divergence <= np.log(2) + rounding)
    assert np.all((results["sigmoid"] >= 0) & (results["sigmoid"] <= 1))
    assert np.all(results["log_sigmoid"] <= 0)
    np.testing.assert_array_equal(results["log_sigmoid"][x == -1000], -1000)  # not -inf
    # The gradient pushes p toward t: positive where p > t, negative where p < t.
    p = nets.sigmoid(x.astype(np.float64))
    grad = results["js_divergence_grad"].astype(np.float64)
    assert np.all(grad[p > t + 1e-3] >= 0) and np.all(grad[p < t - 1e-3] <= 0)


# ----------------------------------------------------------------------------------------
# log q from the logit (Eq. 10) and its derivative 1 - q (gradient 6).
# ----------------------------------------------------------------------------------------


@given(x=st.lists(st.floats(-20.0, 20.0), min_size=1, max_size=8))
def test_log_sigmoid(x):
    x = np.array(x)
    log_q = nets.log_sigmoid(x)
    assert_gradient_close(log_q, np.log(nets.sigmoid(x)), TOL, "log_sigmoid/value")
    assert_gradient_close(nets.log_sigmoid_grad(x), 1.0 - nets.sigmoid(x), TOL, "log_sigmoid/1-q")

    numeric = numerical_derivative_elementwise(nets.log_sigmoid, x)
    assert_gradient_close(nets.log_sigmoid_grad(x), numeric, TOL, "log_sigmoid/fd")


# ----------------------------------------------------------------------------------------
# The Bernoulli entropy (objective 8 of the reward-learning ablation) and p(1 - p).
# ----------------------------------------------------------------------------------------


@given(x=st.lists(st.floats(-6.0, 6.0), min_size=1, max_size=8))
def test_sigmoid_grad(x):
    """Within +/-6, as for the JS gradient: beyond, p(1-p) is so small that the rounding
    of p ~ 1 (ulp / eps ~ 1e-10) dominates the finite difference's relative error."""
    x = np.array(x)
    p = nets.sigmoid(x)
    assert_gradient_close(ablations.sigmoid_grad(x), p * (1 - p), TOL, "sigmoid_grad/value")
    numeric = numerical_derivative_elementwise(nets.sigmoid, x)
    assert_gradient_close(ablations.sigmoid_grad(x), numeric, TOL, "sigmoid_grad/fd")


@given(x=st.lists(st.floats(-6.0, 6.0), min_size=1, max_size=8))
def test_bernoulli_entropy_and_its_gradient(x):
    """H = -p log p - (1-p) log(1-p) and dH/dx = -x p(1-p), against finite differences.

    Logits within +/-6, for the reason given at test_sigmoid_grad (saturation is checked
    below). Where x ~ 0 the gradient vanishes (H is maximal at p = 1/2), and the
    difference's relative error with it; |x| > 0.01 keeps the comparison meaningful.
    """
    x = np.array(x)
    p = nets.sigmoid(x)
    direct = -p * np.log(p) - (1 - p) * np.log1p(-p)
    assume(np.all(np.isfinite(direct)) and np.all(np.abs(x) > 0.01))
    assert_gradient_close(ablations.bernoulli_entropy(x), direct, TOL, "entropy/value", floor=1e-6)
    assert np.all(ablations.bernoulli_entropy(x) <= np.log(2.0) + 1e-15)
    numeric = numerical_derivative_elementwise(ablations.bernoulli_entropy, x)
    assert_gradient_close(ablations.bernoulli_entropy_grad(x), numeric, TOL, "entropy/fd")


def test_bernoulli_entropy_saturates_without_nan():
    x = np.array([-1000.0, -50.0, 0.0, 50.0, 1000.0])
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        h, g = ablations.bernoulli_entropy(x), ablations.bernoulli_entropy_grad(x)
    assert np.all(np.isfinite(h)) and np.all(np.isfinite(g))
    np.testing.assert_allclose(h[[0, 4]], 0.0, atol=1e-300)
    assert h[2] == pytest.approx(np.log(2.0))


# ----------------------------------------------------------------------------------------
# RMSProp, the learning-rate schedule, the soft update.
# ----------------------------------------------------------------------------------------


@given(
    shape=st.tuples(batches, widths),
    lr=st.floats(1e-5, 1e-1),
    decay=st.floats(0.5, 0.999),
    seed=seeds,
)
def test_rmsprop_against_closed_form(shape, lr, decay, seed):
    """From a zero mean square, two steps with the same gradient g move each parameter by
    lr g / (sqrt(1 - d) |g| + eps), then by lr g / (sqrt((1 - d)(1 + d)) |g| + eps).

    Parameters start at 0, so they hold the steps themselves, free of the rounding of
    O(1) values (which would swamp a 1e-5 step at 1e-12 relative error).
    """
    g = np.random.default_rng(seed).normal(size=shape)
    params = {"W": np.zeros(shape)}
    opt = nets.RMSProp(decay=decay)
    opt.step(params, {"W": g}, lr)
    step_one = lr * g / (np.sqrt(1 - decay) * np.abs(g) + opt.eps)
    assert_gradient_close(params["W"], -step_one, EXACT_TOL, "rmsprop/one_step")
    assert_gradient_close(opt.mean_square["W"], (1 - decay) * g * g, EXACT_TOL, "rmsprop/ms")
    opt.step(params, {"W": g}, lr)
    step_two = lr * g / (np.sqrt((1 - decay) * (1 + decay)) * np.abs(g) + opt.eps)
    assert_gradient_close(params["W"], -(step_one + step_two), EXACT_TOL, "rmsprop/two_steps")


@given(seed=seeds, lr=st.floats(1e-5, 1e-1))
def test_rmsprop_two_different_steps(seed, lr):
    g1, g2 = np.random.default_rng(seed).normal(size=(2, 4, 3))
    opt, params = nets.RMSProp(), {"W": np.zeros((4, 3))}
    assert (opt.decay, opt.eps) == (0.995, 1e-8)  # Appendix B
    ms1 = 0.005 * g1**2
    ms2 = 0.995 * ms1 + 0.005 * g2**2
    opt.step(params, {"W": g1}, lr)
    step_one = lr * g1 / (np.sqrt(ms1) + 1e-8)
    assert_gradient_close(params["W"], -step_one, EXACT_TOL, "rmsprop/one_step")
    opt.step(params, {"W": g2}, lr / 2)
    step_two = lr / 2 * g2 / (np.sqrt(ms2) + 1e-8)
    # Steps of opposite sign can cancel: compare to 1e-12 of the step scale lr there.
    expected = -(step_one + step_two)
    assert_gradient_close(params["W"], expected, EXACT_TOL, "rmsprop/two_steps", floor=lr)


def test_rmsprop_keeps_float32():
    params = {"W": np.ones((3, 2), np.float32), "b": np.zeros(2, np.float32)}
    grads = {"W": np.full((3, 2), 0.5), "b": np.ones(2, np.float32)}  # W's gradient float64
    opt = nets.RMSProp()
    for _ in range(2):
        opt.step(params, grads, 1e-3)
    for key in params:
        assert params[key].dtype == np.float32
        assert opt.mean_square[key].dtype == np.float32


def test_linear_decay():
    assert nets.linear_decay(1e-3, 0, 1000) == 1e-3
    assert nets.linear_decay(1e-3, 500, 1000) == pytest.approx(5e-4)
    assert nets.linear_decay(1e-3, 1000, 1000) == 0.0
    assert nets.linear_decay(1e-3, 1500, 1000) == 0.0  # never negative past the budget


@given(tau=st.one_of(st.just(1e-3), st.floats(0.0, 1.0)), seed=seeds)
def test_soft_update(tau, seed):
    rng = np.random.default_rng(seed)
    source = nets.MLP.create([3, 4, 2], "sigmoid", rng, dtype=np.float64)
    target = nets.MLP.create([3, 4, 2], "sigmoid", rng, dtype=np.float64)
    for params in (source.params, target.params):
        for value in params.values():
            value[...] = rng.normal(size=value.shape)
    before, source_before = target.copy(), source.copy()
    nets.soft_update(target, source, tau)
    for key, value in target.params.items():
        expected = tau * source.params[key] + (1 - tau) * before.params[key]
        assert_gradient_close(value, expected, EXACT_TOL, "soft_update")
        np.testing.assert_array_equal(source.params[key], source_before.params[key])


def test_soft_update_default_tau():
    source = nets.MLP.create([2, 2], "identity", np.random.default_rng(0), dtype=np.float64)
    target = source.copy()
    for value in target.params.values():
        value[...] = 0.0
    for value in source.params.values():
        value[...] = 1.0
    nets.soft_update(target, source)
    for value in target.params.values():
        np.testing.assert_allclose(value, 1e-3, rtol=1e-15)


# ----------------------------------------------------------------------------------------
# float32 stays float32.
# ----------------------------------------------------------------------------------------


@pytest.mark.parametrize("head", nets.HEADS)
@pytest.mark.parametrize("input_dtype", [np.float32, np.float64])
def test_float32_network_does_float32_work(head, input_dtype):
    rng = np.random.default_rng(0)
    mlp = nets.MLP.create([5, 8, 8, 2], head, rng, dtype=np.float32)
    assert all(value.dtype == np.float32 for value in mlp.params.values())
    mlp64 = nets.MLP(mlp.sizes, head, {k: v.astype(np.float64) for k, v in mlp.params.items()})
    x = rng.normal(size=(6, 5)).astype(input_dtype)
    blocks = (rng.normal(size=(2, 3)).astype(input_dtype), x[:, :2])  # shared + full
    d_out = rng.normal(size=(6, 2)).astype(input_dtype)
    for inputs in (x, blocks):
        out, cache = mlp.forward(inputs)
        assert out.dtype == np.float32 and cache.logits.dtype == np.float32
        assert all(a.dtype == np.float32 for a in cache.activations)
        for through_head in (True, False):
            for param_grads in (True, False):
                d_x, grads = mlp.backward(
                    d_out, cache, through_head=through_head, param_grads=param_grads
                )
                for d in d_x if isinstance(d_x, tuple) else (d_x,):
                    assert d.dtype == np.float32
                assert len(grads) == (len(mlp.params) if param_grads else 0)
                assert all(g.dtype == np.float32 for g in grads.values())

                # ... and agrees with the same network in float64 to float32 precision.
                out64, cache64 = mlp64.forward(
                    tuple(b.astype(np.float64) for b in inputs)
                    if isinstance(inputs, tuple)
                    else inputs.astype(np.float64)
                )
                np.testing.assert_allclose(out, out64, rtol=1e-5, atol=1e-6)
                d_x64, grads64 = mlp64.backward(
                    d_out, cache64, through_head=through_head, param_grads=param_grads
                )
                for d, d64 in zip(
                    d_x if isinstance(d_x, tuple) else (d_x,),
                    d_x64 if isinstance(d_x64, tuple) else (d_x64,),
                    strict=True,
                ):
                    np.testing.assert_allclose(d, d64, rtol=1e-4, atol=1e-5)
                for key, g in grads.items():
                    np.testing.assert_allclose(g, grads64[key], rtol=1e-4, atol=1e-5)


def test_float32_elementwise_pieces():
    x = np.linspace(-5, 5, 7, dtype=np.float32)
    t = np.full(7, 0.3, dtype=np.float32)
    for fn in (nets.sigmoid, nets.softplus, nets.log_sigmoid, nets.log_sigmoid_grad):
        assert fn(x).dtype == np.float32, fn.__name__
    for head in nets.HEADS:
        out = nets.head_forward(head, x)
        assert out.dtype == np.float32
        assert nets.head_backward(head, np.ones_like(x), out).dtype == np.float32
    assert nets.js_divergence(x, t).dtype == np.float32
    assert nets.js_divergence_grad(x, t).dtype == np.float32
    for fn in (
        ablations.sigmoid_grad,
        ablations.bernoulli_entropy,
        ablations.bernoulli_entropy_grad,
    ):
        assert fn(x).dtype == np.float32, fn.__name__


# ----------------------------------------------------------------------------------------
# The checker itself: a right gradient passes, a wrong one is reported.
# ----------------------------------------------------------------------------------------


def test_numerical_gradient_restores_its_input_and_is_accurate():
    rng = np.random.default_rng(0)
    x, c = rng.normal(size=(3, 4)), rng.normal(size=(3, 4))
    x_before = x.copy()
    numeric = numerical_gradient(lambda: np.sum(c * x**3), x)
    np.testing.assert_array_equal(x, x_before)
    assert relative_error(numeric, 3 * c * x**2) < 1e-6
    with pytest.raises(TypeError, match="float64"):
        numerical_gradient(lambda: 0.0, x.astype(np.float32))


def test_relative_error_definition():
    assert relative_error([1.0, 2.0], [1.0, 2.0]) == 0.0
    assert relative_error([1.0], [3.0]) == pytest.approx(0.5)
    assert relative_error([1e-12], [0.0]) == pytest.approx(1e-4)  # the 1e-8 floor
    np.testing.assert_allclose(relative_errors([1.0, -1.0], [1.0, 1.0]), [0.0, 1.0])


def test_checker_message_names_the_worst_element():
    analytic, numeric = np.zeros((2, 3)), np.zeros((2, 3))
    analytic[1, 2], numeric[1, 2] = 1.0, 2.0
    with pytest.raises(AssertionError, match=r"index \(1, 2\).*analytic 1\.0.*numeric 2\.0"):
        assert_gradient_close(analytic, numeric, name="example")
    with pytest.raises(AssertionError, match="shape"):
        assert_gradient_close(np.zeros(3), np.zeros(4))
    with pytest.raises(AssertionError, match="non-finite"):
        assert_gradient_close(np.array([np.nan]), np.array([0.0]))


def assert_separated(right, wrong, numeric, name, floor=1e-8):
    """The right gradient passes, the wrong one fails by a wide margin."""
    assert_gradient_close(right, numeric, TOL, f"checker/right/{name}", floor=floor)
    assert relative_error(wrong, numeric, floor) > 1e3 * TOL
    with pytest.raises(AssertionError, match="relative error"):
        assert_gradient_close(wrong, numeric, TOL, f"checker/wrong/{name}", floor=floor)


@given(batch=batches, d_in=widths, width=st.integers(2, 6), seed=seeds)
def test_checker_catches_transposed_weight_gradient(batch, d_in, width, seed):
    rng = np.random.default_rng(seed)
    mlp = nets.MLP.create([d_in, width, width, 1], "identity", rng, dtype=np.float64)
    x, weights = rng.normal(size=(batch, d_in)), rng.normal(size=(batch, 1))
    cache = away_from_kink(mlp, x)
    _, grads = mlp.backward(weights, cache)
    numeric = numerical_gradient(linear_loss(mlp, x, weights), mlp.params["W1"])
    # A rank-one gradient a d^T can be symmetric by accident only if a ~ d, and an
    # all-tiny one (every unit off, batch 1) is checked in absolute terms; skip both.
    assume(relative_error(grads["W1"], grads["W1"].T, FD_FLOOR) > 1e-2)
    assert_separated(grads["W1"], grads["W1"].T, numeric, "transposed_W", floor=FD_FLOOR)


@given(x=st.lists(st.floats(-6.0, 6.0), min_size=1, max_size=8), seed=seeds)
def test_checker_catches_js_gradient_without_its_half(x, seed):
    x = np.array(x)
    t = np.random.default_rng(seed).uniform(0.0, 1.0, size=x.shape)
    assume(np.all(np.abs(x - logit((nets.sigmoid(x) + t) / 2)) > 0.1))
    numeric = numerical_derivative_elementwise(lambda x: nets.js_divergence(x, t), x)
    p = nets.sigmoid(x)
    right = nets.js_divergence_grad(x, t)
    assert_separated(right, p * (1 - p) * (x - logit((p + t) / 2)), numeric, "js_without_half")


@given(rows=batches, cols=widths, seed=seeds)
def test_checker_catches_leaky_relu_backward_with_slope_zero(rows, cols, seed):
    rng = np.random.default_rng(seed)
    x = rng.normal(size=(rows, cols))
    assume(np.abs(x).min() > KINK_MARGIN and np.any(x < 0))
    weights = rng.normal(size=x.shape)

    def g(x):
        return nets.leaky_relu_(x.copy(), np.empty_like(x)) * weights

    h = nets.leaky_relu_(x.copy(), np.empty_like(x))
    right = nets.leaky_relu_backward_(weights.copy(), h, np.empty_like(x))
    wrong = weights * (h > 0)  # the plain ReLU's derivative
    numeric = numerical_derivative_elementwise(g, x)
    assert_separated(right, wrong, numeric, "leaky_slope_0")


@pytest.mark.parametrize("wrong_derivative", ["q", "1-q"])
@given(rows=batches, cols=widths, seed=seeds)
def test_checker_catches_sigmoid_head_missing_a_factor(wrong_derivative, rows, cols, seed):
    rng = np.random.default_rng(seed)
    logits = rng.uniform(-5.0, 5.0, size=(rows, cols))
    weights = rng.normal(size=logits.shape)
    q = nets.sigmoid(logits)
    numeric = numerical_derivative_elementwise(lambda z: nets.sigmoid(z) * weights, logits)
    right = nets.head_backward("sigmoid", weights, q)
    wrong = weights * (q if wrong_derivative == "q" else 1 - q)
    assert_separated(right, wrong, numeric, f"sigmoid_head_missing_{wrong_derivative}")


@given(x=st.lists(st.floats(-6.0, 6.0), min_size=1, max_size=8))
def test_checker_catches_entropy_gradient_without_its_sigmoid_factor(x):
    """dH/dp = -x taken for dH/dx (the chain rule's p(1-p) forgotten) is caught."""
    x = np.array(x)
    assume(np.all(np.abs(x) > 0.01))
    numeric = numerical_derivative_elementwise(ablations.bernoulli_entropy, x)
    assert_separated(ablations.bernoulli_entropy_grad(x), -x, numeric, "entropy_without_p(1-p)")
