"""A bubble's physical constants, declared once: the simulated demo bubble and the Punyo.

A :class:`SensorProfile` holds what the estimator must assume about the hardware and cannot
read from a frame: the ambient pressure (a pressure sensor that reads absolute cannot know its
gauge pressure, and the rest gauge pressure sets the membrane's rest tension, which governs
the force a dent means) and the membrane's Young's modulus, thickness and Poisson ratio.

* ``sim``: the simulator's default bubble (its scene physics reads these constants); the
  estimator's modulus there is the one fitted for the linearised model on the calibration
  seeds, since the simulator's membrane is hyperelastic and the estimator's linear.
* ``punyo``: a real Punyo (Intel D405 inside, pressure in hPa). Its constants are identified
  from the real press in ``../shared/data/punyo-demo-0-press`` by ``bubble-rt calibrate
  --recording`` (the evidence and the command are in docs/punyo-profile.md). Its ambient
  pressure is an *effective* one: the rest tension that reproduces the sensor's force for a
  measured dent, written as the ambient pressure that gives it with the rest pressure read.

Commands pick the profile from the data's layout (:func:`profile_for_layout`): Punyo folders,
ROS 2 bags and a RealSense camera are Punyo hardware, everything else the simulator's.
"""

from __future__ import annotations

from dataclasses import dataclass

#: Standard sea-level atmosphere (Pa): the simulator's ambient pressure.
STANDARD_ATMOSPHERE_PA = 101325.0


@dataclass(frozen=True)
class SensorProfile:
    """Physical constants of one kind of bubble.

    Attributes:
        name: profile name ("sim", "punyo").
        ambient_pa: ambient pressure (Pa) subtracted from absolute pressure readings.
        youngs_modulus: the estimator's membrane Young's modulus (Pa).
        thickness: membrane thickness (m).
        poisson: membrane Poisson ratio (-).
        doc: where the numbers come from.
    """

    name: str
    ambient_pa: float
    youngs_modulus: float
    thickness: float
    poisson: float
    doc: str


SIM = SensorProfile(
    name="sim",
    ambient_pa=STANDARD_ATMOSPHERE_PA,
    youngs_modulus=0.66e6,
    thickness=0.65e-3,
    poisson=0.5,
    doc="the simulator's default bubble; E fitted for the linearised model on the "
    "calibration seeds (E 0.3-1.3 MPa scanned)",
)

PUNYO = SensorProfile(
    name="punyo",
    # `bubble-rt calibrate --recording ../shared/data/punyo-demo-0-press --fit ambient_pa`
    # (88926 Pa, with the rest tension from the cap's force balance): a rest gauge pressure of
    # about 17.7 kPa over the 106.6 kPa read at rest, where a sea-level ambient would give
    # 5.3 kPa and read about half the force. Effective, not a barometer reading:
    # docs/punyo-profile.md.
    ambient_pa=88900.0,
    youngs_modulus=0.66e6,
    thickness=0.65e-3,
    poisson=0.5,
    doc="rest tension (as an effective ambient pressure) identified on the real press of "
    "punyo-demo-0-press; membrane constants the simulator's (docs/punyo-profile.md)",
)

PROFILES: dict[str, SensorProfile] = {p.name: p for p in (SIM, PUNYO)}

#: Data layouts recorded on Punyo hardware (``Recording.layout``, camera sources).
_PUNYO_LAYOUTS = frozenset({"punyo", "rosbag", "realsense"})


def profile_for_layout(layout: str) -> SensorProfile:
    """The profile of data in ``layout`` ("punyo", "rosbag", "realsense" -> PUNYO, else SIM)."""
    return PUNYO if layout in _PUNYO_LAYOUTS else SIM


def profile(name: str) -> SensorProfile:
    """The profile called ``name``; ValueError lists the known ones."""
    try:
        return PROFILES[name]
    except KeyError:
        raise ValueError(f"unknown sensor profile {name!r}; known: {', '.join(PROFILES)}") from None


__all__ = [
    "PROFILES",
    "PUNYO",
    "SIM",
    "STANDARD_ATMOSPHERE_PA",
    "SensorProfile",
    "profile",
    "profile_for_layout",
]
