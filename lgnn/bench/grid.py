"""The benchmark's grid, declared once.

- `GRID`: LGNN, GNS, LGN and CLNN trained on `TRAINING_SCENE` (chain4; LGNN also on
  `chain4-varied` and `chain4-drag`, as the paper's appendix), each with the scenes it
  is evaluated on (CLNN, tied to its system size, on chain4 only); the same in 3D,
  trained on `SPATIAL_TRAINING_SCENE`; and the model zoo (the strong GNS, CGNODE, CHGN
  and CHNN) in both. The grid's third axis is the profile's training
  seeds.
- Its tracks (the paper's scenes, varied draws), training jobs and evaluation pairs,
  and the error figures' groups; the functions that read them off a profile
  (`training_jobs`, `evaluation_pairs`, `train_config`, ...). The profiles themselves
  and their settings classes are `lgnn.bench.profiles`'.
"""

from __future__ import annotations

import dataclasses

from lgnn.errors import ConfigError, check_number

# The scene every model of the main grid is trained on.
TRAINING_SCENE = "chain4"
# The scenes the chain4-trained models are evaluated on, in table order. T2 and T3 as
# the paper gives them start self-stressed, where the reference does not converge in dt
# (results/convergence.md): no model number on them could rank models, so the grid
# leaves them out (the report says why); T2-slack and T3-slack, their ropes 0.1 %
# slack, converge at RK4's order from dt 1e-3 (the same file) and stand in for them.
TRANSFER_SCENES = ("chain4", "chain8", "chain16", "chain100", "T1", "T2-slack", "T3-slack")
# The spatial grid (issue 16): models trained on the 3D 4-link chain, evaluated zero-shot
# on the 3D chains, a rope of 30 short links, a net hung from two corners and three
# rods tied by bowed rope chains (`lgnn.scene`'s spatial catalogue), in table order.
SPATIAL_TRAINING_SCENE = "chain4-3d"
SPATIAL_TRANSFER_SCENES = ("chain4-3d", "chain8-3d", "chain16-3d", "chain100-3d", "net4x4-3d", "rope-3d", "tensegrity-3d")
# The main training scene of each dimension's grid (a scene's `dim`): the models a
# scene's snapshots and mass matrix are read from.
TRAINING_SCENES = {2: TRAINING_SCENE, 3: SPATIAL_TRAINING_SCENE}
# The training scene a job of predictions made outside lgnn stands on: they have no
# training scene, checkpoint or seeds (`external_pair`); tables name them `MODEL (external)`.
EXTERNAL = "external"
def check_numbers(group: str, settings, low: float = 0.0, **names: bool) -> None:
    """`ConfigError` naming `group.field` for each named field (or each item of a tuple
    field) of `settings` that is not a finite number above `low` (`True`: a whole
    number >= 1 instead)."""
    for name, whole in names.items():
        value = getattr(settings, name)
        for item in value if isinstance(value, tuple) else (value,):
            check_number(f"setting '{group}.{name}'", item, above=low, whole=whole)


# ---------------------------------------------------------------------------------
# The grid
# ---------------------------------------------------------------------------------


@dataclasses.dataclass(frozen=True)
class GridEntry:
    """A model trained on `train_scene`, evaluated on `eval_scenes`, with the profile's
    seeds and training budget unless the entry gives its own."""

    model: str
    train_scene: str
    eval_scenes: tuple[str, ...]
    # Also evaluated without projecting its rollouts onto the constraints (GNS: its
    # accelerations know no constraints; the projected row hides that, issue 13).
    unprojected: bool = False
    # This entry's training seeds (None: the profile's `seeds`).
    seeds: tuple[int, ...] | None = None
    # This entry's budget: epochs and minutes (None: the profile's `training.train`). Only
    # where its training stops differs: its optimisation (rate, warm-up, batch) is the
    # profile's, so its checkpoint is trained as the profile trains every model.
    epochs: int | None = None
    minutes: float | None = None
    # Trained on this many varied draws of its training chain (`DataConfig.varied_draws`),
    # with link features where the model takes them: the transfer track. 0: the scene alone.
    varied_draws: int = 0

    @property
    def track(self) -> str:
        """The leaderboard the entry ranks on (`TRACKS`)."""
        return track_of(self.varied_draws)

    def __post_init__(self):
        if isinstance(self.varied_draws, bool) or not isinstance(self.varied_draws, int) or self.varied_draws < 0:
            raise ConfigError(f"grid entry {self.model}: 'varied_draws' must be a whole number >= 0, got {self.varied_draws!r}")
        if self.seeds is not None and not self.seeds:
            raise ConfigError(f"grid entry {self.model}: 'seeds' must name at least one training seed")
        check_numbers(f"grid entry {self.model}", self, **{name: name == "epochs" for name in ("epochs", "minutes")
                                                            if getattr(self, name) is not None})


