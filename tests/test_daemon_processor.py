"""bubble_rt.daemon.processor: contact patches (connected components of the contact mask)."""

from __future__ import annotations

import numpy as np
import pytest
from bubble_rt.daemon.processor import PatchFinder
from bubble_rt.mesh import Mesh

pytestmark = pytest.mark.timeout(60)


def test_patches_are_connected_components():
    mesh = Mesh.preset("coarse")
    pf = PatchFinder(mesh)
    # Two far-apart single nodes plus one node's full neighbourhood.
    interior = np.flatnonzero(mesh.interior)
    xs = mesh.vertices[interior, 0]
    a, b = interior[np.argmin(xs)], interior[np.argmax(xs)]
    contact = np.zeros(mesh.n_nodes, bool)
    contact[[a, b]] = True
    nb = pf.adjacency[a].indices
    contact[nb] = True
    forces = np.zeros((mesh.n_nodes, 3))
    forces[contact, 2] = -1.0
    patches = pf.patches(contact, forces)
    assert len(patches) == 2
    big = patches[0]
    assert a in big.nodes and b not in big.nodes
    np.testing.assert_allclose(big.force, [0, 0, -float(len(big.nodes))])
    np.testing.assert_allclose(big.area, pf.areas[big.nodes].sum())
