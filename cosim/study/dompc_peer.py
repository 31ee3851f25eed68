"""The NNPC's problem solved by do-mpc (CasADi + IPOPT): the benchmark suite's peer for the RTI.

Same problem as the workbench's NNPC (:class:`~controllers.predictive.PredictiveController`): the same
trained network, now a CasADi expression built from the weights and normalisation stored in the model
file (:func:`casadi_network`; the workbench's numpy path folds the normalisation into the layers, this one
does not, and a test checks both agree to 1e-12); the same horizon, move blocks (equality constraints
added to do-mpc's NLP between ``prepare_nlp`` and ``create_nlp``), duty bounds, discount and eq. 16 cost;
the same measured history, load estimate and offset-free disturbance estimate (:class:`DoMpcNnpc` is a
:class:`PredictiveController` whose :meth:`plan` asks do-mpc). IPOPT needs a smooth objective, so the norm
is the RTI's smoothed sqrt(|e|^2 + eps^2) with the same eps; the cost each plan achieves is reported in
the paper's exact eq. 16 (the workbench's rollout of the plan), as for the RTI.

do-mpc and casadi are the ``bench`` extra of the package (pinned), not the core install.
"""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np

from controllers.nn_model import NNPlantModel, load_model
from controllers.predictive import PredictiveController, RtiSettings
from controllers.predictors import NNPredictor, PredictionContext


def casadi_network(model: NNPlantModel):
    """``casadi.Function`` x (n_inputs) -> [iL(k), vc(k)] in physical units, from the model's stored layers
    and normalisation (not the numpy path's folded weights)."""
    import casadi
    import torch

    config = model.config
    x = casadi.SX.sym("x", config.n_inputs)
    h = (x - casadi.DM(model.input_mean)) / casadi.DM(model.input_std)
    for layer in model.network.layers:
        if isinstance(layer, torch.nn.Linear):
            h = casadi.mtimes(casadi.DM(layer.weight.detach().numpy()), h) + casadi.DM(layer.bias.detach().numpy())
        elif config.activation == "tanh":
            h = casadi.tanh(h)
        elif config.activation == "sigmoid":
            h = 1.0 / (1.0 + casadi.exp(-h))
        else:
            h = casadi.fmax(h, 0.0)
    y = h * casadi.DM(model.output_std) + casadi.DM(model.output_mean)
    if config.residual:
        y = y + x[:2]
    return casadi.Function("network", [x], [y], ["x"], ["y"])


def casadi_network_from_file(path: Path, expect_period: float | None = None):
    """:func:`casadi_network` of the model file at ``path`` (read and checked by :func:`load_model`)."""
    return casadi_network(load_model(Path(path), expect_period=expect_period))


