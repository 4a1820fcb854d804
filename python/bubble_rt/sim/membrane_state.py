"""Settings and state of the simulated membrane (``bubble_rt.sim.physics``): material, gas,
contact and solver settings, one equilibrium (``SimState``), the rest mesh and pose helpers.

Units: metres, newtons, pascals, joules (mesh frame). Re-exported by ``bubble_rt.sim.physics``.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace

import numpy as np
from numpy.typing import NDArray

from bubble_rt.mesh import Mesh, MeshGeometry
from bubble_rt.sensor import SIM_BUBBLE
from bubble_rt.sim.indenters import Indenter

Array = NDArray[np.float64]


#: Node count of the default simulation mesh.
DEFAULT_NODES = 2000
#: Dome height (m) of the stress-free rest shape (``bubble_rt.sensor.SIM_BUBBLE``).
DEFAULT_REST_DOME_HEIGHT = SIM_BUBBLE.rest_dome_height_m
#: Chamber volume (m^3) behind the membrane; calibrated so a ~4.5 N push with the round
#: indenter raises the pressure by about 0.45 kPa, as on the real sensor.
DEFAULT_CHAMBER_VOLUME = 1.45e-3


class SimConvergenceError(RuntimeError):
    """Raised (only with ``NewtonSettings.strict``) when a step fails even after substeps."""


@dataclass(frozen=True)
class MembraneMaterial:
    """Membrane: Young's modulus ``E`` (Pa), thickness ``thickness`` (m); incompressible."""

    E: float = SIM_BUBBLE.youngs_modulus_pa
    thickness: float = SIM_BUBBLE.thickness_m

    def __post_init__(self) -> None:
        if not (self.E > 0 and self.thickness > 0):
            raise ValueError(f"E and thickness must be positive, got {self.E}, {self.thickness}")

    @property
    def mu_t(self) -> float:
        """Shear modulus times thickness (N/m), mu = E / 3."""
        return self.E / 3.0 * self.thickness


@dataclass(frozen=True)
class GasSettings:
    """Enclosed air: operating gauge pressure (Pa), ambient (Pa), chamber volume (m^3)."""

    gauge_pressure_pa: float = SIM_BUBBLE.gauge_pressure_pa
    atmospheric_pa: float = SIM_BUBBLE.ambient_pa
    chamber_volume_m3: float = DEFAULT_CHAMBER_VOLUME
    compressible: bool = True

    def __post_init__(self) -> None:
        if not self.gauge_pressure_pa > 0:
            raise ValueError(f"gauge pressure must be positive, got {self.gauge_pressure_pa}")
        if not self.atmospheric_pa > 0:
            raise ValueError(f"atmospheric pressure must be positive, got {self.atmospheric_pa}")
        if not self.chamber_volume_m3 >= 0:
            raise ValueError(f"chamber volume must be >= 0, got {self.chamber_volume_m3}")


@dataclass(frozen=True)
class ContactSettings:
    """Contact: Coulomb coefficient (None = frictionless), penalty k (N/m^2, energy
    k d^3 / 3 per node), friction smoothing slip ``slip_tolerance`` (m; below it contact sticks
    elastically), up to ``friction_passes`` re-solves refreshing the lagged normal force until
    it changes by less than ``lag_tolerance`` (relative to the largest).

    Surface samples: each triangle also carries ``surface_samples`` fixed material points at
    barycentric positions (the interior points of a regular barycentric grid, so the count
    must be 0, 1, 3, 6, 10, ...; 0 disables them). A sample at depth d inside the indenter has
    the penalty ``(k / surface_samples) e^3 / 3`` on its excess depth ``e = max(d - a, 0)``,
    with the allowance a = ``sample_allowance`` times the inradius of its triangle in the rest
    mesh. Between its nodes a flat triangle dips into a smooth indenter by the chord sag (about
    rc^2 / 2R at the centre, circumradius rc, indenter radius R); the allowance leaves that to
    the nodes, so contact with an indenter the mesh resolves is unchanged, while one sharper
    than the mesh, which would slip between the nodes, is held by the samples (0.5: a quarter
    of an equilateral triangle's circumradius, the sag on a sphere of radius 2 rc). A loaded
    sample has friction like a node (its own lagged normal force, tangent plane and slip);
    its forces act on the triangle's nodes by the barycentric weights.
    """

    friction: float | None = 0.5
    penalty: float = 2.0e8
    slip_tolerance: float = 2.0e-5
    friction_passes: int = 6
    lag_tolerance: float = 2.0e-3
    surface_samples: int = 3
    sample_allowance: float = 0.5

    def __post_init__(self) -> None:
        if self.friction is not None and not self.friction >= 0:
            raise ValueError(f"friction must be >= 0 or None, got {self.friction}")
        if not (self.penalty > 0 and self.slip_tolerance > 0 and self.friction_passes >= 1):
            raise ValueError("penalty, slip_tolerance and friction_passes must be positive")
        barycentric_samples(self.surface_samples)  # validates the count
        if not self.sample_allowance >= 0:
            raise ValueError(f"sample_allowance must be >= 0, got {self.sample_allowance}")


