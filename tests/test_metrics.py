"""The one definition of each measure (`lgnn.metrics`): energy drift, divergence, errors."""

import json
import re

import numpy as np
import pytest

from lgnn import metrics
from lgnn.cli import main
from lgnn.engines.base import SimulationConfig
from lgnn.engines.lagrangian import simulate
from lgnn.scene import State, get_scene, scene_from_dict
from lgnn.trajectory import Trajectory


def horizontal_double_pendulum():
    """Two unit rods pinned at the origin, released along +x: initial energy exactly 0."""
    return scene_from_dict({
        "name": "double-pendulum", "nodes": [[0, 0], [1, 0], [2, 0]], "pinned": [0],
        "links": [{"nodes": [0, 1], "mass": 1.0, "inertia": 1 / 12}, {"nodes": [1, 2], "mass": 1.0, "inertia": 1 / 12}],
    })


class Frames:
    def __init__(self, q, qd, energy):
        self.q, self.qd, self.energy = np.asarray(q), np.asarray(qd), np.asarray(energy, float)


def test_energy_drift_is_the_maximum_over_frames_over_a_scale_that_cannot_vanish():
    scene = horizontal_double_pendulum()
    q = np.repeat(scene.nodes[None], 3, axis=0)
    qd = np.zeros_like(q)
    scale = metrics.energy_scale(scene, scene.initial_state)
    # weight x size + size^2 per unit time^2 with size = 2 (links) + 2 (extent): m (g s + s^2)
    assert np.isclose(scale, 2 * (10 * 4 + 16))
    # E0 = 0 gives a finite drift; the largest excursion counts, not the last frame's
    assert metrics.energy_drift(scene, Frames(q, qd, [0.0, 3.0, 1.0])) == 3.0 / scale  # exact: one NumPy division of the same scale
    assert np.isnan(metrics.energy_drift(scene, Frames(q[:0], qd[:0], [])))


def test_simulate_reports_the_drift_of_a_pendulum_released_with_zero_energy(tmp_path, capsys):
    """Before: `relative energy drift 1.78e+286` (division by E0 = 0, last frame only)."""
    path = tmp_path / "scene.json"
    path.write_text(json.dumps({
        "name": "double-pendulum", "nodes": [[0, 0], [1, 0], [2, 0]], "pinned": [0],
        "links": [{"nodes": [0, 1], "mass": 1.0, "inertia": 0.0833}, {"nodes": [1, 2], "mass": 1.0, "inertia": 0.0833}],
    }))
    assert main(["simulate", str(path), "--duration", "0.1", "--out", str(tmp_path / "t.npz"), "--quiet"]) == 0
    drift = float(re.search(r"energy drift ([0-9.e+-]+)", capsys.readouterr().out).group(1))
    assert drift < 1e-12


def test_divergence_rule_is_one_rule_for_engines_and_the_benchmark():
    """`divergence_frames` (the benchmark, batched) flags exactly the frames that
    `ExplosionBounds.first_violation` (every engine) stops at."""
    scene = get_scene("chain4")
    traj = simulate(scene, SimulationConfig(dt=1e-3, duration=0.05, frame_dt=5e-3), progress=False)
    q, qd, energy = (np.repeat(np.asarray(a)[None], 4, axis=0).copy() for a in (traj.q, traj.qd, traj.energy))
    bounds = metrics.ExplosionBounds.of(scene, State(traj.q[0], traj.qd[0]), float(traj.energy[0]))
    q[1, 4:] += 2 * metrics.EXPLOSION_FACTOR * bounds.size  # a node far away
    energy[2, 6:] += 2 * metrics.EXPLOSION_FACTOR * bounds.energy_scale  # an impossible energy
    q[3, 8:] = np.nan
    frames = metrics.divergence_frames(scene, traj.t, q, qd, energy)
    assert list(frames) == [-1, 4, 6, 8]
    for c in range(4):
        found = bounds.first_violation(traj.t, q[c], qd[c], energy[c])
        assert (found[0] if found else -1) == frames[c]


def test_true_energies_match_the_engine_and_mask_non_finite_states():
    scene = get_scene("chain4")
    traj = simulate(scene, SimulationConfig(dt=1e-3, duration=0.02, frame_dt=5e-3), progress=False)
    q = np.stack([traj.q, traj.q]); q[1, 2] = np.nan
    energy = metrics.true_energies(scene, q, np.stack([traj.qd, traj.qd]))
    np.testing.assert_allclose(energy[0], traj.energy, rtol=1e-12)
    assert np.isnan(energy[1, 2]) and np.isfinite(np.delete(energy[1], 2)).all()


