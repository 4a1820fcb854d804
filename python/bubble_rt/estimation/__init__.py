"""The real-time estimation path: deformation (flow, lifting), mesh fitting, the membrane model,
the group-lasso solver, the force estimator, the frictionless baseline and the pipeline that
wires them. The only Python that touches the estimator's C++ bindings (``bubble_rt._core``)."""