# The leaderboards: the paper's track (models trained on one chain, `TRAINING_SCENES`)
# and the transfer track (models trained on varied draws of a chain, evaluated on varied
# chains of other lengths and on the trusses, where only unseen link properties separate
# models whose prior holds the rod's energy).
PAPER_TRACK = "paper"
TRANSFER_TRACK = "transfer"
TRACKS = (PAPER_TRACK, TRANSFER_TRACK)


def track_of(varied_draws: int) -> str:
    """The track of a model trained on that many varied draws (0: on its scene alone)."""
    return TRANSFER_TRACK if varied_draws else PAPER_TRACK


def trained_on(scene: str, varied_draws: int = 0) -> str:
    """What a model trained on, as tables name it: the scene (`chain4-varied`), or
    varied draws of it (`chain4-varied, 5 draws`)."""
    return f"{scene}, {varied_draws} draws" if varied_draws else scene


# The transfer track: every graph model trained on TRANSFER_DRAWS draws of varied 4-link
# chains (`lgnn.scene.varied_chain`; 20 trajectories of the full profile's 100 each),
# evaluated zero-shot on the built-in varied chains and the trusses. Named by the
# paper's varied chain, the draws' length and rule.
TRANSFER_TRAINING_SCENE = "chain4-varied"
TRANSFER_DRAWS = 5
TRANSFER_TRACK_SCENES = ("chain4-varied", "chain8-varied", "chain16-varied", "chain100-varied", "T1", "T2-slack", "T3-slack")
# In 3D: draws of varied 4-link chains in 3D (the same rule, the 3D chain sampler),
# evaluated on the built-in varied 3D chains and the 3D grid's net, rope and tensegrity.
SPATIAL_TRANSFER_TRAINING_SCENE = "chain4-3d-varied"
SPATIAL_TRANSFER_TRACK_SCENES = ("chain4-3d-varied", "chain8-3d-varied", "chain16-3d-varied", "chain100-3d-varied", "net4x4-3d", "rope-3d",
                                 "tensegrity-3d")

# The LGNN variants (`lgnn.learn.models`): the per-edge one, the paper's equations with
# 1 and 2 message-passing layers, the authors' notebook; the report's default LGNN is
# the best of them on the validation set (`lgnn.bench.stages.train.default_lgnn`).
LGNN_VARIANTS = ("lgnn", "lgnn-mp1", "lgnn-mp2", "lgnn-notebook")

# The model zoo (`docs/models.md`): the strong GNS (the public GNS-10-128 recipe), the
# constrained graph neural ODE, the constrained Hamiltonian graph network, and CHNN (tied
# to its system's size, as CLNN). Every entry of the grid trains by the one protocol,
# the profile's epoch budget and plateau rule: no wall-clock cap, which would make a row
# depend on the machine and on who shared it (`tools/budget_rule.py` reads from the
# committed checkpoints that no smaller budget keeps the ranking: results/training_budget.md).
ZOO_MODELS = ("gns-10-128", "cgnode", "chgn", "chnn")
# The zoo's graph models (CHNN is tied to its system's size): the transfer track's.
TRANSFER_ZOO = ("gns-10-128", "cgnode", "chgn")
# Each zoo model in both dimensions, model by model (the benchmark's parts start in
# this order, so on a host of several GPUs the large ones land on different GPUs).
ZOO = tuple(GridEntry(model, train_scene, eval_scenes if model != "chnn" else (train_scene,), unprojected=model == "gns-10-128")
            for model in ZOO_MODELS
            for train_scene, eval_scenes in ((TRAINING_SCENE, TRANSFER_SCENES), (SPATIAL_TRAINING_SCENE, SPATIAL_TRANSFER_SCENES)))