class DoMpcNnpc(PredictiveController):
    """The NNPC with do-mpc as its optimizer (the estimation and the protocol are the workbench's own).

    The do-mpc model is discrete: state s = [iL(k), vo(k)] and, for each older row r = 1..delays-1 of the
    history, [iL(k-r), vo(k-r), d(k-r)]; input d(k); the network's next state plus the disturbance estimate;
    parameters (one scenario, set before each solve) the disturbance, the extra signals and the targets;
    a time-varying weight carries the discount (do-mpc's stage cost sits on the state at the start of each
    step, so step 0 weighs 0 and step k weighs gamma^(k-1); the terminal cost weighs the last state)."""

    def __init__(self, model: NNPlantModel, sample_period: float, settings, duty_limits=(0.0, 1.0),
                 name: str = "NNPC-do-mpc", *, nominal_load: float, nominal_input_voltage: float,
                 smoothing: float = RtiSettings().smoothing):
        super().__init__(NNPredictor(model), sample_period, settings, duty_limits, name, nominal_load=nominal_load,
                         nominal_input_voltage=nominal_input_voltage)
        self.model, self.smoothing = model, smoothing
        self.solve_times: list[float] = []
        self._mpc = self._build()

    def _build(self):
        import casadi
        import do_mpc

        config, settings = self.model.config, self.settings
        delays, n_extra, horizon = config.delays, len(config.extra_signals), settings.horizon
        network = casadi_network(self.model)
        model = do_mpc.model.Model("discrete", "SX")
        state = model.set_variable("_x", "s", shape=(2 + 3 * (delays - 1), 1))
        duty = model.set_variable("_u", "d")
        bias = model.set_variable("_p", "bias", shape=(2, 1))
        extras = model.set_variable("_p", "extras", shape=(max(n_extra, 1), 1))
        model.set_variable("_p", "target", shape=(2, 1))  # read back as model.p["target"] after the setup
        weight = model.set_variable("_tvp", "weight")
        inputs = [state[0], state[1], duty, state[2:]] + ([extras[:n_extra]] if n_extra else [])
        predicted = network(casadi.vertcat(*inputs)) + bias
        older = [state[0], state[1], duty] + ([state[2:2 + 3 * (delays - 2)]] if delays > 2 else [])
        model.set_rhs("s", casadi.vertcat(predicted, *older) if delays > 1 else predicted)
        model.setup()
        error = model.x["s"][:2] - model.p["target"]  # the model's own symbols, after its setup
        norm = casadi.sqrt(casadi.sumsqr(error) + self.smoothing ** 2)
        weight = model.tvp["weight"]
        mpc = do_mpc.controller.MPC(model)
        mpc.settings.n_horizon = horizon
        mpc.settings.t_step = self.sample_period
        mpc.settings.n_robust = 0
        mpc.settings.store_full_solution = False
        mpc.settings.supress_ipopt_output()
        mpc.set_objective(lterm=weight * norm, mterm=settings.discount ** (horizon - 1) * norm)
        mpc.set_rterm(d=0.0)
        low, high = self.duty_limits
        mpc.bounds["lower", "_u", "d"] = low
        mpc.bounds["upper", "_u", "d"] = high
        weights = np.concatenate([[0.0], settings.discount ** np.arange(horizon - 1)])
        template = mpc.get_tvp_template()

        def tvp(_t):
            for k in range(horizon + 1):
                template["_tvp", k, "weight"] = weights[k] if k < horizon else 0.0
            return template

        mpc.set_tvp_fun(tvp)
        self._p_template = mpc.get_p_template(1)
        mpc.set_p_fun(lambda _t: self._p_template)
        mpc.prepare_nlp()
        start = 0
        for length in settings.blocks:  # move blocking: the duty is held over each block
            for k in range(start + 1, start + length):
                mpc.nlp_cons.append(mpc.opt_x["_u", k, 0] - mpc.opt_x["_u", start, 0])
                mpc.nlp_cons_lb.append(np.zeros((1, 1)))
                mpc.nlp_cons_ub.append(np.zeros((1, 1)))
            start += length
        mpc.create_nlp()
        return mpc

    def reset(self) -> None:
        super().reset()
        if hasattr(self, "_mpc"):
            self._mpc.reset_history()
            self._mpc.opt_x_num.master[:] = 0.0
        self.solve_times = []

    def plan(self, context: PredictionContext, target: np.ndarray, disturbance: np.ndarray, anchor: float,
             fallback: str) -> tuple[np.ndarray, float, np.ndarray, str]:
        config = self.model.config
        history = context.history
        p = self._p_template
        p["_p", 0, "bias"] = disturbance
        signals = {"load_current": context.load_current, "input_voltage": context.input_voltage,
                   "load_conductance": context.load_conductance}
        p["_p", 0, "extras"] = [signals[s] for s in config.extra_signals] or [0.0]
        p["_p", 0, "target"] = target
        s0 = [history[0, 0], history[0, 1]]
        for r in range(1, config.delays):
            s0 += [history[r, 0], history[r, 1], history[r, 2]]
        start = time.perf_counter()
        self._mpc.make_step(np.array(s0)[:, None])
        self.solve_times.append(time.perf_counter() - start)
        low, high = self.duty_limits
        sequence = np.clip(np.array([float(self._mpc.opt_x_num["_u", k, 0]) for k in
                                     range(self.settings.horizon)]), low, high)
        predicted = self.predictor.rollout(context, sequence[None, :], disturbance)[0]
        error = predicted - target
        cost = float(np.sqrt((error * error).sum(axis=1)) @ self._weights)
        return sequence, cost, predicted[0], "do-mpc"

    def describe(self) -> dict:
        return {**super().describe(), "optimizer": "do-mpc (CasADi + IPOPT), smoothed eq. 16, move blocking as "
                                                   "equality constraints", "smoothing_V": self.smoothing}
