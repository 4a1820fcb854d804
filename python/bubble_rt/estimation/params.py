"""The estimator's parameters, each declared once: key, default, range, unit, meaning, and the
``EstimatorConfig`` field it sets.

Everything else derives from this table: ``EstimatorConfig``'s defaults and
``DEFAULT_MATERIAL`` (:mod:`bubble_rt.estimation.estimator`), its ``CONFIG_KEYS``, the
``[estimator]`` keys of the daemon configuration with their ranges and docs
(:mod:`bubble_rt.config`, hence ``config dump`` and the generated configuration page), the
ranges ``set_params`` checks, and the FEM kind's live parameters
(:mod:`bubble_rt.estimation.registry`). The wire's ``Params`` message
(``proto/bubble_rt/v1/bubble_rt.proto``) lists the live ones; a test keeps the two equal.
"""

from __future__ import annotations

from dataclasses import dataclass

from bubble_rt._validate import ParamRange
from bubble_rt.sensor import SIM

__all__ = ["EstimatorParam", "ESTIMATOR_PARAMS", "LIVE_PARAMS", "FLOW_SCALE"]


@dataclass(frozen=True)
class EstimatorParam:
    """One estimator parameter.

    Attributes:
        key: the ``[estimator]`` key (also the ``set_params`` field when ``live``).
        default: the estimator's default, in ``range.unit``.
        doc: what it means (one line; shown by ``config dump`` and the docs).
        range: accepted values.
        field: the ``EstimatorConfig`` field it sets ("material" for the membrane's).
        material: the ``Material`` field when ``field`` is "material", else None.
        live: ``set_params`` may change it while running.
        config_default: the configuration file's default when it differs from ``default``
            (``ambient_pa``: 0 there means "the sensor profile's").
    """

    key: str
    default: float
    doc: str
    range: ParamRange
    field: str
    material: str | None = None
    live: bool = False
    config_default: float | None = None

    @property
    def file_default(self) -> float:
        """The default a configuration file starts from."""
        return self.default if self.config_default is None else self.config_default


ESTIMATOR_PARAMS: dict[str, EstimatorParam] = {
    p.key: p
    for p in (
        EstimatorParam(
            "k_f", 0.05, "force sparsity weight", ParamRange(1e-4, 1e3, "1/N"), "k_f", live=True
        ),
        EstimatorParam(
            "k_u",
            537592.0,
            "displacement fit weight",
            ParamRange(1e2, 1e10, "1/m^2"),
            "k_u",
            live=True,
        ),
        EstimatorParam(
            "youngs_modulus",
            SIM.youngs_modulus,
            "membrane Young's modulus E",
            ParamRange(1e4, 1e8, "Pa"),
            "material",
            "E",
            live=True,
        ),
        EstimatorParam(
            "poisson", SIM.poisson, "membrane Poisson ratio", ParamRange(0.0, 0.5), "material", "nu"
        ),
        EstimatorParam(
            "thickness",
            SIM.thickness,
            "membrane thickness",
            ParamRange(1e-5, 1e-2, "m"),
            "material",
            "thickness",
        ),
        EstimatorParam(
            "k_const",
            2000.0,
            "contact threshold: constant term",
            ParamRange(0.0, 1e6, "Pa"),
            "k_const",
            live=True,
        ),
        EstimatorParam(
            "k_linear",
            2.0,
            "contact threshold: factor on the mean pressure",
            ParamRange(0.0, 1e3),
            "k_linear",
            live=True,
        ),
        EstimatorParam(
            "support_tol",
            0.2,
            "support rule: a node carries force when its lasso multiplier is within this "
            "fraction of its bound (the multiplier field does not depend on the node count)",
            ParamRange(0.0, 0.9),
            "support_tol",
        ),
        EstimatorParam(
            "peak_radius_m",
            3e-3,
            "contact rule: k_peak compares pressures averaged over a disc of this radius (a "
            "physical length, so the rule does not depend on the node count)",
            ParamRange(0.0, 0.02, "m"),
            "peak_radius_m",
        ),
        EstimatorParam(
            "nonlinear_iterations",
            2,
            "reported forces: modified-Newton steps of the membrane with its geometric "
            "nonlinearity (0: the linear model's forces; about 1 ms each at 390 nodes)",
            ParamRange(0, 10, integer=True),
            "nonlinear_iterations",
        ),
        EstimatorParam(
            "ambient_pa",
            SIM.ambient_pa,
            "ambient pressure, subtracted from absolute pressure readings; it sets the rest "
            "tension (0: the sensor profile's)",
            ParamRange(0.0, 120e3, "Pa"),
            "ambient_pa",
            config_default=0.0,
        ),
    )
}

#: The parameters ``set_params`` may change while running, in declaration order.
LIVE_PARAMS: tuple[str, ...] = tuple(k for k, p in ESTIMATOR_PARAMS.items() if p.live)

#: Image scale the optical flow runs at (``FlowSettings.scale``, ``[flow] scale``): below 0.05
#: a 640 x 480 image is smaller than DIS's patches.
FLOW_SCALE = ParamRange(0.05, 1.0)
