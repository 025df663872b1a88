"""Scenes: the JSON schema, its validation (one clear line per problem), the built-ins."""

import itertools
import json
import re

import numpy as np
import pytest

from lgnn.errors import SceneError
from lgnn.scene import Scene, load_scene_file, scene_from_dict, scene_to_dict, scene_to_json
from lgnn.scene import CATALOGUE, get_scene


def valid():
    return {
        "name": "two-links",
        "gravity": 9.81,
        "drag": 0.0,
        "nodes": [[0.0, 0.0], [0.6, -0.8], [1.6, -0.8]],
        "velocities": [[0.0, 0.0], [0.8, 0.6], [0.8, 1.6]],
        "pinned": [0],
        "links": [
            {"nodes": [0, 1], "mass": 1.0, "inertia": 0.1, "length": 1.0, "type": "rod"},
            {"nodes": [1, 2], "mass": 2.0, "inertia": 0.2},
        ],
    }


def test_valid_scene_loads_with_defaults():
    data = valid()
    del data["velocities"], data["gravity"], data["drag"]
    scene = scene_from_dict(data)
    assert isinstance(scene, Scene)
    assert scene.n_nodes == 3 and scene.n_links == 2 and scene.pinned == (0,)
    assert float(scene.gravity) == 10.0 and scene.drag == 0.0
    np.testing.assert_array_equal(scene.velocities, 0.0)
    assert scene.link_types == ("rod", "link")
    np.testing.assert_allclose(scene.lengths, [1.0, 1.0])


@pytest.mark.parametrize("name", list(CATALOGUE))
def test_json_round_trip_is_exact(name, tmp_path):
    scene = get_scene(name)
    path = tmp_path / f"{name}.json"
    path.write_text(scene_to_json(scene))
    again = load_scene_file(path)
    assert scene_to_dict(again) == scene_to_dict(scene)
    for field in ("nodes", "velocities", "lengths", "masses", "inertias", "gravity"):
        np.testing.assert_array_equal(getattr(again, field), getattr(scene, field))
    assert (again.edges, again.pinned, again.link_types, again.drag) == (scene.edges, scene.pinned, scene.link_types, scene.drag)


def valid3d():
    """`valid()` in 3D: the same links turned about the y axis (so every coordinate is
    used), gravity along -y as in 2D."""
    data = valid()
    for field in ("nodes", "velocities"):
        data[field] = [[0.6 * x, y, 0.8 * x] for x, y in data[field]]
    return data


def lift(path, value):
    """A mutation of `valid()` as one of `valid3d()`: points in nodes and velocities get
    a z = 0 (the 2D values that break a rule break it in 3D too)."""
    is_point = lambda v: isinstance(v, list) and all(isinstance(c, (int, float)) for c in v)  # noqa: E731
    if path[0] not in ("nodes", "velocities") or not isinstance(value, list):
        return value
    if is_point(value) and len(path) == 2:
        return [*value, 0.0]
    if all(is_point(point) for point in value):
        return [[*point, 0.0] for point in value]
    return value


def mutate(path, value, dim=2):
    """A copy of the valid scene (in `dim` dimensions) with the entry at `path`
    (keys/indices) set, or deleted if value is DELETE."""
    data = json.loads(json.dumps(valid() if dim == 2 else valid3d()))
    if dim == 3:
        value = lift(path, value)
    target = data
    for key in path[:-1]:
        target = target[key]
    if value is DELETE:
        del target[path[-1]]
    else:
        target[path[-1]] = value
    return data


DELETE = object()

