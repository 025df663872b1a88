"""Measurements behind issue 13 item 3 (scale-free solves); prints, writes nothing to results/.

    python tools/scale_check.py truth OUT.npz       0.1 s ground truth of every built-in (default settings)
    python tools/scale_check.py compare A.npz B.npz max change of q and qd per scene
    python tools/scale_check.py lgnn-t3 [SECONDS]   the committed LGNN checkpoint on T3 from the scene's state

For a before/after comparison run `truth` with the older `lgnn` first on the path
(`PYTHONPATH=<old worktree>`). Run from the repository root.
"""

import sys

import lgnn
from lgnn.provenance import environment


def truth(path):
    import numpy as np

    from lgnn.engines.base import SimulationConfig
    from lgnn.engines.lagrangian import simulate
    from lgnn.scene import get_scene, scene_names

    arrays = {}
    for name in scene_names("paper"):
        trajectory = simulate(get_scene(name), SimulationConfig(duration=0.1))
        arrays[f"{name}/q"], arrays[f"{name}/qd"] = trajectory.q, trajectory.qd
    np.savez(path, **arrays)
    print(environment())


def compare(first, second):
    import numpy as np

    a, b = np.load(first), np.load(second)
    for key in sorted({key.split("/")[0] for key in a.files}):
        q, qd = (np.abs(a[f"{key}/{part}"] - b[f"{key}/{part}"]).max() for part in ("q", "qd"))
        print(f"{key:14s} max |dq| {q:.2e}  max |dqd| {qd:.2e}  (max |q - q0| {np.abs(a[key + '/q'] - a[key + '/q'][0]).max():.2e})")


def lgnn_t3(seconds=1.0):
    from lgnn.engines.base import SimulationConfig
    from lgnn.engines.lagrangian import simulate
    from lgnn.errors import SimulationError
    from lgnn.learn import models
    from lgnn.learn.checkpoints import load_model
    from lgnn.metrics import relative_error
    from lgnn.scene import get_scene

    scene, settings = get_scene("T3"), SimulationConfig(duration=float(seconds))
    config, params = load_model("results/benchmark/checkpoints/lgnn-chain4-s0.npz")
    try:
        predicted = models.rollout(config, params, scene, settings)
        print(f"ran {predicted.t[-1]:g} s")
    except SimulationError as err:
        print(f"diverged: {err}")
        predicted = err.trajectory
    reference = simulate(scene, settings)
    frames = len(predicted.t)
    error = relative_error(predicted.q, reference.q[:frames], 2)[1:]
    print(f"frames {frames}: rollout error (mean over frames after the first) {error.mean():.3e}, last frame {error[-1]:.3e}")
    print(environment())


if __name__ == "__main__":
    lgnn.configure()
    command, *args = sys.argv[1:]
    {"truth": truth, "compare": compare, "lgnn-t3": lgnn_t3}[command](*args)
