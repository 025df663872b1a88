"""Scenes: the immutable description of a structure, its JSON schema, and the catalogue.

- `schema`: `Scene` (a frozen pytree), `State`, JSON reading, writing and validation;
- `catalogue`: the built-in scenes of the paper, the hard cases, and the
  initial-condition sampler.

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
    BuiltinScene,
    chain,
    chain4_drag,
    chain4_varied,
    chain_positions,
    get_scene,
    paper_structure,
    sample_initial_states,
)

__all__ = [
    "BUILTIN_SCENES",
    "BuiltinScene",
    "Scene",
    "State",
    "chain",
    "chain4_drag",
    "chain4_varied",
    "chain_positions",
    "check_scene",
    "get_scene",
    "is_pinned_chain",
    "load_scene_file",
    "paper_structure",
    "sample_initial_states",
    "scene_from_dict",
    "scene_to_dict",
    "scene_to_json",
]
