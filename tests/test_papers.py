"""Finzi et al. (2020)'s chain pendulums and protocol (`lgnn.bench.papers`): the systems
are the authors', their initial-state distribution and metric are theirs (the chaos
floor, which depends on nothing learned, lands on the published one), and the quick
protocol runs, writes its table and resumes."""

from __future__ import annotations

import dataclasses
import json

import numpy as np
import pytest

from lgnn.bench import papers
from lgnn.engines import get_engine
from lgnn.engines.base import SimulationConfig
from lgnn.errors import ConfigError, SceneError
from lgnn.scene import State, finzi_pendulum, scene_from_dict
from lgnn.scene.catalogue import FINZI_PENDULUMS


@pytest.mark.parametrize("bobs", sorted(FINZI_PENDULUMS))
def test_the_pendulums_have_the_authors_masses_and_lengths(bobs):
    """The authors draw n masses then n lengths as 0.6 + 0.8 U with NumPy's legacy
    generator seeded 0, and hand them out from the end of each list."""
    rng = np.random.RandomState(0)
    masses = [0.6 + 0.8 * rng.rand() for _ in range(bobs)]
    lengths = [0.6 + 0.8 * rng.rand() for _ in range(bobs)]
    scene = finzi_pendulum(bobs)
    assert scene.pinned == (0,) and scene.edges == tuple((k, k + 1) for k in range(bobs))
    np.testing.assert_allclose([m for _, m in scene.point_masses], masses[::-1], rtol=1e-11)
    np.testing.assert_allclose(scene.lengths, lengths[::-1], rtol=1e-11)
    assert np.all(scene.masses == 0) and np.all(scene.inertias == 0) and float(scene.gravity) == 9.81


def test_a_massless_link_needs_mass_at_its_free_nodes_and_has_no_inertia():
    base = {"name": "x", "nodes": [[0, 0], [1, 0], [2, 0]], "pinned": [0],
            "links": [{"nodes": [0, 1], "mass": 0.0, "inertia": 0.0}, {"nodes": [1, 2], "mass": 0.0, "inertia": 0.0}]}
    with pytest.raises(SceneError, match="free node 1 has no mass: it belongs to massless links only"):
        scene_from_dict({**base, "point_masses": [{"node": 2, "mass": 1.0}]})
    with pytest.raises(SceneError, match="massless link has no inertia"):
        scene_from_dict({**base, "links": [{"nodes": [0, 1], "mass": 0.0, "inertia": 0.1}, base["links"][1]]})
    assert scene_from_dict({**base, "point_masses": [{"node": 1, "mass": 1.0}, {"node": 2, "mass": 0.5}]}).n_links == 2


def test_the_pendulums_conserve_energy_and_move_as_mujoco_moves_them():
    """The 3-pendulum from states of the authors' distribution: the Lagrangian engine
    keeps energy and the rod lengths to round-off over 3 s, and MuJoCo C on its
    rendered MJCF (the bobs carried by the massless rods' bodies) agrees within 1e-8 m."""
    scene = finzi_pendulum(3)
    states = papers.finzi_initial_states(scene, 3, seed=7)
    ours = get_engine("lagrangian").rollout(scene, SimulationConfig(dt=1e-3, frame_dt=0.03, duration=3.0), states)
    assert np.abs(ours.q[:, -1] - ours.q[:, 0]).max() > 0.5  # it moves
    assert np.abs(ours.energy - ours.energy[:, :1]).max() < 1e-9 * np.abs(ours.energy).max()
    q = np.asarray(ours.q)
    stretch = np.linalg.norm(q[..., 1:, :] - q[..., :-1, :], axis=-1) - scene.lengths
    assert np.abs(stretch).max() < 1e-10
    config = SimulationConfig(duration=2.0)
    lagrangian, mujoco = (get_engine(name).rollout(scene, config, states) for name in ("lagrangian", "mujoco"))
    assert np.abs(lagrangian.q - mujoco.q).max() < 1e-8


