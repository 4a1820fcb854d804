"""Triangle meshes of the inflated membrane.

Frame ("sensor frame", metres): the clamped rim lies in the plane z = 0 around the origin, the
dome rises towards +z, x runs along the footprint's long axis. Triangles are oriented so that
their normals point outward, away from the camera that sits below the rim looking along +z.

Presets "coarse", "medium" and "fine" have exactly 227, 390 and 749 nodes (the paper's meshes)
and are generated deterministically: a centroidal Voronoi (Lloyd) distribution of nodes on the
domed surface, a Delaunay triangulation of the footprint, and tangential smoothing in 3D.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import scipy.sparse as sp
from numpy.typing import NDArray
from scipy.spatial import Delaunay, cKDTree

from bubble_rt.sensor import SIM_BUBBLE

PRESET_NODES: dict[str, int] = {"coarse": 227, "medium": 390, "fine": 749}
#: Mesh preset names, coarsest first (the one list config, daemon, eval and commands use).
PRESETS: tuple[str, ...] = tuple(PRESET_NODES)

#: Triangles whose smallest angle is below this (degrees) are rejected as slivers.
MIN_ANGLE_DEG = 5.0


class MeshError(ValueError):
    """A mesh failed validation; the message names the offending element."""


@dataclass(frozen=True)
class MeshGeometry:
    """Shape of a generated bubble mesh (metres).

    The footprint is an ellipse with semi-axes ``semi_axis_x`` x ``semi_axis_y`` centred at
    the origin; the dome is the smooth cap ``z = dome_height * (1 - r^2)`` with
    ``r^2 = (x / semi_axis_x)^2 + (y / semi_axis_y)^2``. Defaults match the Punyo bubble:
    a 114.5 mm x 80 mm footprint, dome top about 30 mm above the rim.
    """

    semi_axis_x: float = SIM_BUBBLE.semi_axis_x_m
    semi_axis_y: float = SIM_BUBBLE.semi_axis_y_m
    dome_height: float = SIM_BUBBLE.dome_height_m

    def height(self, x: NDArray[np.float64], y: NDArray[np.float64]) -> NDArray[np.float64]:
        """Dome height z (m) over footprint points x, y (m); zero outside the rim."""
        r2 = (x / self.semi_axis_x) ** 2 + (y / self.semi_axis_y) ** 2
        return self.dome_height * np.clip(1.0 - r2, 0.0, None)

    def slope(
        self, x: NDArray[np.float64], y: NDArray[np.float64]
    ) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """Partial derivatives (dz/dx, dz/dy) of the dome inside the rim."""
        return (
            -2.0 * self.dome_height * x / self.semi_axis_x**2,
            -2.0 * self.dome_height * y / self.semi_axis_y**2,
        )


def _readonly(a: NDArray) -> NDArray:
    a = np.ascontiguousarray(a)
    a.setflags(write=False)
    return a


@dataclass(frozen=True, eq=False)
class Mesh:
    """A membrane mesh.

    Attributes:
        vertices: N x 3 float64, metres.
        triangles: T x 3 int32, counter-clockwise seen from outside (outward normals).
        boundary: sorted int32 indices of the clamped rim nodes.
    """

    vertices: NDArray[np.float64]
    triangles: NDArray[np.int32]
    boundary: NDArray[np.int32] = field(default=None)  # type: ignore[arg-type]

    def __post_init__(self) -> None:
        v = np.asarray(self.vertices, dtype=np.float64)
        t = np.asarray(self.triangles)
        if v.ndim != 2 or v.shape[1] != 3:
            raise MeshError(f"vertices must be N x 3, got shape {v.shape}")
        if t.ndim != 2 or t.shape[1] != 3:
            raise MeshError(f"triangles must be T x 3, got shape {t.shape}")
        if not np.issubdtype(t.dtype, np.integer):
            raise MeshError(f"triangles must hold integer indices, got dtype {t.dtype}")
        if not np.all(np.isfinite(v)):
            bad = int(np.flatnonzero(~np.isfinite(v).all(axis=1))[0])
            raise MeshError(f"vertex {bad} has a non-finite coordinate")
        b = boundary_nodes(t, len(v)) if self.boundary is None else np.asarray(self.boundary)
        object.__setattr__(self, "vertices", _readonly(v))
        object.__setattr__(self, "triangles", _readonly(t.astype(np.int32)))
        object.__setattr__(self, "boundary", _readonly(np.unique(b).astype(np.int32)))

    # ------------------------------------------------------------------ constructors
    @classmethod
    def preset(cls, name: str, geometry: MeshGeometry | None = None) -> Mesh:
        """One of the paper's meshes: "coarse" (227 nodes), "medium" (390), "fine" (749)."""
        if name not in PRESET_NODES:
            raise ValueError(f"unknown mesh preset {name!r}; choose one of {sorted(PRESET_NODES)}")
        return cls.generate(PRESET_NODES[name], geometry or MeshGeometry())

    @classmethod
    def generate(cls, n_nodes: int, geometry: MeshGeometry | None = None) -> Mesh:
        """A bubble mesh with exactly ``n_nodes`` nodes (deterministic, cached)."""
        if n_nodes < 10:
            raise ValueError(f"n_nodes must be at least 10, got {n_nodes}")
        return _generate(int(n_nodes), geometry or MeshGeometry())

    @classmethod
    def from_spec(cls, spec: str | int, geometry: MeshGeometry | None = None) -> Mesh:
        """A mesh named the way configs and command lines name it: a preset ("coarse",
        "medium", "fine"), a node count ("500" or 500: ``generate``) or a mesh file path."""
        name = str(spec)
        if name in PRESET_NODES:
            return cls.preset(name, geometry)
        if name.isdigit():
            return cls.generate(int(name), geometry)
        return cls.load(name)

    @classmethod
    def load(cls, path: str | Path, min_angle_deg: float = MIN_ANGLE_DEG) -> Mesh:
        """Read a mesh with meshio (.vtk, .obj, .ply, .msh, ...) and validate it.

        Only triangle cells are used. Raises MeshError naming the element at fault.
        """
        import meshio

        from bubble_rt._validate import regular_file

        path = Path(path)
        if not path.exists():
            raise FileNotFoundError(f"mesh file not found: {path}")
        regular_file("mesh", path)  # a FIFO or device would block meshio or never end
        if path.stat().st_size == 0:
            raise MeshError(f"cannot read mesh {path}: the file is empty (0 bytes)")
        try:
            m = meshio.read(path)
        # meshio raises many types for malformed files, and SystemExit when no reader fits.
        except (Exception, SystemExit) as exc:
            why = (
                f"meshio has no reader that reads it (as {path.suffix or 'any format'})"
                if isinstance(exc, SystemExit)
                else f"{type(exc).__name__}: {exc}"
            )
            raise MeshError(f"cannot read mesh {path}: {why}") from None
        tris = [c.data for c in m.cells if c.type == "triangle"]
        if not tris:
            raise MeshError(f"{path}: no triangle cells")
        return cls.validated(np.asarray(m.points)[:, :3], np.concatenate(tris), min_angle_deg)

    @classmethod
    def validated(
        cls,
        vertices: NDArray[np.float64],
        triangles: NDArray[np.integer],
        min_angle_deg: float = MIN_ANGLE_DEG,
    ) -> Mesh:
        """Build a mesh from raw arrays after checking it is a usable membrane.

        Checks: indices in range, no degenerate or sliver triangle (smallest angle below
        ``min_angle_deg``), no edge shared by more than two triangles, no unreferenced vertex,
        consistent orientation, a non-empty boundary. Orientation is made outward: if the
        area-weighted normal points away from the side the dome rises to, all triangles flip.
        """
        v = np.asarray(vertices, dtype=np.float64)
        t = np.asarray(triangles)
        mesh = cls(v, t.astype(np.int32), boundary=np.zeros(0, np.int32))
        n = len(mesh.vertices)
        t = mesh.triangles
        if t.size and (t.min() < 0 or t.max() >= n):
            bad = int(np.flatnonzero((t < 0).any(axis=1) | (t >= n).any(axis=1))[0])
            raise MeshError(
                f"triangle {bad} indexes a vertex outside 0..{n - 1}: {t[bad].tolist()}"
            )
        repeated = (t[:, 0] == t[:, 1]) | (t[:, 1] == t[:, 2]) | (t[:, 0] == t[:, 2])
        if repeated.any():
            bad = int(np.flatnonzero(repeated)[0])
            raise MeshError(f"triangle {bad} is degenerate (repeated vertex): {t[bad].tolist()}")
        angles = triangle_angles_deg(v, t)
        worst = angles.min(axis=1)
        if (worst < min_angle_deg).any():
            bad = int(np.argmin(worst))
            raise MeshError(
                f"triangle {bad} {t[bad].tolist()} is a sliver: smallest angle "
                f"{worst[bad]:.3g} deg < {min_angle_deg} deg"
            )
        used = np.zeros(n, bool)
        used[t.ravel()] = True
        if not used.all():
            bad = int(np.flatnonzero(~used)[0])
            raise MeshError(f"vertex {bad} is not referenced by any triangle")
        edges, counts, directed = _edge_table(t)
        if (counts > 2).any():
            e = edges[np.flatnonzero(counts > 2)[0]]
            raise MeshError(
                f"edge ({e[0]}, {e[1]}) is non-manifold: shared by more than 2 triangles"
            )
        # In a consistently oriented mesh every interior edge is traversed once each way.
        interior = counts == 2
        if (directed[interior] != 0).any():
            e = edges[np.flatnonzero(interior & (directed != 0))[0]]
            raise MeshError(
                f"inconsistent orientation: edge ({e[0]}, {e[1]}) is traversed the same way by both "
                "of its triangles"
            )
        if not (counts == 1).any():
            raise MeshError("mesh has no boundary (a closed surface cannot be clamped)")
        boundary = np.unique(edges[counts == 1].ravel())
        if _outward_sign(v, t, boundary) < 0:
            t = t[:, ::-1]
        return cls(v, t, boundary)

    # ------------------------------------------------------------------ queries
    @property
    def n_nodes(self) -> int:
        return int(self.vertices.shape[0])

    @property
    def n_triangles(self) -> int:
        return int(self.triangles.shape[0])

    @property
    def interior(self) -> NDArray[np.bool_]:
        """N bool: True for nodes that are not on the clamped rim."""
        mask = np.ones(self.n_nodes, bool)
        mask[self.boundary] = False
        return mask

    def lumped_areas(self) -> NDArray[np.float64]:
        """(N,) lumped node areas (m^2): see :func:`lumped_areas`."""
        return lumped_areas(self.vertices, self.triangles)

    def vertex_normals(self) -> NDArray[np.float64]:
        """N x 3 area-weighted outward unit normals: see :func:`vertex_normals`."""
        return vertex_normals(self.vertices, self.triangles)

    def adjacency(self) -> sp.csr_matrix:
        """N x N symmetric 0/1 node adjacency over the mesh edges: see :func:`edge_adjacency`."""
        return edge_adjacency(self.triangles, self.n_nodes)

    def min_angle_deg(self) -> float:
        """Smallest triangle angle in the mesh (degrees): the quality figure reported."""
        return float(triangle_angles_deg(self.vertices, self.triangles).min())

    def edge_lengths(self) -> NDArray[np.float64]:
        """Lengths (m) of the unique edges."""
        edges, _, _ = _edge_table(self.triangles)
        return np.linalg.norm(self.vertices[edges[:, 0]] - self.vertices[edges[:, 1]], axis=1)

    def save(self, path: str | Path) -> None:
        """Write the mesh with meshio (format from the suffix); boundary is re-derived on load."""
        import meshio

        meshio.write(Path(path), meshio.Mesh(self.vertices, [("triangle", self.triangles)]))

    def transformed(self, transform: NDArray[np.float64]) -> Mesh:
        """The same mesh with vertices mapped by a 4 x 4 rigid transform."""
        T = np.asarray(transform, dtype=np.float64)
        return Mesh(self.vertices @ T[:3, :3].T + T[:3, 3], self.triangles, self.boundary)

    def with_vertices(self, vertices: NDArray[np.float64]) -> Mesh:
        """Same connectivity and rim, new node positions (N x 3, metres)."""
        return Mesh(vertices, self.triangles, self.boundary)

    def __repr__(self) -> str:
        return f"Mesh(nodes={self.n_nodes}, triangles={self.n_triangles}, rim={len(self.boundary)})"