# (what is changed, new value, words the one-line error must contain)
BAD_SCENES = [
    (("nodes",), DELETE, ["nodes", "missing"]),
    (("links",), DELETE, ["links", "missing"]),
    (("colour",), "red", ["colour", "unknown key"]),
    (("links", 0, "colour"), "red", ["links[0].colour", "unknown key"]),
    (("links", 1, "mass"), DELETE, ["links[1].mass", "missing"]),
    (("name",), 3, ["name", "string"]),
    (("gravity",), "ten", ["gravity", "number"]),
    (("drag",), -0.1, ["drag", ">= 0"]),
    (("nodes",), [[0.0, 0.0, 0.0], [0.6, -0.8], [1.6, -0.8]], ["nodes[0]", "expected 2 coordinates, got 3"]),
    (("nodes", 1), [0.6], ["nodes[1]"]),
    (("nodes",), "here", ["nodes", "list"]),
    (("nodes", 2, 0), float("nan"), ["nodes[2]", "finite"]),
    (("velocities", 1, 1), float("inf"), ["velocities[1]", "finite"]),
    (("velocities",), [[0.0, 0.0]], ["velocities", "3 entries"]),
    (("links", 0, "nodes"), [0, 7], ["links[0].nodes", "out of range"]),
    (("links", 0, "nodes"), [1, 1], ["links[0].nodes", "self link"]),
    (("links", 1, "nodes"), [1, 0], ["links[1].nodes", "duplicate link"]),
    (("links", 0, "nodes"), [0, 1, 2], ["links[0].nodes", "[i, j]"]),
    (("links", 0, "nodes"), [0, 1.5], ["links[0].nodes", "integer"]),
    (("links", 0, "mass"), -1.0, ["links[0].mass", ">= 0"]),
    (("links", 0, "mass"), True, ["links[0].mass", "number"]),
    (("links", 0, "inertia"), -1.0, ["links[0].inertia", ">= 0"]),
    (("links", 0, "length"), -1.0, ["links[0].length", "> 0"]),
    (("links", 0, "length"), 1.2, ["links[0]", "violate the link length"]),
    (("links", 0, "type"), "", ["links[0].type"]),
    (("links",), [], ["links", "non-empty"]),
    (("pinned",), [5], ["pinned[0]", "out of range"]),
    (("pinned",), [0, 0], ["pinned", "twice"]),
    (("pinned",), 0, ["pinned", "list"]),
    (("velocities", 0), [1.0, 0.0], ["velocities[0]", "pinned node"]),
    (("velocities", 2), [0.0, 0.0], ["velocities", "stretch links[1]"]),
]


@pytest.mark.parametrize("dim", [2, 3])
@pytest.mark.parametrize(("path", "value", "words"), BAD_SCENES, ids=[f"{'.'.join(map(str, p))}" for p, _, _ in BAD_SCENES])
def test_every_schema_violation_is_one_clear_line(path, value, words, dim):
    """Every rule holds with the same message in 3D (`lift` adds a z to the bad points;
    a first node of 3 coordinates becomes one of 4 among 3D nodes)."""
    if dim == 3 and words[-1] == "expected 2 coordinates, got 3":
        words = [words[0], "expected 3 coordinates, got 4"]
    with pytest.raises(SceneError) as info:
        scene_from_dict(mutate(path, value, dim))
    message = str(info.value)
    assert "\n" not in message
    for word in words:
        assert word in message, message


def test_a_spatial_scene_loads_with_three_coordinates():
    scene = scene_from_dict(valid3d())
    assert scene.dim == 3 and scene.nodes.shape == scene.velocities.shape == (3, 3)
    np.testing.assert_allclose(scene.lengths, [1.0, 1.0])
    data = valid3d()
    del data["velocities"]
    np.testing.assert_array_equal(scene_from_dict(data).velocities, np.zeros((3, 3)))
    assert scene_from_dict(valid()).dim == 2


@pytest.mark.parametrize(
    ("field", "points", "words"),
    [
        # The scene's dimension is what most points have; the odd one is named.
        ("nodes", [[0.0, 0.0, 0.0], [0.6, -0.8], [1.6, -0.8, 0.0]], ["nodes[1]", "expected 3 coordinates, got 2", "3D throughout"]),
        ("velocities", [[0.0, 0.0, 0.0], [0.0, 0.0], [0.0, 0.0]], ["velocities[0]", "expected 2 coordinates, got 3", "2D throughout"]),
        ("nodes", [[0.0, 0.0, 0.0, 0.0], [0.6, -0.8, 0.0, 0.0], [1.6, -0.8, 0.0, 0.0]], ["nodes[0]", "2 (planar) or 3 (spatial)", "got 4"]),
        ("nodes", [[0.0], [0.6], [1.6]], ["nodes[0]", "2 (planar) or 3 (spatial)", "got 1"]),
    ],
)
def test_a_scene_is_2d_or_3d_throughout(field, points, words):
    data = valid()
    data[field] = points
    with pytest.raises(SceneError) as info:
        scene_from_dict(data)
    message = str(info.value)
    assert "\n" not in message and "np." not in message  # numbers as numbers, not reprs
    for word in words:
        assert word in message, message