GRID = (
    *(GridEntry(variant, TRAINING_SCENE, TRANSFER_SCENES) for variant in LGNN_VARIANTS),
    GridEntry("gns", TRAINING_SCENE, TRANSFER_SCENES, unprojected=True),
    GridEntry("lgn", TRAINING_SCENE, TRANSFER_SCENES),
    GridEntry("clnn", TRAINING_SCENE, (TRAINING_SCENE,)),
    GridEntry("lgnn", "chain4-varied", ("chain4-varied",)),
    GridEntry("lgnn", "chain4-drag", ("chain4-drag",)),
    # In 3D: the per-edge LGNN and the planar grid's best variant (the authors'
    # notebook, results/README.md), not all four: each 3D group costs as much again.
    *(GridEntry(variant, SPATIAL_TRAINING_SCENE, SPATIAL_TRANSFER_SCENES) for variant in ("lgnn", "lgnn-notebook")),
    GridEntry("gns", SPATIAL_TRAINING_SCENE, SPATIAL_TRANSFER_SCENES, unprojected=True),
    GridEntry("lgn", SPATIAL_TRAINING_SCENE, SPATIAL_TRANSFER_SCENES),
    GridEntry("clnn", SPATIAL_TRAINING_SCENE, (SPATIAL_TRAINING_SCENE,)),
    *ZOO,
    # The transfer track (a profile's `tracks` selects it).
    *(GridEntry(model, TRANSFER_TRAINING_SCENE, TRANSFER_TRACK_SCENES, varied_draws=TRANSFER_DRAWS)
      for model in (*LGNN_VARIANTS, "gns", "lgn", *TRANSFER_ZOO)),
    # In 3D, the LGNN variants of the paper track's 3D grid (each 3D group costs as much
    # again), the paper's graph baselines and the zoo's graph models.
    *(GridEntry(model, SPATIAL_TRANSFER_TRAINING_SCENE, SPATIAL_TRANSFER_TRACK_SCENES, varied_draws=TRANSFER_DRAWS)
      for model in ("lgnn", "lgnn-notebook", "gns", "lgn", *TRANSFER_ZOO)),
)


@dataclasses.dataclass(frozen=True)
class FigureGroup:
    """An error-against-time figure of the report: its file under `figures/`, the scenes
    drawn side by side (those with curves), what its title says the models trained on
    ("each": the scenes' own), and the track whose models it draws (`TRACKS`)."""

    file: str
    scenes: tuple[str, ...]
    trained_on: str
    track: str = PAPER_TRACK