# ---------------------------------------------------------------------- helpers
def lumped_areas(vertices: NDArray[np.float64], triangles: NDArray[np.integer]) -> NDArray:
    """(N,) lumped node areas, m^2: one third of every incident triangle's area.

    The Python copy of what the C++ membrane model computes (``MembraneModel.areas``), for the
    code that must not build a model (daemon patches, evaluation metrics).
    """
    v = np.asarray(vertices, dtype=np.float64)
    t = np.asarray(triangles)
    cross = np.cross(v[t[:, 1]] - v[t[:, 0]], v[t[:, 2]] - v[t[:, 0]])
    area = 0.5 * np.linalg.norm(cross, axis=1)
    a = np.zeros(len(v))
    for k in range(3):
        np.add.at(a, t[:, k], area / 3.0)
    return a


def vertex_normals(vertices: NDArray[np.float64], triangles: NDArray[np.integer]) -> NDArray:
    """Area-weighted outward unit normals (N x 3), as the C++ model's ``normals``."""
    v = np.asarray(vertices, dtype=np.float64)
    t = np.asarray(triangles)
    cross = np.cross(v[t[:, 1]] - v[t[:, 0]], v[t[:, 2]] - v[t[:, 0]])
    n = np.zeros_like(v)
    for k in range(3):
        np.add.at(n, t[:, k], cross)
    norm = np.linalg.norm(n, axis=1, keepdims=True)
    return n / np.where(norm > 0, norm, 1.0)


