"""Where the Punyo sensor's camera sits: the camera -> mesh pose of TRI's public recordings,
shared by every recording layout that holds Punyo frames (the .npy folders and ROS 2 bags)."""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

#: The public implementation's mesh frame is the camera frame rotated 25 degrees about the
#: camera's y axis with the rim plane at z = 0.054 m; the footprint centre sits at x = 0.04025
#: m there (its 390-node reference mesh spans x -0.017..0.0975, y -0.04..0.04).
PUNYO_TILT_DEG = 25.0
PUNYO_RIM_Z = 0.054
PUNYO_CENTRE_X = 0.04025


def punyo_pose(
    tilt_deg: float = PUNYO_TILT_DEG, rim_z: float = PUNYO_RIM_Z, centre_x: float = PUNYO_CENTRE_X
) -> NDArray[np.float64]:
    """Camera -> mesh transform (4 x 4) for the Punyo sensor of the public recordings.

    p_mesh = R_y(tilt) p_cam - (centre_x, 0, rim_z): the rim in z = 0, footprint centred.
    """
    a = np.radians(tilt_deg)
    R = np.array([[np.cos(a), 0.0, np.sin(a)], [0.0, 1.0, 0.0], [-np.sin(a), 0.0, np.cos(a)]])
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = -np.array([centre_x, 0.0, rim_z])
    return T
