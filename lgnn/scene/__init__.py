"""Scenes: the immutable description of a structure, its JSON schema, and the catalogue.

- `schema`: `Scene` (a frozen pytree), `State`, JSON reading, writing and validation;
- `catalogue`: the one catalogue of scenes (`CATALOGUE`: the paper's scenes, the hard
  cases and the 3D scenes, each with its tags and initial-state policy;
  `scene_names(*tags)`, `initial_state_policy`), and the initial-condition samplers.

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
    CATALOGUE,
    CHAIN_SAMPLER,
    INITIAL_STATE_POLICIES,
    OWN_STATE,
    PROJECTED,
    TAGS,
    CatalogueEntry,
    catalogue_entry,
    chain,
    chain4_drag,
    chain4_varied,
    varied_chain,
    chain_positions,
    get_scene,
    initial_state_policy,
    double_pinned_chain,
    embedded_in_3d,
    folded_chain,
    free_triangle,
    paper_structure,
    pendulum,
    pinned_triangle,
    sample_initial_states,
    scene_names,
    spatial_chain,
    spatial_chain_state,
    spatial_net,
    spatial_rope,
    spatial_tensegrity,
    taut_chain,
)

__all__ = [
    "CATALOGUE",
    "CHAIN_SAMPLER",
    "CatalogueEntry",
    "INITIAL_STATE_POLICIES",
    "OWN_STATE",
    "PROJECTED",
    "TAGS",
    "Scene",
    "State",
    "chain",
    "chain4_drag",
    "chain4_varied",
    "varied_chain",
    "chain_positions",
    "check_scene",
    "double_pinned_chain",
    "embedded_in_3d",
    "folded_chain",
    "free_triangle",
    "catalogue_entry",
    "get_scene",
    "initial_state_policy",
    "is_pinned_chain",
    "load_scene_file",
    "paper_structure",
    "pendulum",
    "pinned_triangle",
    "sample_initial_states",
    "scene_names",
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