def edge_adjacency(triangles: NDArray[np.integer], n_nodes: int) -> sp.csr_matrix:
    """N x N symmetric node adjacency (float 0/1, no diagonal) over the triangles' edges."""
    t = np.asarray(triangles)
    i = np.concatenate([t[:, 0], t[:, 1], t[:, 2], t[:, 1], t[:, 2], t[:, 0]])
    j = np.concatenate([t[:, 1], t[:, 2], t[:, 0], t[:, 0], t[:, 1], t[:, 2]])
    A = sp.coo_matrix((np.ones(len(i)), (i, j)), shape=(n_nodes, n_nodes)).tocsr()
    A.data[:] = 1.0
    return A


def triangle_angles_deg(vertices: NDArray[np.float64], triangles: NDArray[np.integer]) -> NDArray:
    """T x 3 interior angles (degrees) of each triangle, at its three corners."""
    p = vertices[triangles]
    out = np.empty((len(triangles), 3))
    for k in range(3):
        a = p[:, (k + 1) % 3] - p[:, k]
        b = p[:, (k + 2) % 3] - p[:, k]
        cross = np.linalg.norm(np.cross(a, b), axis=1)
        out[:, k] = np.degrees(np.arctan2(cross, np.einsum("ij,ij->i", a, b)))
    return out