def test_not_an_object():
    with pytest.raises(SceneError, match="JSON object"):
        scene_from_dict([1, 2])


def test_zero_and_nearly_zero_length_links_are_rejected():
    data = valid()
    data["nodes"][2] = [0.6, -0.8 - 1e-9]
    with pytest.raises(SceneError, match=r"links\[1\].length.*nearly\) zero"):
        scene_from_dict(data)
    data["nodes"][2] = [0.6, -0.8]
    with pytest.raises(SceneError, match=r"links\[1\].length"):
        scene_from_dict(data)


def test_free_node_without_links_is_rejected():
    data = valid()
    data["nodes"].append([5.0, 5.0])
    data["velocities"].append([0.0, 0.0])
    with pytest.raises(SceneError, match="free node 3 has no mass: it belongs to no link"):
        scene_from_dict(data)


@pytest.mark.parametrize(
    ("content", "words"),
    [
        ('{"name": "x", ', "not valid JSON"),
        ("not json at all", "not valid JSON"),
        ('{"name": "x", "nodes": [[0, NaN]], "pinned": [], "links": []}', "NaN is not a JSON number"),
        (b"\xff\xfe\x00binary", "not a text"),
    ],
)
def test_bad_files(tmp_path, content, words):
    path = tmp_path / "scene.json"
    if isinstance(content, bytes):
        path.write_bytes(content)
    else:
        path.write_text(content)
    with pytest.raises(SceneError, match=words) as info:
        load_scene_file(path)
    assert str(path) in str(info.value)


def test_missing_and_huge_files(tmp_path, monkeypatch):
    with pytest.raises(SceneError, match="no such scene file"):
        load_scene_file(tmp_path / "absent.json")
    with pytest.raises(SceneError, match="not a regular file"):
        load_scene_file(tmp_path)
    import lgnn.scene.schema

    big = tmp_path / "big.json"
    big.write_text(" " * 2048)
    monkeypatch.setattr(lgnn.scene.schema, "MAX_SCENE_FILE_BYTES", 1024)  # stands in for a 2 GB file
    with pytest.raises(SceneError, match="larger than"):
        load_scene_file(big)


def test_unknown_scene_name():
    with pytest.raises(SceneError, match="unknown scene 'chain5'"):
        get_scene("chain5")


def test_paper_scene_conventions():
    """SPEC: unit-link chains have I = 1/12; T1-T3 links m = 1, I = l^4/12; varied chain I_k l_k^4."""
    chain = get_scene("chain8")
    np.testing.assert_allclose(chain.inertias, 1 / 12)
    np.testing.assert_allclose(chain.lengths, 1.0)
    assert chain.pinned == (0,)
    np.testing.assert_array_equal(chain.nodes[0], 0.0)
    t1 = get_scene("T1")
    np.testing.assert_allclose(t1.inertias, t1.lengths**4 / 12)
    np.testing.assert_allclose(t1.masses, 1.0)
    assert t1.link_types.count("rod") == 6
    varied = get_scene("chain4-varied")
    np.testing.assert_allclose(varied.inertias, np.array([1.21233911, 1.18340451, 1.52475643, 1.29122914]) * varied.lengths**4)
    assert get_scene("chain4-drag").drag == 0.01
    # built-ins are deterministic
    np.testing.assert_array_equal(get_scene("chain16").nodes, get_scene("chain16").nodes)


def test_scenes_compare_and_hash_by_content():
    """Caches keyed on a scene key on what it holds: the same scene built twice is one
    key; any change to its structure, parameters or initial state is another."""
    a, b = get_scene("chain4"), scene_from_dict(scene_to_dict(get_scene("chain4")))
    assert a is not b and a == b and hash(a) == hash(b) and len({a, b}) == 1
    heavier = a.replace(masses=a.masses * 1.001)
    moved = a.replace(velocities=a.velocities + 1e-12)
    renamed = a.replace(name="other")
    assert len({a, heavier, moved, renamed}) == 4
    assert a != "chain4"


