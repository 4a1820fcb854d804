"""Names the estimation path is configured by, in a module that imports nothing, so that the
config loader, the command line (``--help``) and the simulator can use them cheaply."""

from __future__ import annotations

#: Optical-flow methods of the deformation tracker (``FlowSettings.method``).
IMAGE_FLOW_METHODS: tuple[str, ...] = (
    "dis_ultrafast",
    "dis_fast",
    "dis_medium",
    "farneback",
    "farneback_heavy",
)
#: Ground-truth displacements instead of images: the simulator provides this tracker.
ORACLE_FLOW_METHOD = "oracle"
#: Every flow method a config may name.
FLOW_METHODS: tuple[str, ...] = IMAGE_FLOW_METHODS + (ORACLE_FLOW_METHOD,)
#: The default: DIS ultrafast at its preset's pyramid level 2, then refined at each node by
#: Lucas-Kanade (FlowSettings.refine_window_px; docs/evaluation.md, "The flow refined at the
#: nodes").
DEFAULT_FLOW_METHOD = "dis_ultrafast"
#: Window (pixels) of that refinement; 0 turns it off.
DEFAULT_REFINE_WINDOW_PX = 15


def refine_window_problem(window: int) -> str | None:
    """Why ``window`` is not a refinement window (odd, at least 5 px, or 0: none), or None."""
    if window == 0 or (window >= 5 and window % 2 == 1):
        return None
    return f"must be 0 (none) or odd and >= 5 pixels, got {window}"
