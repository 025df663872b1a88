"""Scenes: the immutable description of a structure, its JSON schema, and the catalogue.

- `schema`: `Scene` (a frozen pytree), `State`, JSON reading, writing and validation;
- `catalogue`: the one catalogue of scenes: the built-in scenes of the paper
  (`BUILTIN_SCENES`), the hard cases and small physics-test scenes (`HARD_SCENES`),
  the spatial (3D) scenes (`SPATIAL_SCENES`), and the initial-condition samplers.

Everything above this package takes a `Scene`; nothing here imports anything of lgnn
but `lgnn.errors`.
"""

from lgnn.scene.schema import (
    Scene,
    State,
    check_scene,
    is_pinned_chain,
    load_scene_file,
    scene_from_dict,
    scene_to_dict,
    scene_to_json,
)
from lgnn.scene.catalogue import (
    BUILTIN_SCENES,
    HARD_SCENES,
    SPATIAL_SCENES,
    BuiltinScene,
    chain,
    chain4_drag,
    chain4_varied,
    chain_positions,
    get_scene,
    is_catalogue_scene,
    double_pinned_chain,
    embedded_in_3d,
    folded_chain,
    free_triangle,
    paper_structure,
    pendulum,
    pinned_triangle,
    sample_initial_states,
    spatial_chain,
    spatial_chain_state,
    spatial_net,
    spatial_rope,
    spatial_tensegrity,
    taut_chain,
)

__all__ = [
    "BUILTIN_SCENES",
    "BuiltinScene",
    "HARD_SCENES",
    "SPATIAL_SCENES",
    "Scene",
    "State",
    "chain",
    "chain4_drag",
    "chain4_varied",
    "chain_positions",
    "check_scene",
    "double_pinned_chain",
    "embedded_in_3d",
    "folded_chain",
    "free_triangle",
    "get_scene",
    "is_catalogue_scene",
    "is_pinned_chain",
    "load_scene_file",
    "paper_structure",
    "pendulum",
    "pinned_triangle",
    "sample_initial_states",
    "spatial_chain",
    "spatial_chain_state",
    "spatial_net",
    "spatial_rope",
    "spatial_tensegrity",
    "scene_from_dict",
    "scene_to_dict",
    "scene_to_json",
    "taut_chain",
]