def _edge_table(t: NDArray[np.integer]) -> tuple[NDArray, NDArray, NDArray]:
    """Unique undirected edges (E x 2), how many triangles use each, net direction count."""
    d = np.concatenate([t[:, [0, 1]], t[:, [1, 2]], t[:, [2, 0]]])
    sign = np.where(d[:, 0] < d[:, 1], 1, -1)
    und = np.sort(d, axis=1)
    edges, inv, counts = np.unique(und, axis=0, return_inverse=True, return_counts=True)
    directed = np.zeros(len(edges), np.int64)
    np.add.at(directed, inv.ravel(), sign)
    return edges, counts, directed


def boundary_nodes(triangles: NDArray[np.integer], n_nodes: int) -> NDArray[np.int32]:
    """Indices of nodes on edges used by exactly one triangle."""
    if len(triangles) == 0:
        return np.zeros(0, np.int32)
    edges, counts, _ = _edge_table(np.asarray(triangles))
    return np.unique(edges[counts == 1].ravel()).astype(np.int32)


def _outward_sign(v: NDArray, t: NDArray, boundary: NDArray) -> float:
    """+1 when triangle normals point to the side the dome rises to, -1 otherwise."""
    rim = v[boundary]
    c = rim.mean(axis=0)
    _, _, vt = np.linalg.svd(rim - c)
    plane_n = vt[2]
    rise = (v - c) @ plane_n
    side = np.sign(rise[np.argmax(np.abs(rise))]) if np.abs(rise).max() > 0 else 1.0
    p = v[t]
    area_n = np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0]).sum(axis=0)
    s = float(np.sign(area_n @ plane_n * side))
    return s if s != 0 else 1.0


