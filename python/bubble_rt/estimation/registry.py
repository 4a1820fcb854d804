"""Estimator kinds, registered in one place.

A kind says how to build its estimator and how the pipeline drives it:

* ``tracked``: the estimator works on node displacements (``estimate(U, dp)``), so the
  pipeline's first stage tracks the deformation (flow + lifting); otherwise the estimator
  reads the frame itself (``process(frame)``) and the first stage has nothing to do;
* ``uses_reference``: the estimator cannot be built without the camera and the reference
  capture (the FEM estimator takes the reference's rest pressure when there is one); a tare
  rebuilds every kind's estimator;
* ``params``: the ``[estimator]`` keys it can change while running (``set_params``).

Builders import their estimator when called, so this module stays cheap to import.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

from bubble_rt.estimation.params import LIVE_PARAMS

#: (mesh, config: EstimatorConfig, camera, reference) -> estimator
Builder = Callable[[Any, Any, Any, Any], Any]


@dataclass(frozen=True)
class EstimatorKind:
    """One registered estimator kind (see the module docstring)."""

    name: str
    build: Builder
    params: tuple[str, ...]
    tracked: bool = True
    uses_reference: bool = False
    description: str = ""


_KINDS: dict[str, EstimatorKind] = {}


def register_estimator(kind: EstimatorKind) -> EstimatorKind:
    """Add (or replace) an estimator kind; returns it."""
    _KINDS[kind.name] = kind
    return kind


def estimator_kinds() -> tuple[str, ...]:
    """Names of the registered kinds, in registration order."""
    return tuple(_KINDS)


def estimator_kind(name: str) -> EstimatorKind:
    """The kind registered as ``name``; ValueError names the choices."""
    try:
        return _KINDS[name]
    except KeyError:
        choices = " or ".join(repr(k) for k in _KINDS)
        raise ValueError(f"unknown estimator kind {name!r}; choose {choices}") from None


def make_estimator(
    kind: str, mesh: Any, config: Any = None, camera: Any = None, reference: Any = None
) -> Any:
    """An estimator by kind name (``camera`` and ``reference`` for kinds that use them)."""
    k = estimator_kind(kind)
    if config is None:
        from bubble_rt.estimation.estimator import EstimatorConfig

        config = EstimatorConfig()
    if k.uses_reference and (camera is None or reference is None):
        raise ValueError(f"estimator kind {kind!r} needs the camera and the reference")
    return k.build(mesh, config, camera, reference)


def _fem(mesh: Any, config: Any, camera: Any, reference: Any) -> Any:
    from bubble_rt.estimation.estimator import ForceEstimator

    return ForceEstimator(mesh, config, reference)


def _frictionless(mesh: Any, config: Any, camera: Any, reference: Any) -> Any:
    from bubble_rt.estimation.baseline import FrictionlessEstimator

    return FrictionlessEstimator(mesh, camera, reference, config)


register_estimator(
    EstimatorKind(
        "fem",
        _fem,
        params=LIVE_PARAMS,
        description="FEM membrane + group-lasso ADMM (the product)",
    )
)
register_estimator(
    EstimatorKind(
        "frictionless",
        _frictionless,
        params=("k_const", "k_linear"),
        tracked=False,
        uses_reference=True,
        description="Kuppuswamy et al.'s frictionless baseline on depth images (OSQP)",
    )
)
