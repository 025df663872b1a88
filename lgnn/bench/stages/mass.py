"""Mass-matrix stage: the learned LGNN mass matrix `d2L/dqd2` against the true one at a
state of a ground-truth trajectory (`MassSettings.scenes`: chain16 and T1 with the LGNN
trained on chain4, chain16-3d with the one trained on chain4-3d; quick: chain8). The
true one is the rods' (`lgnn.physics`): in 3D a thin rod has no spin about its own
axis, so only motion across the rod turns it.

A scene's record depends on the profile's `MassSettings`, the scene's ground-truth key
(`lgnn.bench.stages.truth.truth_key`) and the checkpoint's content (`mass_key`);
`load_mass` gives the report the records that match.
"""

from __future__ import annotations

from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

from lgnn import physics, records
from lgnn.bench import store
from lgnn.bench.grid import TrainingJob
from lgnn.bench.profiles import Profile, lgnn_job
from lgnn.records import settings_key
from lgnn.bench.stages.evaluate import load_truth, truth_key
from lgnn.bench.store import log
from lgnn.errors import ConfigError
from lgnn.learn import models
from lgnn.learn.checkpoints import content_digest, load_model
from lgnn.scene import get_scene


def mass_key(profile: Profile, scene_name: str, checkpoint: Path) -> str:
    """Settings a mass-matrix record depends on (module docstring)."""
    return records.digest({"mass": settings_key(profile.mass), "truth": truth_key(profile, scene_name), "checkpoint": content_digest(checkpoint)})


def mass_matrices(profile: Profile, scene_name: str, out: Path, job: TrainingJob | None = None) -> Path:
    """The true and learned (`lgnn_job`: the LGNN of the scene's dimension) mass
    matrices over the free node coordinates at a ground-truth state (IC 0 at half the
    rollout, from the scene's evaluation record), and their percentage errors
    `100 ||M_hat - M||_F / ||M||_F`: over all free coordinates, and on the constraint
    tangent space (`P M P`, P the orthogonal projector onto `A v = 0`: the part of M the
    dynamics see). Accelerations determine a Lagrangian only up to an overall factor
    (`c L` has the same Euler-Lagrange equations), so both are also given for
    `c M_hat`, `c` the least-squares factor on the tangent space (recorded as `scale`)."""
    job = job or lgnn_job(profile, scene_name)
    layout = store.layout(profile, out)
    checkpoint = layout.found(layout.checkpoint(job))
    scene = get_scene(scene_name)
    path, key = layout.mass_record(scene_name), mass_key(profile, scene_name, checkpoint)
    if layout.load(path, key) is not None:
        return path
    truth = load_truth(profile, scene_name, out)
    if truth is None:
        raise ConfigError(f"mass matrix on {scene_name}: run its evaluation stage first (the state comes from its ground truth)")
    q, qd = (jnp.asarray(a) for a in truth[0]["mid_state"])
    model, params = load_model(checkpoint)
    free = np.setdiff1d(np.arange(scene.n_nodes), scene.pinned)
    coords = (free[:, None] * scene.dim + np.arange(scene.dim)).reshape(-1)
    true_m = np.asarray(jax.jit(physics.mass_matrix_fn(physics.lagrangian_fn(scene)))(q, qd))[np.ix_(coords, coords)]
    learned_m = np.asarray(jax.jit(models.mass_matrix_fn(model, params, scene))(q, qd))[np.ix_(coords, coords)]
    constraints = physics.prepare(scene).constraints
    jac = np.asarray(constraints.jacobian(constraints.restrict(q)))
    projector = np.eye(len(coords)) - jac.T @ np.linalg.pinv(jac @ jac.T) @ jac  # analysis only, not dynamics
    tangent_true, tangent_learned = projector @ true_m @ projector, projector @ learned_m @ projector
    scale = float(np.sum(tangent_learned * tangent_true) / np.sum(tangent_learned**2))
    percent = lambda a, b: float(100 * np.linalg.norm(a - b) / np.linalg.norm(b))  # noqa: E731
    meta = dict(scene=scene_name, job=job.name, percent_error=percent(learned_m, true_m),
                tangent_percent_error=percent(tangent_learned, tangent_true), scale=scale,
                scaled_percent_error=percent(scale * learned_m, true_m),
                scaled_tangent_percent_error=percent(scale * tangent_learned, tangent_true))
    store.save(path, key, {"true": true_m, "learned": learned_m}, meta)
    log(f"mass matrix {scene_name}: learned within {meta['percent_error']:.2g}% (tangent space {meta['tangent_percent_error']:.2g}%); "
        f"times {scale:.3g}: {meta['scaled_percent_error']:.2g}% (tangent {meta['scaled_tangent_percent_error']:.2g}%)")
    return path


def load_mass(profile: Profile, out: Path) -> list[tuple[dict, dict]]:
    """`(arrays, meta)` of every mass-matrix record that matches the profile and the
    LGNN checkpoint it analyses."""
    found, layout = [], store.layout(profile, out)
    for scene in profile.mass.scenes:
        checkpoint = layout.found(layout.checkpoint(lgnn_job(profile, scene)))
        if checkpoint.exists():
            found.append(layout.load(layout.mass_record(scene), mass_key(profile, scene, checkpoint)))
    return [record for record in found if record is not None]