def _ellipse_perimeter(a: float, b: float) -> float:
    h = ((a - b) / (a + b)) ** 2
    return float(np.pi * (a + b) * (1 + 3 * h / (10 + np.sqrt(4 - 3 * h))))  # Ramanujan II


@functools.lru_cache(maxsize=16)
def _generate(n_nodes: int, g: MeshGeometry) -> Mesh:
    """The generated mesh, from the on-disk cache when this module's code, the numpy and scipy
    versions (qhull's triangulation), ``n_nodes`` and ``g`` are unchanged (generating takes
    about a second, the largest part of the daemon's start-up), else generated and stored."""
    from bubble_rt import _diskcache

    key = _diskcache.source_key(
        "mesh", n_nodes, g, np.__version__, _scipy_version(), files=(Path(__file__),)
    )
    path = _diskcache.cache_dir() / f"mesh-{key}.npz"
    cached = _diskcache.load(path)
    if cached is not None:
        try:
            return Mesh(cached["vertices"], cached["triangles"], cached["boundary"])
        except (KeyError, MeshError):
            pass  # a damaged entry: generate again (and overwrite it)
    mesh = _generate_now(n_nodes, g)
    try:
        _diskcache.store(
            path,
            {"vertices": mesh.vertices, "triangles": mesh.triangles, "boundary": mesh.boundary},
        )
    except OSError:
        pass  # a read-only home: the mesh is still right, only not cached
    return mesh


def _scipy_version() -> str:
    import scipy

    return str(scipy.__version__)