def test_every_catalogue_entry_has_its_dimension_an_origin_and_a_policy_that_fits():
    """One dimension tag matching the scene, one origin tag, and the chain sampler only
    on a pinned chain (the only scenes it can start)."""
    from lgnn.scene import CHAIN_SAMPLER, is_pinned_chain
    from lgnn.scene.catalogue import DIMENSION_TAGS

    for name, entry in CATALOGUE.items():
        scene = entry.build()
        assert scene.name == name
        assert [tag for tag in entry.tags if tag in DIMENSION_TAGS.values()] == [DIMENSION_TAGS[scene.dim]], name
        assert len([tag for tag in entry.tags if tag in ("paper", "hard", "transfer", "imported", "papers")]) == 1, name
        assert entry.initial_states != CHAIN_SAMPLER or is_pinned_chain(scene), name


def test_varied_chains_follow_their_stated_rule():
    """`varied_chain(n, seed)`: lengths, masses and paper inertias within the ranges of the
    paper's varied 4-link chain, physical inertia `I l^4`, the same scene for the same
    seed and another for another; the built-ins are `varied_chain(n, seed=n)`."""
    from lgnn.scene import chain4_varied, get_scene, varied_chain
    from lgnn.scene.catalogue import VARIED_LENGTHS, VARIED_MASSES, VARIED_PAPER_INERTIAS

    for n, dim in itertools.product((8, 16, 100), (2, 3)):
        scene = get_scene(f"chain{n}{'-3d' if dim == 3 else ''}-varied")
        assert scene == varied_chain(n, n, dim=dim) and scene.n_links == n and scene.pinned == (0,) and scene.dim == dim
        paper_inertias = scene.inertias / scene.lengths**4
        for values, listed in ((scene.lengths, VARIED_LENGTHS), (scene.masses, VARIED_MASSES), (paper_inertias, VARIED_PAPER_INERTIAS)):
            assert min(listed) <= values.min() and values.max() <= max(listed)
            assert np.ptp(values) > 0.5 * np.ptp(listed)  # spread over the range, not one value
    # A dimension draws the same links; only the start differs (each dimension's sampler).
    flat, spatial = varied_chain(16, 16), varied_chain(16, 16, dim=3)
    for field in ("lengths", "masses", "inertias"):
        np.testing.assert_array_equal(getattr(flat, field), getattr(spatial, field))
    assert varied_chain(8, 3) == varied_chain(8, 3) and varied_chain(8, 3) != varied_chain(8, 4)
    with pytest.raises(SceneError, match="at least one link"):
        varied_chain(0, 1)
    with pytest.raises(SceneError, match="dim must be 2 or 3, got 4"):
        varied_chain(4, 1, dim=4)
    with pytest.raises(SceneError, match="dim must be 2 or 3, got True"):
        chain4_varied(dim=True)


def test_the_3d_varied_chain_is_the_papers_varied_links_started_by_the_3d_sampler():
    """`chain4-3d-varied`: the links of `chain4-varied`, each link's length its nodes'
    distance, started on its constraints (lengths stationary) by the 3D chain sampler."""
    from lgnn.scene import get_scene

    flat, spatial = get_scene("chain4-varied"), get_scene("chain4-3d-varied")
    assert spatial.dim == 3 and spatial.pinned == (0,)
    for field in ("lengths", "masses", "inertias"):
        np.testing.assert_array_equal(getattr(flat, field), getattr(spatial, field))
    steps = np.diff(spatial.nodes, axis=0)
    np.testing.assert_allclose(np.linalg.norm(steps, axis=1), spatial.lengths, rtol=1e-12)
    np.testing.assert_allclose(np.sum(steps * np.diff(spatial.velocities, axis=0), axis=1), 0.0, atol=1e-12)
    assert np.abs(spatial.velocities).max() > 0.1 and np.abs(spatial.nodes[:, 2]).max() > 0.1  # turning, off the plane