def test_errors_are_clipped_and_count_as_one_after_divergence():
    errors = np.array([[0.0, 1e-3, 1e-3], [1e-3, np.nan, 1e-3]])
    clean = metrics.clean_errors(errors, np.array([2, -1]))
    assert clean.tolist() == [[metrics.ERROR_FLOOR, 1e-3, 1.0], [1e-3, 1.0, 1e-3]]
    a = np.ones((2, 3, 2))
    assert np.allclose(metrics.relative_error(a, -a, 2), 1.0) and np.allclose(metrics.relative_error(a, a, 2), 0.0)


def test_a_maximum_per_trajectory_replaces_frames_from_divergence_and_bounds_the_rest():
    errors = np.array([[0.0, 3.0, 50.0], [2.0, np.inf, 2.0]])
    clean = metrics.clean_errors(errors, np.array([-1, 2]), maximum=np.array([10.0, 20.0]))
    assert clean.tolist() == [[10.0 * metrics.ERROR_FLOOR, 3.0, 10.0], [2.0, 20.0, 20.0]]


def test_node_rms_error_is_the_root_mean_square_distance_over_nodes():
    a = np.zeros((2, 3, 2))
    b = a.copy()
    b[1, 0] = [3.0, 4.0]  # one node of three 5 away at the second frame
    np.testing.assert_allclose(metrics.node_rms_error(a, b), [0.0, np.sqrt(25 / 3)], rtol=1e-15)


def _chain4_truth():
    scene = get_scene("chain4")
    traj = simulate(scene, SimulationConfig(dt=1e-3, duration=0.05, frame_dt=5e-3), progress=False)
    q, qd, energy = (np.stack([np.asarray(a)] * 2) for a in (traj.q, traj.qd, traj.energy))
    return scene, np.asarray(traj.t), q, qd, energy


def test_a_diverged_rollout_scores_each_metric_maximum_from_its_divergence_frame_on():
    """Two hand-made predictions of the same truth, 1e-3 off along x at every node; the
    second also flung 2 x 10 sizes away from frame 6 on: identical scores before frame 6,
    each metric's maximum from it on (the frame the one divergence rule flags)."""
    scene, t, q, qd, energy = _chain4_truth()
    predicted = q.copy()
    predicted[..., 0] += 1e-3
    size = metrics.structure_size(scene, q[0, 0])
    predicted[1, 6:] += 2 * metrics.EXPLOSION_FACTOR * size
    scored = metrics.score_rollouts(scene, metrics.trajectory_of(scene, t, predicted, qd), Trajectory(t, q, qd, energy))
    scores, diverged = scored.errors, scored.diverged
    assert diverged.tolist() == [-1, 6]
    assert set(scores) == set(metrics.METRICS)
    for name, errors in scores.items():
        assert errors.shape == (2, len(t) - 1), name
        # Frames 1..5: t > 0, before divergence; exact: equal inputs in one call.
        np.testing.assert_array_equal(errors[1, :5], errors[0, :5])
    np.testing.assert_allclose(scores["node_rms_error"][0], 1e-3, rtol=1e-9)
    expected = np.linalg.norm(predicted[0] - q[0], axis=(-1, -2)) / (np.linalg.norm(predicted[0], axis=(-1, -2)) + np.linalg.norm(q[0], axis=(-1, -2)))
    np.testing.assert_allclose(scores["rollout_error"][0], expected[1:], rtol=1e-12)
    assert (scores["rollout_error"][1, 5:] == 1.0).all() and (scores["energy_error"][1, 5:] == 1.0).all()
    assert (scores["node_rms_error"][1, 5:] == metrics.diverged_node_error(scene, predicted[1, 0])).all()
    # Exact: the shift along x leaves chain4's larger extent, along y, as it was.
    assert metrics.diverged_node_error(scene, predicted[1, 0]) == metrics.EXPLOSION_FACTOR * size