def test_the_initial_states_follow_the_authors_distribution():
    """One bob (length l): its angle is the rod's N(0, 1) angle moved by position noise
    0.2 (std about sqrt(1 + (0.2 / l)^2)), its speed along the circle 3 (0.5 l w + 0.4
    n) (std 3 sqrt(0.25 l^2 + 0.16)); every state on the constraints."""
    scene = finzi_pendulum(1)
    length = float(scene.lengths[0])
    states = papers.finzi_initial_states(scene, 4000, seed=0)
    bob, velocity = states.q[:, 1], states.qd[:, 1]
    np.testing.assert_allclose(np.linalg.norm(bob, axis=-1), length, rtol=1e-9)
    np.testing.assert_allclose(np.sum(bob * velocity, -1), 0.0, atol=1e-9)
    angle = np.arctan2(bob[:, 0], -bob[:, 1])
    tangent = np.stack([np.cos(angle), np.sin(angle)], -1)
    speed = np.sum(velocity * tangent, -1)
    assert abs(np.mean(angle)) < 0.05 and abs(np.std(angle) / np.sqrt(1 + (0.2 / length) ** 2) - 1) < 0.04
    assert abs(np.mean(speed)) < 0.1 and abs(np.std(speed) / (3 * np.sqrt(0.25 * length**2 + 0.16)) - 1) < 0.04
    from lgnn.scene import get_scene
    with pytest.raises(SceneError, match="planar chains pinned at node 0"):
        papers.finzi_initial_states(get_scene("T1"), 2, seed=0)


def test_the_chaos_floor_lands_on_the_published_one():
    """The truth against itself started 1e-4 away, on the 2-pendulum's 100 test
    trajectories: the published floor by the stated rule (it depends on the system,
    the distribution and the metric, nothing learned)."""
    protocol = papers.Protocol(bobs=(2,), train=1, batch=1, validation=1)
    scene = finzi_pendulum(2)
    start = papers.finzi_initial_states(scene, protocol.test, protocol.data_seeds[2])
    data = papers.Data(State(start.q[:1, None], start.qd[:1, None]), None, papers.truth(scene, protocol, start))
    floor = float(np.mean(papers.chaos_floor(scene, protocol, data)))
    assert papers.reproduced(floor, papers.PUBLISHED[(2, "floor")]), floor


def test_the_metric_is_the_authors():
    """`|z - z*| / (|z| + |z*|)` over the bobs' positions and velocities, and its
    geometric mean `exp(trapz(log(err + 1e-8), dt) / duration)`."""
    scene = finzi_pendulum(2)
    rng = np.random.default_rng(0)
    true = State(rng.standard_normal((3, 100, 3, 2)), rng.standard_normal((3, 100, 3, 2)))
    doubled = State(2 * true.q, 2 * true.qd)
    np.testing.assert_allclose(papers.relative_errors(scene, doubled, true), 1 / 3, rtol=1e-12)
    errors = np.full((2, 100), 1e-3)
    np.testing.assert_allclose(papers.geometric_means(errors, 0.03, 3.0), (1e-3 + 1e-8) ** (99 * 0.03 / 3.0), rtol=1e-12)


