"""controllers/lbfgs.py: torch's L-BFGS with a line search whose square root is IEEE-exact (the same bits
on every CPU); the emulated-CPU test of the whole training is in tests/test_numeric_env.py."""

from __future__ import annotations

import math

import pytest
import torch
import torch.optim.lbfgs as torch_lbfgs

from controllers.lbfgs import LBFGS, cpu_independent_line_search, cubic_minimum


def test_torch_still_has_the_interpolation_it_replaces():
    """torch is pinned; a version that renames its line search's interpolation must fail here, loudly."""
    assert callable(torch_lbfgs._cubic_interpolate) and callable(torch_lbfgs._strong_wolfe)


@pytest.mark.parametrize("points", [
    (0.0, 1.0, -2.0, 1.0, 0.5, 1.0),  # the minimum between the points
    (2.0, 0.5, 1.0, 0.0, 1.0, -2.0),  # the same, the farther point first
    (0.0, 0.0, -1.0, 1.0, -0.25, -0.5),
    (-1.5, 3.0, -4.0, 2.5, 1.0, 2.0),
])
def test_the_cubic_minimum_is_torchs_where_torchs_square_root_is_exact(points):
    """Where torch.sqrt happens to be correctly rounded (these discriminants), torch's interpolation and the
    replacement give the same bits: the replacement changes nothing but the square root."""
    ours = cubic_minimum(*points)
    theirs = torch_lbfgs._cubic_interpolate(*(torch.tensor(v, dtype=torch.float64) for v in points))
    x1, f1, g1, x2, f2, g2 = points
    d1 = g1 + g2 - 3 * (f1 - f2) / (x1 - x2)
    square = d1 * d1 - g1 * g2
    assert float(torch.tensor(square, dtype=torch.float64).sqrt()) == math.sqrt(square)  # the premise
    assert ours == float(theirs)


def test_the_cubic_minimum_is_the_cubics_minimiser():
    """Against the closed form: the cubic with f(0) = 0, f'(0) = -3, f(2) = 2, f'(2) = 9 is x^3 - 3x, minimum at 1."""
    assert cubic_minimum(0.0, 0.0, -3.0, 2.0, 2.0, 9.0) == pytest.approx(1.0, abs=1e-15)
    assert cubic_minimum(0.0, 0.0, -3.0, 2.0, 2.0, 9.0, bounds=(1.5, 3.0)) == 1.5  # clamped to the bounds
    # no minimum (slopes 1 at both ends and a secant slope of 2/3: the discriminant is -1): the middle of the bounds
    assert cubic_minimum(0.0, 0.0, 1.0, 1.0, 2 / 3, 1.0, bounds=(0.0, 4.0)) == 2.0


def test_the_replacement_is_in_force_during_a_step_only():
    x = torch.tensor([3.0, -2.0], dtype=torch.float64, requires_grad=True)
    seen = []

    def closure():
        seen.append(torch_lbfgs._cubic_interpolate is cubic_minimum)
        optimizer.zero_grad()
        loss = ((x - 1.0) ** 2).sum() + 0.1 * ((x - 1.0) ** 4).sum()
        loss.backward()
        return loss

    optimizer = LBFGS([x], max_iter=50, line_search_fn="strong_wolfe")
    optimizer.step(closure)
    assert seen and all(seen) and torch_lbfgs._cubic_interpolate is not cubic_minimum
    assert torch.allclose(x, torch.ones(2, dtype=torch.float64), atol=1e-6)  # it still minimises
    with pytest.raises(RuntimeError, match="boom"):  # restored after an error too
        with cpu_independent_line_search():
            raise RuntimeError("boom")
    assert torch_lbfgs._cubic_interpolate is not cubic_minimum
