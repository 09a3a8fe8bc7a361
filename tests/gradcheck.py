"""Finite-difference gradient checks, cs231n style, shared by every gradient test.

Usage, for a scalar loss `f()` that reads the array `x` (a parameter, an input):

    numeric = numerical_gradient(f, x)          # perturbs x in place, then restores it
    assert_gradient_close(analytic, numeric)    # relative error below 1e-6

Checks run in float64: with eps = 1e-6 a centered difference has truncation error
O(eps^2 f''') ~ 1e-12 and rounding error O(ulp(f) / eps) ~ 1e-10 |f|, so a correct
gradient of an O(1) loss agrees to about 1e-8 relative error element by element, while
a wrong one (a missing factor, a transposed matrix) is off by O(1).

The rounding error is absolute: an element whose gradient is far smaller than the loss
(a weight behind a leaky-ReLU unit that is off, slope 0.01) cannot be resolved to 1e-6
relative error. Such checks pass a larger `floor`, which turns the comparison of tiny
elements into an absolute one, |a - b| <= tol * floor, and say why.
"""

from __future__ import annotations

import numpy as np

RELATIVE_ERROR_FLOOR = 1e-8


def numerical_gradient(f, x: np.ndarray, eps: float = 1e-6) -> np.ndarray:
    """d f() / d x by centered differences, one element at a time.

    `f` takes no argument and reads `x`; each element of `x` is moved to x_i +/- eps in
    place and restored afterwards (exactly: the saved value is written back), so `x` is
    unchanged on return, even if `f` raises.
    """
    if x.dtype != np.float64:
        raise TypeError(f"gradient checks run in float64, got {x.dtype}")
    grad = np.zeros_like(x)
    it = np.nditer(x, flags=["multi_index"])
    for _ in it:
        i = it.multi_index
        saved = x[i].copy()
        try:
            x[i] = saved + eps
            f_plus = float(f())
            x[i] = saved - eps
            f_minus = float(f())
        finally:
            x[i] = saved
        grad[i] = (f_plus - f_minus) / (2.0 * eps)
    return grad


def numerical_derivative_elementwise(g, x: np.ndarray, eps: float = 1e-6) -> np.ndarray:
    """g'(x) for an element-wise function g, by centered differences of all elements at
    once: (g(x + eps) - g(x - eps)) / (2 eps).

    For element-wise pieces this beats `numerical_gradient` of sum(g(x)): each element's
    rounding error then scales with its own g, not with the largest term of the sum.
    """
    if x.dtype != np.float64:
        raise TypeError(f"gradient checks run in float64, got {x.dtype}")
    return (g(x + eps) - g(x - eps)) / (2.0 * eps)


def relative_errors(a, b, floor: float = RELATIVE_ERROR_FLOOR) -> np.ndarray:
    """Element-wise |a - b| / max(floor, |a| + |b|), floor 1e-8 unless told."""
    a, b = np.asarray(a, dtype=np.float64), np.asarray(b, dtype=np.float64)
    return np.abs(a - b) / np.maximum(floor, np.abs(a) + np.abs(b))


def relative_error(a, b, floor: float = RELATIVE_ERROR_FLOOR) -> float:
    """max over elements of |a - b| / max(1e-8, |a| + |b|); 0 for empty arrays."""
    errors = relative_errors(a, b, floor)
    return float(errors.max()) if errors.size else 0.0


def assert_gradient_close(
    analytic,
    numeric,
    tol: float = 1e-6,
    name: str = "gradient",
    *,
    floor: float = RELATIVE_ERROR_FLOOR,
) -> float:
    """Raise AssertionError unless every element agrees to relative error `tol`.

    Returns the worst relative error, so a caller can record it. The message names the
    worst element, its index and both values. `floor`: see the module docstring.
    """
    analytic, numeric = np.asarray(analytic), np.asarray(numeric)
    if analytic.shape != numeric.shape:
        raise AssertionError(
            f"{name}: analytic shape {analytic.shape} != numeric shape {numeric.shape}"
        )
    if not np.all(np.isfinite(analytic)):
        raise AssertionError(f"{name}: analytic gradient has non-finite values")
    errors = relative_errors(analytic, numeric, floor)
    worst = float(errors.max()) if errors.size else 0.0
    if worst > tol:
        index = tuple(int(i) for i in np.unravel_index(int(errors.argmax()), errors.shape))
        raise AssertionError(
            f"{name}: relative error {worst:.3e} > {tol:.1e} at index {index}: "
            f"analytic {float(analytic[index])!r}, numeric {float(numeric[index])!r} "
            f"(shape {analytic.shape}; {int((errors > tol).sum())} of {errors.size} "
            f"elements exceed the tolerance)"
        )
    _record(name, worst)
    return worst


# Worst relative error seen per check name, for reporting (see `worst_errors`).
_WORST: dict[str, float] = {}


def _record(name: str, error: float) -> None:
    if error > _WORST.get(name, -1.0):
        _WORST[name] = error


def worst_errors() -> dict[str, float]:
    """{check name: worst relative error} over the passing `assert_gradient_close` calls
    so far (the checker's own tests, which expect failures, are not recorded)."""
    return dict(_WORST)