def _generate_now(n_nodes: int, g: MeshGeometry) -> Mesh:
    a, b = g.semi_axis_x, g.semi_axis_y
    # Area-element weights make node density uniform on the dome, not on the footprint.
    step = min(a, b) / 150.0
    xs = np.arange(-a, a + step, step)
    ys = np.arange(-b, b + step, step)
    X, Y = np.meshgrid(xs, ys)
    inside = (X / a) ** 2 + (Y / b) ** 2 < 1.0
    S = np.column_stack([X[inside], Y[inside]])
    zx, zy = g.slope(S[:, 0], S[:, 1])
    w = np.sqrt(1.0 + zx**2 + zy**2)
    area3d = float(w.sum() * step * step)
    spacing = np.sqrt(2.0 * area3d / (np.sqrt(3.0) * n_nodes))
    n_rim = max(8, int(round(_ellipse_perimeter(a, b) / spacing)))
    n_inner = n_nodes - n_rim
    if n_inner < 1:
        raise ValueError(f"{n_nodes} nodes are too few for this geometry")
    # Rim nodes equally spaced in arc length.
    th = np.linspace(0, 2 * np.pi, 4000, endpoint=False)
    ring = np.column_stack([a * np.cos(th), b * np.sin(th)])
    seg = np.linalg.norm(np.roll(ring, -1, axis=0) - ring, axis=1)
    s = np.concatenate([[0], np.cumsum(seg)])
    targets = np.arange(n_rim) * s[-1] / n_rim
    th_rim = np.interp(targets, s, np.concatenate([th, [2 * np.pi]]))
    rim = np.column_stack([a * np.cos(th_rim), b * np.sin(th_rim)])
    # Interior generators: a sunflower spiral (deterministic), then Lloyd iterations.
    k = np.arange(n_inner) + 0.5
    r = np.sqrt(k / n_inner) * 0.92
    phi = k * np.pi * (3.0 - np.sqrt(5.0))
    inner = np.column_stack([a * r * np.cos(phi), b * r * np.sin(phi)])
    for _ in range(40):
        gens = np.vstack([rim, inner])
        _, owner = cKDTree(gens).query(S)
        sel = owner >= n_rim
        o = owner[sel] - n_rim
        mass = np.bincount(o, weights=w[sel], minlength=n_inner)
        cx = np.bincount(o, weights=w[sel] * S[sel, 0], minlength=n_inner)
        cy = np.bincount(o, weights=w[sel] * S[sel, 1], minlength=n_inner)
        ok = mass > 0
        inner[ok] = np.column_stack([cx[ok] / mass[ok], cy[ok] / mass[ok]])
    pts2 = np.vstack([rim, inner])
    tri = Delaunay(pts2).simplices.astype(np.int64)
    # Counter-clockwise in the footprint means normals toward +z (outward).
    p = pts2[tri]
    ccw = (p[:, 1, 0] - p[:, 0, 0]) * (p[:, 2, 1] - p[:, 0, 1]) - (p[:, 1, 1] - p[:, 0, 1]) * (
        p[:, 2, 0] - p[:, 0, 0]
    )
    tri[ccw < 0] = tri[ccw < 0][:, ::-1]
    tri = tri[np.abs(ccw) > 1e-14]
    verts = np.column_stack([pts2, g.height(pts2[:, 0], pts2[:, 1])])
    verts = _smooth_on_dome(verts, tri, n_rim, g)
    return Mesh(verts, tri.astype(np.int32), np.arange(n_rim, dtype=np.int32))


def _smooth_on_dome(v: NDArray, tri: NDArray, n_fixed: int, g: MeshGeometry) -> NDArray:
    """Tangential Laplacian smoothing in 3D, re-projected onto the dome; evens out edges that
    the footprint triangulation stretched where the dome is steep."""
    A = edge_adjacency(tri, len(v))
    deg = np.asarray(A.sum(axis=1)).ravel()
    a, b = g.semi_axis_x, g.semi_axis_y
    for _ in range(30):
        avg = (A @ v) / deg[:, None]
        new = v.copy()
        new[n_fixed:] = 0.5 * v[n_fixed:] + 0.5 * avg[n_fixed:]
        xy = new[:, :2]
        r = np.sqrt((xy[:, 0] / a) ** 2 + (xy[:, 1] / b) ** 2)
        over = r > 0.995
        xy[over] *= (0.995 / r[over])[:, None]
        xy[:n_fixed] = v[:n_fixed, :2]
        cand = np.column_stack([xy, g.height(xy[:, 0], xy[:, 1])])
        cand[:n_fixed, 2] = 0.0
        # Keep the step only where it leaves every triangle oriented outward.
        p = cand[tri]
        nz = (p[:, 1, 0] - p[:, 0, 0]) * (p[:, 2, 1] - p[:, 0, 1]) - (p[:, 1, 1] - p[:, 0, 1]) * (
            p[:, 2, 0] - p[:, 0, 0]
        )
        if (nz <= 0).any():
            break
        v = cand
    return v
