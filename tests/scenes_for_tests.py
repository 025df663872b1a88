"""Small scenes used across the tests, built through the public JSON schema."""

import numpy as np

from lgnn.scene import scene_from_dict


def pendulum(angle: float = 0.3, length: float = 1.0, mass: float = 1.0, gravity: float = 10.0):
    """One uniform rod pinned at node 0, released from rest at `angle` from the vertical."""
    tip = [length * np.sin(angle), -length * np.cos(angle)]
    return scene_from_dict(
        {
            "name": "pendulum",
            "gravity": gravity,
            "nodes": [[0.0, 0.0], tip],
            "pinned": [0],
            "links": [{"nodes": [0, 1], "mass": mass, "inertia": mass * length**2 / 12}],
        }
    )


def pinned_triangle():
    """A rigid triangle pinned at two corners: 3 links + 2 pins on 3 nodes (redundant)."""
    return scene_from_dict(
        {
            "name": "triangle",
            "nodes": [[0.0, 0.0], [1.0, 0.0], [0.5, -0.8]],
            "pinned": [0, 1],
            "links": [
                {"nodes": [0, 1], "mass": 1.0, "inertia": 0.1},
                {"nodes": [1, 2], "mass": 1.0, "inertia": 0.1},
                {"nodes": [2, 0], "mass": 1.0, "inertia": 0.1},
            ],
        }
    )


def free_triangle():
    """An unpinned triangle with some spin: a free rigid body (no pins, no pin rows)."""
    nodes = np.array([[0.0, 0.0], [1.0, 0.0], [0.5, 0.8]])
    centre = nodes.mean(0)
    spin = 1.3
    velocities = spin * np.stack([-(nodes[:, 1] - centre[1]), nodes[:, 0] - centre[0]], -1) + [0.2, 0.5]
    return scene_from_dict(
        {
            "name": "free-triangle",
            "gravity": 10.0,
            "nodes": nodes.tolist(),
            "velocities": velocities.tolist(),
            "pinned": [],
            "links": [
                {"nodes": [0, 1], "mass": 1.0, "inertia": 0.1},
                {"nodes": [1, 2], "mass": 2.0, "inertia": 0.3},
                {"nodes": [2, 0], "mass": 0.5, "inertia": 0.05},
            ],
        }
    )


def double_pinned_chain(n_links: int = 4, sag: float = 0.5):
    """A chain of unit links hanging between two pins (a closed loop through the ground)."""
    half = n_links // 2
    xs = np.concatenate([np.arange(half + 1) * np.sqrt(1 - sag**2), half * np.sqrt(1 - sag**2) + np.arange(1, n_links - half + 1) * np.sqrt(1 - sag**2)])
    ys = np.concatenate([-np.arange(half + 1) * sag, -half * sag + np.arange(1, n_links - half + 1) * sag])
    nodes = np.stack([xs, ys], -1)
    return scene_from_dict(
        {
            "name": "double-pinned",
            "nodes": nodes.tolist(),
            "pinned": [0, n_links],
            "links": [{"nodes": [k, k + 1], "mass": 1.0, "inertia": 1 / 12} for k in range(n_links)],
        }
    )