def test_scene_names_select_by_tag_and_a_bad_tag_is_one_line():
    from lgnn.scene import scene_names

    assert scene_names("paper") == ("chain4", "chain8", "chain16", "chain100", "chain4-varied", "chain4-drag", "T1", "T2", "T3")
    assert "T2-slack" in scene_names("planar", "hard") and "T2-slack" not in scene_names("mjcf")
    assert set(scene_names("transfer")) == set(scene_names("3d")) - set(scene_names("imported")) | {"chain8-varied", "chain16-varied", "chain100-varied"}
    assert scene_names("3d", "imported") == ("rope-capsules-3d",)
    assert {"chain4-3d-varied", "chain100-3d-varied"} <= set(scene_names("3d", "transfer")) - set(scene_names("mjcf"))
    with pytest.raises(SceneError, match="unknown scene tag 'spatial'"):
        scene_names("spatial")


def test_a_file_with_a_builtins_content_is_that_entry_and_a_reused_name_is_not():
    """`catalogue_entry` compares content, so a user's file reusing a name is a scene of its own."""
    from lgnn.scene import catalogue_entry

    t1 = get_scene("T1")
    assert catalogue_entry(scene_from_dict(scene_to_dict(t1))) is CATALOGUE["T1"]
    assert catalogue_entry(get_scene("chain8").replace(name="T1")) is None


def test_checking_a_scene_name_builds_no_catalogue_scene(monkeypatch, tmp_path):
    """`check_scene_name` (what a profile's names are checked with at import): a
    catalogue name passes without its builder running, a file is loaded, an unknown
    name or a broken file is a `SceneError`."""
    import dataclasses

    from lgnn.scene import check_scene_name

    def unbuildable():
        raise AssertionError("built")

    monkeypatch.setitem(CATALOGUE, "chain4", dataclasses.replace(CATALOGUE["chain4"], build=unbuildable))
    check_scene_name("chain4")
    path = tmp_path / "mine.json"
    path.write_text(scene_to_json(dataclasses.replace(get_scene("chain8"), name="mine")))
    check_scene_name(str(path))
    with pytest.raises(SceneError, match="unknown scene 'chain5'"):
        check_scene_name("chain5")
    path.write_text("{")
    with pytest.raises(SceneError):
        check_scene_name(str(path))


def damped():
    """`valid()` with its two joints damped (the pin's and the elbow's)."""
    return {**valid(), "dampers": [{"links": [0], "damping": 0.1}, {"links": [1, 0], "damping": 0.05}]}


def test_dampers_load_and_round_trip_and_change_the_content_key():
    scene = scene_from_dict(damped())
    assert scene.dampers == ((0, -1, 0.1), (1, 0, 0.05))
    again = scene_from_dict(json.loads(scene_to_json(scene)))
    assert again.dampers == scene.dampers and again == scene
    undamped = scene_from_dict(valid())
    assert undamped.dampers == () and "dampers" not in scene_to_dict(undamped)
    assert undamped.content_key != scene.content_key and undamped != scene


def _refused_in_one_line(data: dict, words: list[str]) -> None:
    """`scene_from_dict(data)` raises `SceneError` in one line holding every one of `words`."""
    with pytest.raises(SceneError) as info:
        scene_from_dict(data)
    assert "\n" not in str(info.value)
    for word in words:
        assert word in str(info.value), str(info.value)


@pytest.mark.parametrize(
    ("dampers", "words"),
    [
        ({"links": [0]}, ["dampers", "expected a list"]),
        ([{"links": [0], "damping": 0.1, "axis": 1}], ["dampers[0]", "expected {"]),
        ([{"links": [0, 1, 2], "damping": 0.1}], ["dampers[0].links", "expected [e, p] or [e]"]),
        ([{"links": [5], "damping": 0.1}], ["dampers[0].links", "link indices 0..1"]),
        ([{"links": [True], "damping": 0.1}], ["dampers[0].links", "link indices"]),
        ([{"links": [1, 1], "damping": 0.1}], ["dampers[0].links", "link 1 twice"]),
        ([{"links": [1], "damping": 0.1}], ["dampers[0].links", "link 1 has no pinned end"]),
        ([{"links": [0, 1], "damping": 0.1}, {"links": [1, 0], "damping": 0.2}], ["dampers[1].links", "already have a damper"]),
        ([{"links": [0], "damping": -0.1}], ["dampers[0].damping", "must be >= 0"]),
        ([{"links": [0], "damping": "a"}], ["dampers[0].damping"]),
    ],
)
def test_every_bad_damper_is_one_clear_line(dampers, words):
    _refused_in_one_line({**valid(), "dampers": dampers}, words)