# The error-against-time figures of the built-in grid: each transfer group a figure,
# the large chains apart (their curves would flatten the small ones' scale). A scene
# of a profile's grid in none of them gets a figure of its own (`error_figures`).
ERROR_FIGURES = (
    FigureGroup("error_vs_time_chain4_8_16.png", ("chain4", "chain8", "chain16"), TRAINING_SCENE),
    FigureGroup("error_vs_time_chain100.png", ("chain100",), TRAINING_SCENE),
    FigureGroup("error_vs_time_T1_T2slack_T3slack.png", ("T1", "T2-slack", "T3-slack"), TRAINING_SCENE),
    FigureGroup("error_vs_time_varied_drag.png", ("chain4-varied", "chain4-drag"), "each"),
    FigureGroup("error_vs_time_chain4_8_16_3d.png", ("chain4-3d", "chain8-3d", "chain16-3d"), SPATIAL_TRAINING_SCENE),
    FigureGroup("error_vs_time_chain100_3d.png", ("chain100-3d",), SPATIAL_TRAINING_SCENE),
    FigureGroup("error_vs_time_net_rope_tensegrity_3d.png", ("net4x4-3d", "rope-3d", "tensegrity-3d"), SPATIAL_TRAINING_SCENE),
    FigureGroup("error_vs_time_transfer_chains.png", TRANSFER_TRACK_SCENES[:4], trained_on(TRANSFER_TRAINING_SCENE, TRANSFER_DRAWS), TRANSFER_TRACK),
    FigureGroup("error_vs_time_transfer_T1_T2slack_T3slack.png", TRANSFER_TRACK_SCENES[4:], trained_on(TRANSFER_TRAINING_SCENE, TRANSFER_DRAWS),
                TRANSFER_TRACK),
    FigureGroup("error_vs_time_transfer_chains_3d.png", SPATIAL_TRANSFER_TRACK_SCENES[:4],
                trained_on(SPATIAL_TRANSFER_TRAINING_SCENE, TRANSFER_DRAWS), TRANSFER_TRACK),
    FigureGroup("error_vs_time_transfer_net_rope_tensegrity_3d.png", SPATIAL_TRANSFER_TRACK_SCENES[4:],
                trained_on(SPATIAL_TRANSFER_TRAINING_SCENE, TRANSFER_DRAWS), TRANSFER_TRACK),
)
# Scenes whose snapshots (learned against MuJoCo) the report draws: a chain and a
# truss in each dimension, and the 3D net.
SNAPSHOT_SCENES = ("chain8", "T1", "chain8-3d", "net4x4-3d", "tensegrity-3d")
# The model whose learned mass matrix and cost against size are measured (`lgnn_job`):
# the per-edge LGNN.
MEASURED_MODEL = LGNN_VARIANTS[0]


@dataclasses.dataclass(frozen=True)
class TrainingJob:
    model: str
    scene: str
    seed: int
    # Trained on this many varied draws of `scene` (`GridEntry.varied_draws`).
    varied_draws: int = 0

    @property
    def group(self) -> str:
        """The job's name but for its seed: the seeds of one group train (and evaluate)
        in one program."""
        return f"{self.model}-{self.scene}" + (f"-draws{self.varied_draws}" if self.varied_draws else "")

    @property
    def name(self) -> str:
        return f"{self.group}-s{self.seed}"

    @property
    def track(self) -> str:
        return track_of(self.varied_draws)

    @property
    def trained_on(self) -> str:
        """What the job trains on, as tables name it (`trained_on`)."""
        return trained_on(self.scene, self.varied_draws)

    @property
    def label(self) -> str:
        """The model as tables name it: `lgnn`, or `lgnn (chain4-varied)` off the main
        training scene, `lgnn (chain4-varied, 5 draws)` on varied draws of it, or
        `my-sim (external)` for predictions made outside lgnn."""
        return self.model if self.scene == TRAINING_SCENE and not self.varied_draws else f"{self.model} ({self.trained_on})"

    @property
    def external(self) -> bool:
        """Predictions made outside lgnn (`external_pair`): no checkpoint, parameters or training."""
        return self.scene == EXTERNAL


@dataclasses.dataclass(frozen=True)
class Pair:
    """One evaluation: a trained job on a scene, its rollouts projected onto the
    constraints after every step (as the ground truth's) unless `projected` is false."""

    job: TrainingJob
    scene: str
    projected: bool = True

    @property
    def label(self) -> str:
        """The row the tables give it: the job's label, `(unprojected)` added."""
        return self.job.label + ("" if self.projected else " (unprojected)")


def external_pair(model: str, scene: str) -> Pair:
    """The pair that tables and records give predictions of `model` made outside lgnn on
    `scene`: a job on no training scene (`EXTERNAL`), seed 0, labelled `MODEL (external)`."""
    return Pair(TrainingJob(model, EXTERNAL, 0), scene)