def test_the_rest_baseline_scores_exactly_the_truths_displacement_from_its_start():
    scene, t, q, qd, energy = _chain4_truth()
    truth = Trajectory(t, q, qd, energy)
    rest = metrics.rest_rollouts(truth)
    assert (rest.q == q[:, :1]).all() and (rest.qd == qd[:, :1]).all() and (rest.energy == energy[:, :1]).all() and rest.q.shape == q.shape
    scored = metrics.score_rollouts(scene, rest, truth)
    scores, diverged = scored.errors, scored.diverged
    assert diverged.tolist() == [-1, -1]
    q0, later = q[0, 0], q[0, 1:]
    displacement = [np.sqrt(np.mean([np.sum((node - node0) ** 2) for node, node0 in zip(frame, q0)])) for frame in later]
    np.testing.assert_allclose(scores["node_rms_error"][0], displacement, rtol=1e-12)
    relative = [np.linalg.norm(frame - q0) / (np.linalg.norm(frame) + np.linalg.norm(q0)) for frame in later]
    np.testing.assert_allclose(scores["rollout_error"][0], relative, rtol=1e-12)
    e = energy[0]
    np.testing.assert_allclose(scores["energy_error"][0], np.maximum(np.abs(e[1:] - e[0]) / (np.abs(e[1:]) + np.abs(e[0])), metrics.ERROR_FLOOR), rtol=1e-9)
    # Released from rest, the chain falls: after 0.05 s its nodes have moved by millimetres.
    assert 1e-4 < displacement[-1] < 0.05


def test_seed_intervals_cover_the_spread_between_seeds():
    """Seeds far apart (every IC of one at 1e-3, of the other at 1e-5) give the
    geometric mean 1e-4 with an interval reaching both; equal seeds give the
    single-seed interval over ICs; one seed is `summarise`."""
    from lgnn.metrics import summarise, summarise_seeds

    apart = [np.log(np.full(5, 1e-3)), np.log(np.full(5, 1e-5))]
    value, low, high = summarise_seeds(apart)
    assert value == pytest.approx(1e-4) and low == pytest.approx(1e-5) and high == pytest.approx(1e-3)
    ics = np.log(np.geomspace(1e-4, 1e-2, 8))
    assert summarise_seeds([ics])[0] == summarise(ics)[0]
    value, low, high = summarise_seeds([ics, ics])
    single = summarise(ics)
    assert value == pytest.approx(single[0]) and low < value < high and high / low < 1.5 * single[2] / single[1]


@pytest.mark.parametrize("seeds", [2, 3])
@pytest.mark.parametrize("ics", [1, 2, 3, 8, 100, [8, 5, 8]])
def test_the_seed_bootstrap_draws_what_one_call_per_resampled_seed_draws(seeds, ics):
    """The two-level bootstrap draws every resampled seed's ICs in one call where its
    generator gives the same numbers as one call per seed (even sizes, one IC): its
    interval is the one of that loop, written out here, to the last bit (one process,
    one generator: the same draws and the same sums)."""
    from lgnn.metrics import summarise_seeds

    sizes = ics if isinstance(ics, list) else [ics] * seeds
    logs = [np.random.default_rng(k).normal(-8, 3, size) for k, size in enumerate(sizes[:seeds])]
    rng = np.random.default_rng(0)
    picks = rng.integers(0, len(logs), (2000, len(logs)))
    boots = np.array([np.mean([logs[k][rng.integers(0, len(logs[k]), len(logs[k]))].mean() for k in pick]) for pick in picks])
    low, high = np.exp(np.percentile(boots, [2.5, 97.5]))
    assert summarise_seeds(logs)[1:] == (low, high)


def test_a_limits_angles_read_in_parts_unwrap_as_they_do_whole():
    """The engines check joint limits chunk by chunk, carrying the last frame's values
    (`limit_values(..., after=)`): over a link turning three and a half times, the parts' angles
    are the whole trajectory's, so a limit far past one turn is still seen."""
    scene = scene_from_dict({"name": "spinner", "nodes": [[0.0, 0.0], [1.0, 0.0]], "pinned": [0],
                             "links": [{"nodes": [0, 1], "mass": 1.0, "inertia": 0.1}],
                             "limits": [{"links": [0], "range": [-20.0, 20.0]}]})
    turned = np.linspace(0.0, 7 * np.pi, 301)
    q = np.stack([np.zeros((301, 2)), np.stack([np.cos(turned), np.sin(turned)], -1)], 1)
    whole = metrics.limit_values(scene, q)
    np.testing.assert_allclose(whole[:, 0], turned, atol=1e-12)
    parts, at = [], whole[0]
    for frames in (slice(1, 40), slice(40, 41), slice(41, 301)):
        parts.append(metrics.limit_values(scene, q[frames], after=at))
        at = parts[-1][-1]
    np.testing.assert_allclose(np.concatenate(parts), whole[1:], atol=1e-12)
    t = np.arange(301) * 0.01
    k, reason = metrics.first_outside_limits(scene, t, whole)
    assert turned[k] > 20.0 >= turned[k - 1] and "links [0]" in reason
