import numpy as np
import pytest
from bubble_rt.sim.indenters import (
    PRESET_SIZES,
    Box,
    Capsule,
    Indenter,
    Sphere,
    Union,
    from_spec,
    preset,
)

I4 = np.eye(4)


def _fd_gradient(shape, p, h=1e-7):
    g = np.zeros_like(p)
    for k in range(3):
        e = np.zeros(3)
        e[k] = h
        g[:, k] = (shape.distance(p + e, I4)[0] - shape.distance(p - e, I4)[0]) / (2 * h)
    return g


def _random_points(n=200, seed=0, scale=0.03):
    return np.random.default_rng(seed).uniform(-scale, scale, (n, 3))


def test_sphere_distance_and_gradient():
    s = Sphere(0.01, (0.0, 0.0, 0.01))
    d, g = s.distance(np.array([[0, 0, -0.002], [0, 0, 0.01], [0.02, 0, 0.01]]), I4)
    assert np.allclose(d, [0.002, -0.01, 0.01])
    assert np.allclose(g[0], [0, 0, -1]) and np.allclose(g[2], [1, 0, 0])
    assert np.allclose(np.linalg.norm(g, axis=1), 1.0)


def test_capsule_distance_to_segment_and_caps():
    c = Capsule((-0.02, 0, 0), (0.02, 0, 0), 0.004)
    d, g = c.distance(np.array([[0, 0, 0.01], [0.03, 0, 0], [0.0, 0.0, 0.0]]), I4)
    assert np.allclose(d, [0.006, 0.006, -0.004])
    assert np.allclose(g[0], [0, 0, 1]) and np.allclose(g[1], [1, 0, 0])


def test_sharp_box_distance_inside_outside_and_corner():
    b = Box((0.01, 0.02, 0.005))
    p = np.array([[0, 0, 0.008], [0, 0, 0.004], [0.013, 0.024, 0.0], [0.0, -0.019, 0.0]])
    d, g = b.distance(p, I4)
    assert np.allclose(d, [0.003, -0.001, 0.005, -0.001])
    assert np.allclose(g[0], [0, 0, 1]) and np.allclose(g[2], [0.6, 0.8, 0])
    assert np.allclose(g[3], [0, -1, 0])


def test_rounded_box_keeps_outer_size_and_rounds_edges():
    b = Box((0.01, 0.01, 0.01), rounding=0.002)
    d, _ = b.distance(np.array([[0, 0, 0.01], [0.01, 0.01, 0.0]]), I4)
    assert abs(d[0]) < 1e-12  # face centre still on the surface
    assert np.isclose(d[1], 0.002 * (np.sqrt(2) - 1))  # the edge is rounded away


@pytest.mark.parametrize(
    "shape",
    [
        Sphere(0.01),
        Capsule((0, 0, -0.01), (0.005, 0, 0.01), 0.004),
        Box((0.01, 0.015, 0.008), rounding=0.002),
        Box((0.01, 0.015, 0.008)),
        Union((Sphere(0.006, (0.01, 0, 0)), Sphere(0.006, (-0.01, 0, 0)))),
    ],
    ids=["sphere", "capsule", "rounded_box", "box", "union"],
)
def test_gradient_matches_finite_differences(shape):
    p = _random_points()
    d, g = shape.distance(p, I4)
    fd = _fd_gradient(shape, p)
    # Skip points on the non-smooth medial sets (ties), where any subgradient is valid.
    smooth = np.linalg.norm(fd, axis=1) > 0.999
    assert smooth.sum() > 150
    assert np.allclose(g[smooth], fd[smooth], atol=1e-5)
    assert np.allclose(np.linalg.norm(g, axis=1), 1.0)


def test_union_takes_nearest_member():
    u = Union((Sphere(0.005, (0.02, 0, 0)), Sphere(0.005, (-0.02, 0, 0))))
    d, g = u.distance(np.array([[0.02, 0, 0.01], [-0.02, 0, -0.01], [0.0, 0, 0]]), I4)
    assert np.allclose(d, [0.005, 0.005, 0.015])
    assert np.allclose(g[0], [0, 0, 1]) and np.allclose(g[1], [0, 0, -1])


def test_pose_moves_and_rotates_the_shape():
    c = Capsule((0, 0, 0.004), (0, 0, 0.03), 0.004)
    T = np.eye(4)
    # Rotate 90 deg about y: local +z -> mesh +x; then translate.
    T[:3, :3] = [[0, 0, 1], [0, 1, 0], [-1, 0, 0]]
    T[:3, 3] = [0.01, 0.0, 0.02]
    d, g = c.distance(np.array([[0.01 + 0.02, 0, 0.02 + 0.01], [0.0, 0.0, 0.02]]), T)
    # The tip (local origin) sits at mesh (0.01, 0, 0.02); the axis runs along mesh +x.
    assert np.allclose(d, [0.006, 0.01])
    assert np.allclose(g[0], [0, 0, 1]) and np.allclose(g[1], [-1, 0, 0])


@pytest.mark.parametrize("name", sorted(PRESET_SIZES))
def test_presets_have_tip_at_origin_and_body_above(name):
    s = preset(name)
    assert isinstance(s, Indenter)
    d, _ = s.distance(np.array([[0.0, 0.0, -0.001], [0.0, 0.0, 0.0]]), I4)
    if name == "split":  # two prongs either side of the axis, tips at z = 0
        d, _ = s.distance(np.array([[0.0125, 0.0, -0.001], [0.0125, 0.0, 0.0]]), I4)
    assert np.isclose(d[0], 0.001, atol=1e-9)
    assert abs(d[1]) < 1e-9
    d_up, _ = s.distance(np.array([[0.0, 0.0, 0.005 if name != "split" else 0.03]]), I4)
    assert d_up[0] < 0 or name == "split"


def test_split_prongs_leave_a_gap_between_them():
    s = preset("split")
    d, _ = s.distance(np.array([[0.0, 0.0, 0.003]]), I4)
    assert d[0] > 0.005


def test_from_spec_builds_user_shapes_and_rejects_bad_input():
    u = from_spec(
        {
            "type": "union",
            "shapes": [
                {"type": "sphere", "radius": 0.01},
                {"type": "box", "half_extents": [0.01, 0.01, 0.01], "rounding": 0.001},
                {"type": "capsule", "a": [0, 0, 0], "b": [0, 0, 0.01], "radius": 0.002},
                "round",
            ],
        }
    )
    assert isinstance(u, Union) and len(u.shapes) == 4
    cap = from_spec({"type": "capsule", "radius": 0.002, "length": 0.01, "center": [0, 0, 0.01]})
    assert np.allclose(cap.a, (0, 0, 0.005)) and np.allclose(cap.b, (0, 0, 0.015))
    box = from_spec({"type": "box", "size": [0.02, 0.01, 0.004]})
    assert np.allclose(box.half_extents, (0.01, 0.005, 0.002))
    with pytest.raises(ValueError, match="radius"):
        from_spec({"type": "sphere"})
    with pytest.raises(ValueError, match="unknown indenter type"):
        from_spec({"type": "cone"})
    with pytest.raises(ValueError, match="unknown indenter"):
        preset("triangle")
    with pytest.raises(ValueError):
        Sphere(-1.0)
    with pytest.raises(ValueError):
        Sphere(0.01).distance(np.zeros((3, 2)), I4)
