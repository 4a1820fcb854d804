"""Simulation truth beside each published frame (ForceFrame.sim_truth).

A frame from the simulator carries its scene's exact state (``Frame.truth``, a
:class:`bubble_rt.sim.truth.GroundTruth`); a real sensor's or a replayed recording's frames
carry none, and their ForceFrames get no ``sim_truth``. The truth is duck-typed here (the
daemon does not import the simulator): ``net_force`` (3,) N and ``contact_mask(mesh)``, the
true contact on the published mesh's nodes.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from bubble_rt.io import protocol


def attach_sim_truth(msg: Any, frame: Any, mesh: Any) -> bool:
    """Set ``msg.sim_truth`` from ``frame.truth`` on ``mesh``'s nodes; False (nothing set)
    when the frame has no truth, the simulator flags it as unreliable (not converged) or its
    contact on ``mesh`` is not known yet (``contact_mask`` returned None)."""
    truth = getattr(frame, "truth", None)
    if truth is None or getattr(truth, "net_force", None) is None:
        return False
    if not getattr(truth, "converged", True):
        return False
    mask = truth.contact_mask(mesh)
    if mask is None:  # not derived yet (the sim source derives it in its own process)
        return False
    contact = np.asarray(mask, dtype=bool)
    protocol.set_sim_truth(msg, np.asarray(truth.net_force, dtype=np.float64), contact)
    return True