def test_the_rate_is_pytorch_cosine_annealing_stepped_per_epoch():
    protocol = papers.Protocol()
    rate = papers.schedule(protocol)
    per_epoch = protocol.steps_per_epoch
    assert float(rate(0)) == pytest.approx(3e-3) and float(rate(per_epoch - 1)) == float(rate(0))
    assert float(rate(per_epoch * protocol.epochs // 2)) == pytest.approx(1.5e-3)
    assert float(rate(per_epoch * protocol.epochs)) == pytest.approx(0.0, abs=1e-18)


def test_the_quick_protocol_trains_writes_its_table_and_resumes(tmp_path):
    lines = []
    readme = papers.run(papers.QUICK, tmp_path / "papers", log=lines.append)
    text = readme.read_text()
    for name in papers.QUICK.models:
        assert f"{papers.PUBLISHED[(2, papers.PUBLISHED_MODEL[name])][0]:.2e} [" in text and f"| 2-pendulum | {name}" in text
    assert "chaos floor" in text
    csv = (tmp_path / "papers" / "quick.csv").read_text().splitlines()
    assert len(csv) == 1 + len(papers.QUICK.models) * len(papers.QUICK.seeds)
    lines.clear()
    papers.run(papers.QUICK, tmp_path / "papers", log=lines.append)
    assert [line for line in lines if "reusing" in line] == [f"{name} on finzi-pendulum2: reusing its record" for name in papers.QUICK.models]
    assert (tmp_path / "papers" / "README.md").read_text() == text
    with pytest.raises(ConfigError, match="is not recorded with these settings"):
        papers.run(dataclasses.replace(papers.QUICK, epochs=21), tmp_path / "papers", log=lines.append, train=False)


def test_the_committed_table_is_its_records_rendered(tmp_path):
    """results/papers/README.md and its CSV are what the run makes of the committed
    group records (every group reused, nothing trained): no number edited by hand."""
    import shutil
    from pathlib import Path

    committed = Path(__file__).resolve().parents[1] / "results" / "papers"
    shutil.copytree(committed / "groups", tmp_path / "groups")
    settings = json.loads((committed / "run.json").read_text())["protocol"]
    protocol = papers.Protocol(**{k: tuple(v) if isinstance(v, list) else v for k, v in settings.items()})
    papers.run(protocol, tmp_path, log=lambda line: None, train=False)
    assert (tmp_path / "README.md").read_text() == (committed / "README.md").read_text()
    assert (tmp_path / "finzi2020.csv").read_text() == (committed / "finzi2020.csv").read_text()


def test_the_lgnn_paper_table_reads_the_benchmark_cells_by_its_rule(tmp_path):
    """`lgnn2022_report`: the pooled cell of each model, scene and metric against the
    stated ~1e-4 (half a decade either side), and the committed table is the committed
    summary's cells rendered."""
    import gzip
    from pathlib import Path

    root = Path(__file__).resolve().parents[1] / "results"
    assert papers.lgnn2022_report(root) == (root / "papers" / "lgnn2022.md").read_text()
    rows = ["scene,model,seed,metric,commit,versions,device,statistic,value"]
    for scene, value in (("T1", 2e-4), ("T2-slack", 5e-3), ("T3-slack", 1e-5)):
        rows += [f"{scene},lgnn,{seed},rollout_error,abc,v,d,gmean,{value}" for seed in (-1, 0)]
    (tmp_path / "benchmark").mkdir()
    with gzip.open(tmp_path / "benchmark" / "summary.csv.gz", "wt") as handle:
        handle.write("\n".join(rows) + "\n")
    text = papers.lgnn2022_report(tmp_path)
    assert "| T1 | lgnn | rollout error | ~1e-4 | 2.00e-04 | 2.00e-04 | yes |" in text
    assert "| T2-slack | lgnn | rollout error | ~1e-4 | 5.00e-03 | 5.00e-03 | no: higher |" in text
    assert "| T3-slack | lgnn | rollout error | ~1e-4 | 1.00e-05 | 1.00e-05 | no: lower |" in text
    assert "| T1 | lgnn | energy violation | ~1e-4 | | not in the summary | |" in text
    with pytest.raises(ConfigError, match="no benchmark summary"):
        papers.lgnn2022_report(tmp_path / "nowhere")


def test_the_papers_command_refuses_options_its_protocol_does_not_read(capsys, tmp_path):
    from lgnn.cli import main

    for argv, words in ((["--protocol", "lgnn2022", "--seeds", "1"], "trains nothing"),
                        (["--protocol", "quick", "--results", "results"], "--results is read by --protocol lgnn2022 only")):
        assert main(["papers", *argv, "--out-dir", str(tmp_path / "x")]) == 2
        err = capsys.readouterr().err.strip()
        assert words in err and "\n" not in err
    assert not (tmp_path / "x").exists()