def barycentric_samples(n: int) -> Array:
    """Barycentric weights (n x 3) of the interior points of the smallest regular barycentric
    grid that has n of them (n = 0, 1, 3, 6, 10, ...)."""
    if n == 0:
        return np.zeros((0, 3))
    m = 3
    while (m - 1) * (m - 2) // 2 < n:
        m += 1
    if (m - 1) * (m - 2) // 2 != n:
        raise ValueError(f"surface_samples must be 0, 1, 3, 6, 10, ... (got {n})")
    pts = [(i, j, m - i - j) for i in range(1, m) for j in range(1, m - i)]
    return np.array(pts, dtype=np.float64) / m


@dataclass(frozen=True)
class NewtonSettings:
    """Equilibrium solver: stop when every free node's residual force is below
    ``tolerance_n`` (N); ``max_iterations`` per (sub)step; a failing step is halved up to
    ``max_halvings`` times; inflation in ``inflation_steps`` equal pressure increments;
    Newton steps are capped at ``max_step_m`` per node. ``strict`` raises instead of
    returning a state with ``converged=False``. With ``reuse_factorization`` a Newton system
    is first solved by conjugate gradients preconditioned with the previous factorisation
    (relative tolerance ``cg_tolerance``, at most ``cg_max_iterations``), and factorised anew
    only when that fails."""

    tolerance_n: float = 1.0e-8
    max_iterations: int = 40
    max_halvings: int = 5
    inflation_steps: int = 10
    max_step_m: float = 2.0e-3
    strict: bool = False
    reuse_factorization: bool = True
    cg_tolerance: float = 1.0e-7
    cg_max_iterations: int = 15


@dataclass(frozen=True, eq=False)
class SimState:
    """One equilibrium. Arrays are M x 3 (M simulation nodes) unless noted.

    vertices (m); triangles (T x 3); pressure_pa absolute (Pa); volume_m3 enclosed by the
    membrane and the rim plane; contact_forces (N) the indenter applies on the membrane;
    rim_reactions (N) the base applies on rim nodes (zero elsewhere); pressure_forces (N)
    gauge pressure on the nodes; contact (M,) bool: nodes penetrating the indenter or owning
    a surface sample deeper than its allowance (see ``ContactSettings``; the owner is the node
    with the largest barycentric weight, all tied ones for a centroid); converged; iterations
    (Newton, all substeps and friction passes); residual (N, largest free-node force
    imbalance); substeps used for this step; pose (4 x 4) of this equilibrium or None. A
    step that failed reports the last converged equilibrium (its vertices, forces and pose)
    with ``converged=False``.
    """

    vertices: Array
    triangles: NDArray[np.int32]
    pressure_pa: float
    volume_m3: float
    contact_forces: Array
    rim_reactions: Array
    pressure_forces: Array
    contact: NDArray[np.bool_]
    converged: bool
    iterations: int
    residual: float
    substeps: int
    pose: Array | None = None
    gauge_pressure_pa: float = 0.0
    elastic_energy_j: float = 0.0
    notes: tuple[str, ...] = field(default_factory=tuple)

    @property
    def net_contact_force(self) -> Array:
        """Total force (3,) N the indenter applies on the membrane (all nodes; an indenter
        touching the clamped rim also loads rim nodes, see ``contact_forces``)."""
        return self.contact_forces.sum(axis=0)


def default_rest_mesh(
    n_nodes: int = DEFAULT_NODES,
    geometry: MeshGeometry | None = None,
    rest_dome_height_m: float = DEFAULT_REST_DOME_HEIGHT,
) -> Mesh:
    """The stress-free rest shape: the bubble footprint with a ``rest_dome_height_m`` dome
    (the default's, inflated to 5 kPa, gives the 30 mm operating dome)."""
    g = geometry or MeshGeometry()
    return Mesh.generate(n_nodes, replace(g, dome_height=rest_dome_height_m))


def skew_free_pose(pose: Array) -> Array:
    T = np.asarray(pose, dtype=np.float64)
    if T.shape != (4, 4) or not np.all(np.isfinite(T)):
        raise ValueError(f"pose must be a finite 4 x 4 transform, got shape {T.shape}")
    return T


def interpolate_pose(a: Array, b: Array, s: float) -> Array:
    """Pose a fraction s of the way from a to b (linear translation, slerp rotation)."""
    from scipy.spatial.transform import Rotation, Slerp

    out = np.eye(4)
    rots = Rotation.from_matrix(np.stack([a[:3, :3], b[:3, :3]]))
    out[:3, :3] = Slerp([0.0, 1.0], rots)([s]).as_matrix()[0]
    out[:3, 3] = (1 - s) * a[:3, 3] + s * b[:3, 3]
    return out


@dataclass
class Problem:
    """Everything fixed during one Newton solve."""

    indenter: Indenter | None
    pose: Array | None
    gauge: float  # constant gauge pressure (Pa) when gas_C is None
    gas_C: float | None  # P0 (V0 + Vc) when the gas is sealed
    lam: Array | None = None  # lagged normal force per contact point (P,), friction only
    tangent: Array | None = None  # P x 3 x 3 lagged tangent projectors
    anchor: Array | None = None  # M x 3 node slip origins carried with the indenter


def pose_of(prob: Problem) -> Array:
    if prob.pose is None:
        raise ValueError("an indenter needs a pose")
    return prob.pose