def test_dampers_are_refused_in_3d():
    """In 3D a joint's damping would also act about a rod's own axis, which a node
    description has no spin about."""
    with pytest.raises(SceneError, match="planar scenes only"):
        scene_from_dict({**valid3d(), "dampers": [{"links": [0], "damping": 0.1}]})


def test_links_sharing_no_node_cannot_share_a_damper():
    data = valid()
    data["nodes"].append([2.6, -0.8])
    data["velocities"].append([0.8, 1.6])
    data["links"].append({"nodes": [2, 3], "mass": 1.0, "inertia": 0.1})
    with pytest.raises(SceneError, match="share no node"):
        scene_from_dict({**data, "dampers": [{"links": [0, 2], "damping": 0.1}]})


def carted():
    """`valid()` with node 0 a 2 kg cart sliding along x (unpinned) and a bob at node 2."""
    data = valid()
    data["pinned"] = []
    data["velocities"] = [[0.3, 0.0], [1.1, 0.6], [1.1, 1.6]]
    return {**data, "point_masses": [{"node": 0, "mass": 2.0}, {"node": 2, "mass": 0.5}], "rails": [{"node": 0, "axis": 0, "damping": 0.1}]}


def test_point_masses_and_rails_load_round_trip_and_fix_coordinates():
    scene = scene_from_dict(carted())
    assert scene.point_masses == ((0, 2.0), (2, 0.5)) and scene.rails == ((0, 0, 0.1),)
    np.testing.assert_array_equal(scene.fixed_mask, [[False, True], [False, False], [False, False]])
    np.testing.assert_array_equal(scene.node_mass_array, [2.0, 0.0, 0.5])
    again = scene_from_dict(json.loads(scene_to_json(scene)))
    assert (again.point_masses, again.rails) == (scene.point_masses, scene.rails) and again == scene
    assert scene_from_dict({**carted(), "rails": []}).content_key != scene.content_key


@pytest.mark.parametrize(
    ("changes", "words"),
    [
        ({"point_masses": {"node": 0}}, ["point_masses", "expected a list"]),
        ({"point_masses": [{"node": 0}]}, ["point_masses[0]", "expected {"]),
        ({"point_masses": [{"node": 7, "mass": 1.0}]}, ["point_masses[0].node", "out of range"]),
        ({"point_masses": [{"node": 0, "mass": 0.0}]}, ["point_masses[0].mass", "must be > 0"]),
        ({"point_masses": [{"node": 0, "mass": 1.0}, {"node": 0, "mass": 2.0}]}, ["point_masses[1].node", "already has a point mass"]),
        ({"rails": [{"node": 0}]}, ["rails[0]", "expected {"]),
        ({"rails": [{"node": 0, "axis": 2}]}, ["rails[0].axis", "scene axis 0..1"]),
        ({"rails": [{"node": 0, "axis": True}]}, ["rails[0].axis"]),
        ({"rails": [{"node": 0, "axis": 0}, {"node": 0, "axis": 1}]}, ["rails[1].node", "already has a rail"]),
        ({"rails": [{"node": 0, "axis": 0, "damping": -1}]}, ["rails[0].damping", "must be >= 0"]),
        ({"pinned": [0], "velocities": [[0, 0], [0.8, 0.6], [0.8, 1.6]]}, ["rails[0].node", "node 0 is pinned"]),
        ({"rails": [{"node": 0, "axis": 1}]}, ["velocities[0]", "slides along axis 1 only"]),
    ],
)
def test_every_bad_point_mass_and_rail_is_one_clear_line(changes, words):
    _refused_in_one_line({**carted(), **changes}, words)


