"""The user guide's Python example (docs/guide/python-controller.md) runs as written, with the public names
of the package top level."""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np

from cosim.study.vocabulary import PAPER_SPEC

README = Path(__file__).resolve().parents[1] / "docs" / "guide" / "python-controller.md"


def readme_example() -> str:
    text = README.read_text(encoding="utf-8")
    match = re.search(r"<!-- python-api-example -->\n```python\n(.*?)```", text, re.DOTALL)
    assert match, "the user guide lost its Python example"
    return match.group(1)


def test_the_readme_example_runs_a_controller_on_the_plant_fmu(capsys):
    code = readme_example()
    assert len([line for line in code.splitlines() if line.strip()]) <= 20
    namespace: dict = {}
    exec(compile(code, str(README), "exec"), namespace)  # exactly the guide's lines
    result = namespace["result"]
    assert result.complete and result.metadata["controller"]["name"] == "integrator"
    tail = result.frame[result.frame["time"] > 0.025]
    assert abs(np.mean(tail["measured_output_voltage"]) - 12.0) < 0.05  # the integrator regulates
    assert "output_voltage" in capsys.readouterr().out


def test_the_public_names_are_importable_from_the_top_level():
    import cosim

    for name in cosim.__all__:
        assert getattr(cosim, name) is not None, name
    assert set(cosim.__all__) <= set(dir(cosim))


def test_simulate_refuses_a_controller_whose_duty_limits_are_not_a_fraction():
    """A controller written for a duty in percent, duty_limits (0, 100), ran at full duty and recorded 50 as the duty
    cycle; the command line refused it, the Python API now does too, before the plant steps."""
    import pytest

    from cosim import builtin_binding, load_scenario, simulate
    from cosim.base.errors import ConfigError

    class Percent:
        name, sample_period, duty_limits = "percent", 1e-3, (0.0, 100.0)

        def reset(self):
            pass

        def step(self, measurement):
            return 50.0

        def describe(self):
            return {"name": self.name}

    with pytest.raises(ConfigError, match=r"^controller percent: duty limits \(0.0, 100.0\) are invalid: expected "
                                          r"0 <= min < max <= 1$"):
        simulate(builtin_binding("averaged"), Percent(), load_scenario("startup", PAPER_SPEC))


def test_simulate_takes_names_and_paths_as_the_command_line_does_and_names_the_mistakes_it_cannot_take(tmp_path):
    """A scenario's name or file and a binding file's path work as on the command line (they were AttributeErrors
    deep inside); a controller class for an instance and a period as text are named in one line."""
    import pytest

    from controllers.pi import PIController
    from cosim import builtin_binding, load_scenario, simulate
    from cosim.base.errors import ConfigError

    pi = PIController(0.0017, 15.6, 1e-3)
    by_name = simulate(builtin_binding("averaged"), pi, "startup")
    by_object = simulate(builtin_binding("averaged"), pi, load_scenario("startup", PAPER_SPEC))
    np.testing.assert_array_equal(by_name.frame["output_voltage"], by_object.frame["output_voltage"])
    with pytest.raises(TypeError, match=r"^controller PIController is a class: pass an instance, PIController\(\.\.\.\)$"):
        simulate(builtin_binding("averaged"), PIController, "startup")
    with pytest.raises(ConfigError, match=r"^record period = '1e-5' is invalid: expected a number of seconds$"):
        simulate(builtin_binding("averaged"), pi, "startup", record_period="1e-5")
    with pytest.raises(ConfigError, match=r"binding file \S+none.toml does not exist"):
        simulate(str(tmp_path / "none.toml"), pi, "startup")
