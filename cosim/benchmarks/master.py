"""Group master: the master's overhead against the raw fmpy floor."""

from __future__ import annotations

import statistics
import time

from cosim.benchmarks.common import BenchRow
from cosim.benchmarks.subjects import _RawSlave


class _Constant:
    name = "constant"
    duty_limits = (0.0, 1.0)

    def __init__(self, period):
        self.sample_period = period

    def reset(self):
        pass

    def step(self, measurement):
        return 0.25

    def describe(self):
        return {"type": "constant", "name": self.name, "duty_limits": [0.0, 1.0]}


def _raw_floor(step: float, count: int) -> float:
    """Seconds per macro step of the bare loop: fmpy setReal + doStep + getReal."""
    slave = _RawSlave({"plant_mode": 0})
    vr = slave.vr
    inputs, outputs = [vr["duty_cycle"]], [vr["output_voltage"], vr["inductor_current"], vr["load_current"]]
    fmu = slave.fmu
    try:
        start = time.perf_counter()
        for i in range(count):
            fmu.setReal(inputs, [0.25])
            fmu.doStep(i * step, step)
            fmu.getReal(outputs)
        return (time.perf_counter() - start) / count
    finally:
        slave.close()


def _master_step(step: float, count: int, isolate: bool = False) -> float:
    from cosim.fmi.binding import builtin_binding
    from cosim.fmi.plant import open_plant
    from cosim.master import run
    from cosim.scenarios import parse_scenario

    scenario = parse_scenario(f'name = "bench"\nduration = {count * step!r}\n[initial]\nreference = 12.0\n'
                              'load_resistance = 6.0\ninput_voltage = 48.0\n')
    with open_plant(builtin_binding("averaged"), isolate=isolate) as plant:
        start = time.perf_counter()
        result = run(plant, _Constant(step), scenario, record_period=step)
        elapsed = time.perf_counter() - start
    return elapsed / (len(result.frame) - 1)


def bench_master(quick: bool) -> list[BenchRow]:
    step = 1e-5
    count = 200 if quick else 20000
    repeats = 1 if quick else 5
    floors, masters = [], []
    for _ in range(repeats):  # interleaved, so drift hits both alike
        floors.append(_raw_floor(step, count))
        masters.append(_master_step(step, count))
    ratios = [m / f for m, f in zip(masters, floors)]
    ratio = statistics.median(ratios)
    isolated = [_master_step(step, count // 4 if not quick else count, isolate=True) for _ in range(repeats)]
    cost = statistics.median(isolated) - statistics.median(masters)
    return [
        BenchRow("raw fmpy floor: setReal + doStep + getReal per macro step (averaged, 10 us)",
                 statistics.median(floors) * 1e6, None, "us"),
        BenchRow("master per macro step, plant FMU isolated in a child process (--isolate)",
                 statistics.median(isolated) * 1e6, None, "us", "",
                 None, f"isolation adds {cost * 1e6:.3g} us per instant (one pipe round trip); it is the default for "
                       "binding-file plants only, whose FMUs are foreign code and slower per step anyway"),
        BenchRow("isolation cost ratio: isolated / in-process master per macro step",
                 statistics.median(isolated) / statistics.median(masters), None, "ratio"),
        BenchRow("master per macro step (control + record every 10 us, constant controller)",
                 statistics.median(masters) * 1e6, None, "us"),
        BenchRow("master overhead ratio: master / raw fmpy floor (median of interleaved repeats)",
                 ratio, max(ratios), "ratio", "<= 1.5", bool(ratio <= 1.5),
                 "p99 column: worst repeat"),
    ]