def test_a_node_with_only_a_point_mass_is_a_body():
    """A free node of no link is refused for having no mass, unless it has a point mass."""
    data = valid()
    data["nodes"].append([3.0, 0.0])
    data["velocities"].append([0.0, 0.0])
    with pytest.raises(SceneError, match="has no mass"):
        scene_from_dict(data)
    assert scene_from_dict({**data, "point_masses": [{"node": 3, "mass": 1.0}]}).n_nodes == 4


def test_limits_load_round_trip_and_are_checked():
    from lgnn.scene import JointLimit

    scene = scene_from_dict({**carted(), "limits": [{"links": [0], "range": [-1.0, 1.0]}, {"links": [1, 0], "range": [-0.5, 0.5]},
                                                    {"node": 0, "range": [-2.0, 2.0]}]})
    assert scene.limits == (JointLimit((0,), -1, -1.0, 1.0), JointLimit((1, 0), -1, -0.5, 0.5), JointLimit((), 0, -2.0, 2.0))
    again = scene_from_dict(json.loads(scene_to_json(scene)))
    assert again.limits == scene.limits and again == scene
    assert scene_from_dict(carted()).content_key != scene.content_key


@pytest.mark.parametrize(
    ("limits", "words"),
    [
        ({"links": [0]}, ["limits", "expected a list"]),
        ([{"links": [0]}], ["limits[0]", "expected {"]),
        ([{"links": [0], "range": [1.0]}], ["limits[0].range", "expected [low, high]"]),
        ([{"links": [0], "range": [1.0, -1.0]}], ["limits[0].range", "low must be below high"]),
        ([{"links": [0], "range": [0.0, "x"]}], ["limits[0].range", "expected a number"]),
        ([{"node": 2, "range": [0.0, 1.0]}], ["limits[0].node", "the node of a rail ([0])"]),
        ([{"links": [3], "range": [0.0, 1.0]}], ["limits[0].links", "link indices 0..1"]),
        ([{"links": [1], "range": [0.0, 1.0]}], ["limits[0].links", "link 1 has no pinned end and no end on a rail"]),
        ([{"links": [0, 0], "range": [0.0, 1.0]}], ["limits[0].links", "link 0 twice"]),
        ([{"links": [0], "range": [0.0, 1.0]}, {"links": [0], "range": [0.0, 2.0]}], ["limits[1]", "a second limit"]),
    ],
)
def test_every_bad_limit_is_one_clear_line(limits, words):
    _refused_in_one_line({**carted(), "limits": limits}, words)


def test_gravity_as_a_vector_loads_and_round_trips():
    scene = scene_from_dict({**valid(), "gravity": [0.5, -9.0]})
    assert float(scene.gravity) == 9.0 and scene.lateral_gravity == (0.5,)
    np.testing.assert_array_equal(scene.gravity_vector, [0.5, -9.0])
    assert scene_from_dict(json.loads(scene_to_json(scene))) == scene
    # A vector along -y is the number: the same scene.
    assert scene_from_dict({**valid(), "gravity": [0.0, -9.81]}) == scene_from_dict(valid())
    spatial = scene_from_dict({**valid3d(), "gravity": [0.0, -9.0, 1.5]})
    np.testing.assert_array_equal(spatial.gravity_vector, [0.0, -9.0, 1.5])
    for bad, words in (([1.0, 2.0, 3.0], "a vector of 2 coordinates"), ([1.0, "x"], "gravity[1]"), ([], "a vector of 2")):
        with pytest.raises(SceneError, match=re.escape(words)):
            scene_from_dict({**valid(), "gravity": bad})


def test_a_scene_dissipates_where_drag_a_damper_or_a_damped_rail_takes_energy_out():
    from lgnn.scene import get_scene

    assert not get_scene("chain4").dissipates and get_scene("chain4-drag").dissipates
    assert get_scene("cartpole").dissipates and get_scene("acrobot").dissipates
    undamped = scene_from_dict({**carted(), "rails": [{"node": 0, "axis": 0}]})
    assert not undamped.dissipates and scene_from_dict(carted()).dissipates
    assert not scene_from_dict({**valid(), "dampers": [{"links": [0], "damping": 0.0}]}).dissipates
