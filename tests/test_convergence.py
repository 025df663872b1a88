"""The reference-convergence measurement (lgnn.bench.convergence): it recovers RK4's
order on a chain, flags a step that is too large, and judges successive differences
as the module says."""

import math

import numpy as np

import pytest

from lgnn.bench import convergence
from lgnn.engines.base import SimulationConfig
from lgnn.scene import get_scene


@pytest.fixture(scope="module")
def chain4_rows():
    """chain4 over 1 s at dt 0.25, 0.125, 0.0625, 0.03125 (frames every 0.25 s): RK4
    with projection diverges at 0.25 (its energy grows to 1e5) and is in its asymptotic
    range from 0.125 on."""
    config = SimulationConfig(dt=0.25, frame_dt=0.25, duration=1.0)
    return convergence.reference_convergence(get_scene("chain4"), config, halvings=3)


def test_recovers_rk4_order_with_projection(chain4_rows):
    """RK4 with projection keeps order 4: projecting an O(dt^5) local error onto the
    constraint manifold moves the state by O(dt^5) per step, so the projection does not
    limit the order (measured 4.15 here, 3.99 at dt 1e-3)."""
    row = chain4_rows[1]
    assert row["dt"] == 0.125
    assert abs(row["order"] - 4) < 0.5, chain4_rows
    assert row["verdict"] == "asymptotic"
    # Richardson: the estimate is the difference over 2^p - 1 ~ 15.
    assert row["error_estimate"] == pytest.approx(row["difference"] / (2 ** row["order"] - 1))
    # The finer run's estimate, at the same order, is ~16 x smaller.
    assert 8 < row["error_estimate"] / chain4_rows[2]["error_estimate"] < 32


def test_flags_a_bad_step(chain4_rows):
    row = chain4_rows[0]
    assert row["verdict"] == "diverged" and row["verdict"] not in convergence.TRUSTED
    assert math.isnan(row["error_estimate"]) and "exploded" in row["note"]
    assert convergence.summary(chain4_rows)[0].endswith("diverged; NOT RANKABLE: a reference run diverged")


FLOORS = [1e-14] * 4


@pytest.mark.parametrize(
    ("differences", "verdicts"),
    [
        # Order 4, steady: Richardson on each but the last, which borrows the order before it.
        ([1.6e-6, 1e-7, 6.25e-9], ["asymptotic", "asymptotic", "asymptotic"]),
        # T3's measured differences (issue 13): order ~0.2, not a sane order.
        ([1.5e-3, 1.25e-3, 1.1e-3], ["not-converged", "not-converged", "unassessed"]),
        # A steady order 1: trusted as a low-order estimate.
        ([4e-4, 2e-4, 1e-4], ["low-order", "low-order", "low-order"]),
        # Orders 4 then 1: not steady.
        ([1.6e-5, 1e-6, 5e-7], ["not-converged", "low-order", "low-order"]),
        # Round-off: everything agrees to round-off, or the next halving does.
        ([1e-12, 1e-15, 1e-15], ["resolved", "round-off", "round-off"]),
        # A run diverged.
        ([math.nan, 1e-6, 6.25e-8], ["diverged", "asymptotic", "asymptotic"]),
    ],
)
def test_assess(differences, verdicts):
    assessments = convergence.assess(differences, FLOORS, 4)
    assert [a.verdict for a in assessments] == verdicts
    for d, a in zip(differences, assessments):
        if a.verdict == "not-converged":
            assert a.error_estimate == d  # the raw difference, a lower bound
        if a.verdict == "asymptotic" and math.isfinite(a.order):
            assert a.error_estimate == pytest.approx(d / 15, rel=0.05)


def test_rigidity_of_the_structures():
    """T2 is prestress-stable (one self-stress, ropes in tension and the rod in
    compression, definite on all its flexes): rigid, its exact motion is rest. T3 is
    singular too, with flexes no self-stress resists (a mechanism that can move). A
    chain is regular: no self-stress, every flex free."""
    t2 = convergence.rigidity(get_scene("T2"))
    assert (t2.self_stresses, t2.unresisted, t2.prestress_stable) == (1, 0, True) and t2.flexes > 30
    t3 = convergence.rigidity(get_scene("T3"))
    assert t3.self_stresses == 4 and 0 < t3.unresisted < t3.flexes
    chain = convergence.rigidity(get_scene("chain4"))
    assert (chain.flexes, chain.self_stresses, chain.unresisted) == (4, 0, 4) and chain.describe() == ""
    # A rope pulled exactly taut between two pins: one self-stress, rigid.
    taut = convergence.rigidity(get_scene("taut4-exact"))
    assert (taut.self_stresses, taut.unresisted, taut.prestress_stable) == (1, 0, True)


@pytest.mark.parametrize("name", ["T2", "T3"])
def test_slackened_structure_is_regular(name):
    """The slackened T2/T3 (catalogue.slackened): ropes 0.1 % longer, rods unchanged, the
    start on the new lengths, a few centimetres from the taut one, and no self-stress
    (so the inextensible model is regular there; results/convergence.md: order 4)."""
    from lgnn.scene.catalogue import ROPE_SLACK

    taut, slack = get_scene(name), get_scene(f"{name}-slack")
    ropes = np.array([t == "link" for t in taut.link_types])
    np.testing.assert_allclose(slack.lengths[ropes], taut.lengths[ropes] * (1 + ROPE_SLACK), rtol=1e-14)
    np.testing.assert_array_equal(slack.lengths[~ropes], taut.lengths[~ropes])
    i, j = slack.edge_index.T
    np.testing.assert_allclose(np.linalg.norm(slack.nodes[i] - slack.nodes[j], axis=-1), slack.lengths, rtol=0, atol=1e-12)
    assert 1e-3 < np.max(np.abs(slack.nodes - taut.nodes)) < 0.1
    assert convergence.rigidity(slack).self_stresses == 0
