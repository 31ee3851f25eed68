"""torch's L-BFGS with a line search whose arithmetic is the same on every x86-64 CPU.

The networks (:mod:`controllers.nn_model`, :mod:`controllers.explicit_policy`) are trained with
full-batch L-BFGS and the strong-Wolfe line search of ``torch.optim.LBFGS``. That line search picks
its trial steps by cubic interpolation, which takes a square root -- of a 0-dim tensor, so with
``torch.sqrt``. ``torch.sqrt`` (like ``torch.log``) is not correctly rounded for float64 on the CPU and
its result depends on the CPU beyond the kernels :mod:`cosim.base.numeric_env` pins: measured with
the workbench's pinned environment, the same 20 011 inputs give other last bits on an AVX-512 CPU
(AMD Zen 4) than on AVX2-only CPUs (Intel Haswell and AMD Zen 2, emulated by QEMU), while ``exp``,
``tanh``, the matrix products and the reductions agree bit for bit. One differing trial step is
enough: L-BFGS amplifies it into other weights after a few iterations, and the reproduction's models
and conclusions differed between machines.

:class:`LBFGS` is ``torch.optim.LBFGS`` unchanged, except that during its ``step`` the cubic
interpolation is :func:`cubic_minimum`: the same formula (Nocedal & Wright, *Numerical Optimization*,
eq. 3.59) evaluated in Python floats, whose square root (``math.sqrt``) is IEEE correctly rounded on
every CPU. Written here rather than using another optimizer so that training keeps torch's
algorithm, settings and results wherever the square root was exact already. It replaces the
private ``torch.optim.lbfgs._cubic_interpolate`` for the duration of a step (torch is pinned to one
version; ``tests/test_lbfgs.py`` fails if that function moves).
"""

from __future__ import annotations

import math
import threading
from contextlib import contextmanager

import torch
import torch.optim.lbfgs as _torch_lbfgs

_lock = threading.Lock()


def cubic_minimum(x1, f1, g1, x2, f2, g2, bounds=None) -> float:
    """The minimiser of the cubic through two points with values ``f`` and slopes ``g``, clamped to
    ``bounds`` (default: between the points); the bounds' midpoint when the cubic has no minimum.

    Arguments may be floats or 0-dim tensors; the arithmetic is done in Python floats."""
    x1, f1, g1, x2, f2, g2 = (float(v) for v in (x1, f1, g1, x2, f2, g2))
    if bounds is None:
        low, high = (x1, x2) if x1 <= x2 else (x2, x1)
    else:
        low, high = (float(b) for b in bounds)
    d1 = g1 + g2 - 3 * (f1 - f2) / (x1 - x2)
    discriminant = d1 * d1 - g1 * g2
    if discriminant < 0:
        return (low + high) / 2.0
    d2 = math.sqrt(discriminant)
    if x1 <= x2:  # measured from the farther point, as the formula is written
        step = x2 - (x2 - x1) * ((g2 + d2 - d1) / (g2 - g1 + 2 * d2))
    else:
        step = x1 - (x1 - x2) * ((g1 + d2 - d1) / (g1 - g2 + 2 * d2))
    return min(max(step, low), high)


@contextmanager
def cpu_independent_line_search():
    """torch's strong-Wolfe line search with :func:`cubic_minimum` as its interpolation, for this block."""
    with _lock:
        original = _torch_lbfgs._cubic_interpolate
        _torch_lbfgs._cubic_interpolate = cubic_minimum
        try:
            yield
        finally:
            _torch_lbfgs._cubic_interpolate = original


class LBFGS(torch.optim.LBFGS):
    """``torch.optim.LBFGS`` whose line search computes the same bytes on every x86-64 CPU (module docstring)."""

    def step(self, closure):
        with cpu_independent_line_search():
            return super().step(closure)
