"""The benchmark's `README.md`: its settings, warnings, training table, summary tables per
track and dimension, the mass-matrix and speed sections, provenance and file list, as
text from the records (`lgnn.bench.report.write` writes it)."""

from __future__ import annotations

from pathlib import Path

from lgnn import metrics
from lgnn.bench.grid import PAPER_TRACK, TRACKS, TRAINING_SCENES, TRANSFER_TRACK, TrainingJob
from lgnn.bench.profiles import PROFILES, Profile, evaluation_pairs, evaluation_scenes, model_order, train_config, training_jobs
from lgnn.records import settings_key
from lgnn.bench.report.performance import speed_markdown
from lgnn.bench.stages.evaluate import CURVE_DT, unmatched_base_pairs
from lgnn.bench.stages.train import default_lgnn
from lgnn.bench.report.summary import (
    DIMENSION_NAMES,
    EXACT_NO_DRAG,
    EXTERNAL_MARK,
    REST,
    scene_groups,
    summary_markdown,
    summary_tables,
    track_rows,
    unrankable_scenes,
)
from lgnn.bench.tables import escape_markdown_cell
from lgnn.learn.protocol import stop_reason, training_key
from lgnn.scene import CHAIN_SAMPLER, OWN_STATE, PROJECTED, get_scene, initial_state_policy


def _command(profile: Profile, command: str | None) -> str:
    """What wrote the report: the command given (`lgnn benchmark ...`), else a call of
    `lgnn.bench.run.run` or `report.write` on the profile (the tests' and notebooks' way)."""
    return command or f"lgnn.bench.run.run(load_profile(...)), profile {profile.name!r}"


def _stopped_by(state, config) -> str:
    """Why a run's training ended (`lgnn.learn.protocol.stop_reason`), or that it has not."""
    return stop_reason(state, config) or "not finished: cut off, resumable"


def _training_lines(profile: Profile, out: Path, checkpoints: list) -> list[str]:
    """The training table of `checkpoints` (`stages.train.load_checkpoints`) and each dimension's default LGNN."""
    lines = ["| model | training scene | seed | epochs | minutes | best validation MSE (epoch) | stopped by |", "|---|---|---|---|---|---|---|"]
    for trained in checkpoints:
        job, state = trained.job, trained.state
        lines.append(f"| {job.model} | {job.scene} | {job.seed} | {state.epoch} | {state.elapsed_s / 60:.1f} | {state.best_val:.3g} ({state.best_epoch}) "
                     f"| {_stopped_by(state, train_config(profile, job))} |")
    for dim, training_scene in TRAINING_SCENES.items():
        chosen, scores = default_lgnn(profile, out, training_scene, checkpoints)
        if scores:
            # The planar grid's is "the" default LGNN; another dimension's is named.
            lines += ["", f"Default LGNN{'' if dim == 2 else ' in ' + DIMENSION_NAMES.get(dim, f'{dim}D')} (trained on {training_scene}; lowest geometric mean over seeds of the best "
                      f"validation MSE among the variants with every seed trained): **{chosen}** ({', '.join(f'{v} {s:.3g}' for v, s in scores.items())})."]
    return lines


def _provenance_lines(truths: dict, pairs: list, speed_rows: list[dict], mass_records: list, out: Path) -> list[str]:
    """Which folder (this report's `out`, or the base read in place: `store.Layout.load`),
    machine and commit made each record, grouped (the stages may run apart)."""
    groups: dict[tuple[str, str, str], list[str]] = {}

    def add(meta: dict, label: str) -> None:
        env = meta.get("environment", meta)
        folder = meta.get("folder", str(out))
        groups.setdefault((folder, env.get("device", "unknown"), env.get("commit", "unknown")), []).append(label)

    for scene, (_, meta) in truths.items():
        add(meta, f"ground truth {scene}")
    for pair, (_, meta) in pairs:
        add(meta, f"{pair.label}{'' if pair.job.external else f' s{pair.job.seed}'} on {pair.scene}")
    for scene, device, commit, folder in dict.fromkeys((r["scene"], r["device"], r["commit"], r.get("folder", str(out))) for r in speed_rows):
        add({"device": device, "commit": commit, "folder": folder}, f"speed {scene}")
    for _, meta in mass_records:
        add(meta, f"mass matrix {meta['scene']}")
    lines = ["| folder | machine | commit | records |", "|---|---|---|---|"]
    lines += [f"| `{folder}` | {device} | {commit} | {', '.join(labels)} |" for (folder, device, commit), labels in groups.items()]
    return lines


# Heads a non-full profile's report (and the console, which prints the report).
QUICK_WARNING = ("**Not results.** This profile checks that the pipeline runs: its training budgets are tiny and it has few initial "
                 "conditions, so the ranking of the models means nothing, and so do its timings: a few runs of a short horizon on a "
                 "shared machine, which vary several-fold between benchmark runs (single runs gave a Lagrangian/MuJoCo ratio of 3.05 "
                 "in one, 0.41 in the next; the speed table's spread column shows the runs of this one). "
                 "Numbers: `lgnn benchmark --full`, or the committed `results/`.")


def _cut_off_lines(profile: Profile, checkpoints: list) -> list[str]:
    """A warning naming the checkpoints whose training the protocol's rules (epoch
    budget, plateau) did not end: cut off by a wall-clock cap they were trained under,
    or by an interrupted run. Their rows rank what that training learned, not the
    protocol's; a full run resumes or retrains them. Nothing where every run ended."""
    cut: dict[str, list[TrainingJob]] = {}
    for trained in checkpoints:
        if stop_reason(trained.state, train_config(profile, trained.job)) is None:
            cut.setdefault(trained.job.model, []).append(trained.job)
    if not cut:
        return []
    named = [f"{model} ({'; '.join(dict.fromkeys(j.trained_on for j in jobs))}; {len(jobs)} run{'s' if len(jobs) > 1 else ''})"
             for model, jobs in cut.items()]
    return [f"**Training cut off.** These runs stopped before the training protocol's rules ended them (the epoch budget or "
            f"the plateau rule; the training table says where each stopped): {', '.join(named)}. Their rows rank what that "
            "training learned, not what the protocol's would: `lgnn benchmark --full --stage train` resumes or retrains them.", ""]


def banner(profile: Profile) -> list[str]:
    """The report's opening warning, from what was run, not the profile's name:
    `QUICK_WARNING` unless the evaluation settings and training data are the full
    profile's; with those, the training jobs whose settings differ from the full
    profile's (a smaller budget, or another optimisation), each named: their rows rank
    what that training learned, not the full recipe's. No warning otherwise."""
    full = PROFILES["full"]
    if settings_key(profile.evaluate) != settings_key(full.evaluate) or profile.training.data != full.training.data:
        return [QUICK_WARNING, ""]
    recipe = full.training.train
    short_jobs: dict[tuple[str, str], list[TrainingJob]] = {}
    other = []
    for job in training_jobs(profile):
        config = train_config(profile, job)
        if training_key(config) | {"seed": 0} != training_key(recipe) | {"seed": 0}:
            other.append(job.name)
        elif config.epochs < recipe.epochs or (config.minutes is not None and (recipe.minutes is None or config.minutes < recipe.minutes)):
            budget = f"{config.epochs} epochs" + (f" or {config.minutes:g} minutes" if config.minutes else "")
            short_jobs.setdefault((job.model, budget), []).append(job)
    # One entry per model and budget: its training scenes and seeds.
    short = [f"{model} ({budget}; {'; '.join(dict.fromkeys(j.trained_on for j in jobs))}; "
             f"seed{'s' if len({j.seed for j in jobs}) > 1 else ''} {', '.join(str(s) for s in sorted({j.seed for j in jobs}))})"
             for (model, budget), jobs in short_jobs.items()]
    lines = []
    if short:
        lines.append(f"**Full-profile evaluation, shorter training.** Trained on a smaller budget than the full profile's "
                     f"({recipe.epochs} epochs" + (f" or {recipe.minutes:g} minutes" if recipe.minutes else "") + ", or its plateau rule): "
                     + ", ".join(short) + ". Their rows rank what that budget learned, not what the full recipe would.")
    if other:
        lines.append("**Full-profile evaluation, other training.** Trained with other optimisation settings than the full profile's "
                     "(batch, rate, schedule): " + ", ".join(other) + ".")
    return [line for text in lines for line in (text, "")]


def _unmatched_lines(profile: Profile, out: Path) -> list[str]:
    """One line naming the base folder's evaluations made with other settings than this
    report's (`evaluate.unmatched_base_pairs`): their cells say "not evaluated"."""
    if profile.base is None:
        return []
    unmatched = unmatched_base_pairs(profile, out)
    if not unmatched:
        return []
    return [f"**Not compared:** {len(unmatched)} evaluation(s) of `{profile.base}`'s models were made with other evaluation settings than "
            f"this report's ({', '.join(dict.fromkeys(pair.label for pair in unmatched))}): they read \"not evaluated\", never mixed in."]



def _summary_sections(profile: Profile, summary, unrankable: dict[str, str]) -> list[str]:
    """The summary tables of each track (`grid.TRACKS`: models trained on the paper's
    scenes, then on varied draws) and dimension's grid apart (`scene_groups`), each
    heading naming the grid and what its models were trained on (`track_rows`)."""
    pairs = evaluation_pairs(profile)
    lines = []
    for track in [t for t in TRACKS if t == PAPER_TRACK or any(p.job.track == t for p in pairs)]:
        track_pairs = [p for p in pairs if p.job.track == track]
        expected = {(pair.scene, pair.label) for pair in track_pairs}
        shown = track_rows(summary, pairs, track)
        modelled = shown[~shown["model"].isin(("ground truth", REST, EXACT_NO_DRAG))]["scene"] if not shown.empty else []
        groups = scene_groups([*modelled, *(pair.scene for pair in track_pairs)], track) if not shown.empty else {2: []}
        for dim, scenes in groups.items():
            trained = list(dict.fromkeys(pair.job.trained_on for pair in track_pairs if pair.scene in scenes))
            grid_name = (DIMENSION_NAMES.get(dim, f"{dim}D") + (", transfer track" if track == TRANSFER_TRACK else "")
                         + (f": trained on {', '.join(trained)}" if trained else ""))
            for metric, heading in summary_tables(profile.evaluate.references):
                table = summary_markdown(shown, metric, expected, unrankable, scenes, trained[0] if len(trained) == 1 else None,
                                         model_order(profile), profile.evaluate.references)
                lines += [f"## {heading} ({grid_name})", "", table]
    return lines


def _external_lines(pairs: list) -> list[str]:
    """The predictions made outside lgnn among the records (`lgnn.bench.stages.external`):
    what each is and which scenes it answers; none: no lines."""
    found: dict[str, list] = {}
    for pair, (_, meta) in pairs:
        if pair.job.external:
            found.setdefault(pair.label, []).append(meta)
    if not found:
        return []
    lines = ["## External predictions", "",
             f"Rows marked `{EXTERNAL_MARK.strip()}` are predictions made outside lgnn from the same exported initial conditions "
             "(`lgnn dataset export`), scored here against the same ground truth with the same metrics and divergence rule "
             "(`lgnn benchmark --add-predictions`; docs/formats.md, \"Predictions\"). They have no checkpoint, parameters or "
             "training time here, and are not in the training table.", "",
             "| model | scenes | file | about |", "|---|---|---|---|"]
    for label, metas in found.items():
        files = ", ".join(dict.fromkeys(f"`{m['file']}`" for m in metas))
        about = escape_markdown_cell("; ".join(dict.fromkeys(m["about"] for m in metas if m.get("about")))) or "—"
        lines.append(f"| {label} | {', '.join(m['scene'] for m in metas)} | {files} | {about} |")
    return [*lines, ""]


def _initial_states_text(profile: Profile) -> str:
    """Which of the profile's evaluation scenes start how (`lgnn.scene.initial_state_policy`)."""
    by_policy: dict[str, list[str]] = {}
    for scene in evaluation_scenes(profile):
        by_policy.setdefault(initial_state_policy(get_scene(scene)), []).append(scene)
    how = {CHAIN_SAMPLER: "the paper's chain sampler (in 3D the 3D chain sampler)", PROJECTED: "projected perturbations of their own state",
           OWN_STATE: "their own state, one initial condition"}
    return "; ".join(f"{how[policy]}: {', '.join(scenes)}" for policy, scenes in by_policy.items())


def readme_markdown(profile: Profile, out: Path, records: tuple, checkpoints: list, summary, speed_rows, mass_records, figures: list[str], env: dict[str, str],
           stage_lines: list[str] = (), command: str | None = None) -> str:
    p, t, e = profile, profile.training, profile.evaluate
    envs = sorted(set(summary["device"])) if not summary.empty else []
    unrankable = unrankable_scenes(out)
    lines = [
        f"# Benchmark results ({p.name} profile)",
        "",
        f"Written by `{_command(p, command)}`; nothing here is edited by hand.",
        f"Report written at commit {env['commit']}" + (" (lgnn not run from a git checkout; `LGNN_COMMIT` names it)" if env["commit"] == "unknown" else "")
        + f"; {env['versions']}.",
        *([f"Records and checkpoints of `{p.base}` are read in place (never copied or written) beside this folder's; "
           "each record's folder and commit are under \"Where each record was made\"."] if p.base is not None else []),
        *_unmatched_lines(p, out),
        "Each number's own commit, versions and device are columns of `benchmark/summary.csv.gz` (the stages may run on different machines): "
        + "; ".join(envs) + ".",
        "",
        *banner(p),
        *_cut_off_lines(p, checkpoints),
        "## Settings",
        "",
        f"- Training: {t.data.n_trajectories} trajectories of {t.data.duration:g} s, a state every {t.data.sample_dt:g} s (75:25 split), "
        f"Adam {t.train.learning_rate:g}, batch {t.train.batch_size}, budget {t.train.epochs} epochs"
        + (f" or {t.train.minutes:g} minutes per model (whichever ends first; the paper's 10 000 epochs did not fit)" if t.train.minutes else "")
        + (f", plateau: stop when the best validation MSE has not improved by {t.train.min_improvement:.0%} in {t.train.patience} epochs"
           if t.train.min_improvement else f", patience {t.train.patience}")
        + f", seeds {', '.join(map(str, p.seeds))}.",
        f"- Evaluation: {e.initial_conditions} initial conditions per scene, seed {e.ic_seed}, {_initial_states_text(p)}, "
        f"{e.duration:g} s, frames every {e.frame_dt:g} s, RK4 at dt {e.dt:g} with projection for models and the Lagrangian ground truth"
        + "".join(f" ({scene}: dt {dt:g})" for scene, dt in e.scene_dts if scene in evaluation_scenes(p)) + "; "
        f"MuJoCo C at RK4 dt {e.mujoco_dt:g}. Chaos floor: initial positions perturbed by {e.floor_perturbation:g}.",
        "- Errors (SPEC): per frame `||q_hat - q|| / (||q_hat|| + ||q||)`; energy error the same on the true Hamiltonian; "
        "geometric mean over frames t > 0 and initial conditions, [bootstrap 95% interval over initial conditions]; "
        f"errors clipped to [{metrics.ERROR_FLOOR:g}, 1]; a rollout counts as diverged at the first frame whose state is non-finite, "
        f"whose true energy is {metrics.EXPLOSION_FACTOR:g} energy scales from the initial one, or where a node moved {metrics.EXPLOSION_FACTOR:g} "
        "structure sizes (plus a free fall's reach) from its start (`lgnn.metrics`, the rule that stops every engine): error 1 from then on, and the cell says when.",
        "- Per-node RMS position error `sqrt(mean over nodes |q_hat - q|^2)` (length units), beside the paper's normalised error, which "
        "shrinks as a structure grows: the same statistics; a diverged frame counts as the divergence rule's reach "
        f"({metrics.EXPLOSION_FACTOR:g} structure sizes), which also caps it; `Nx floor` is its ratio to the chaos floor's RMS error on the scene.",
        "- `rest`: the rest baseline, the initial state held (`lgnn.metrics.rest_rollouts`), scored like a model: its errors are the truth's own "
        "displacement from its start, the bar any model must clear. The chaos floor is not given (\"diverged\") on a scene where a "
        "perturbed run diverged: it is then no floor. \"not computed\": a record written before that metric existed.",
        "- `gns` rollouts are projected onto the constraints after every step, as the ground truth's and every Lagrangian model's "
        "(GNS's own accelerations know no constraints); `gns (unprojected)` is the same checkpoint without projection. "
        f"`{EXACT_NO_DRAG}` (drag scenes): the exact physics with the drag term removed, from the same states: what ignoring drag scores.",
        "- Several training seeds: a cell is the geometric mean over seeds and initial conditions with a two-level bootstrap 95% interval "
        "(seeds, then each seed's initial conditions), `(n seeds)`; each seed's own numbers are rows of `benchmark/summary.csv.gz`. "
        "\"not evaluated\": a pair of the grid with no record yet (`lgnn benchmark --stage evaluate` resumes there).",
        *(["- Not rankable (`results/convergence.md`, `lgnn convergence`): the reference itself does not converge in dt, so no "
           "model number on these scenes could rank models and none is reported"
           + (" (the full grid does not evaluate them; T2-slack and T3-slack, their ropes 0.1 % slack, converge and stand in for them)"
              if p.name == "full" else "") + ": " + "; ".join(f"{scene}: {why}" for scene, why in unrankable.items()) + "."]
          if unrankable else []),
        "",
        "## Training",
        "",
        *_training_lines(p, out, checkpoints),
        "",
        *_external_lines(records[1]),
        *_summary_sections(p, summary, unrankable),
    ]
    if mass_records:
        lines += ["## Learned mass matrix (LGNN)", "",
                  "Each scene's LGNN is the one trained on its dimension's training scene (" + ", ".join(
                      f"{DIMENSION_NAMES.get(dim, f'{dim}D')}: {scene}" for dim, scene in TRAINING_SCENES.items()) + "; checkpoint "
                  "column), against the rods' mass matrix (in 3D a thin rod has no spin about its own axis). "
                  "Percentage Frobenius error over the free node coordinates and on the constraint tangent space (the part the dynamics "
                  "see), as learned and after the least-squares overall factor: accelerations fix a Lagrangian only up to a factor.", "",
                  "| scene | checkpoint | % error | % error, tangent space | factor | % error x factor | % error x factor, tangent space |",
                  "|---|---|---|---|---|---|---|"]
        lines += [f"| {m['scene']} | {m['job']} | {m['percent_error']:.3g} | {m['tangent_percent_error']:.3g} | {m['scale']:.3g} | "
                  f"{m['scaled_percent_error']:.3g} | {m['scaled_tangent_percent_error']:.3g} |" for _, m in mass_records]
        lines.append("")
    if speed_rows:
        lines += [f"## Speed against error (single trajectory, {speed_rows[0]['horizon_s']:g} s horizon, compile apart)", "",
                  "Error: geometric-mean rollout error against MuJoCo C at a tenth of the smallest step. Each scene's row group was "
                  "timed by one process on its own CPU core (`taskset`), the learned models and the Lagrangian engine through XLA's CPU "
                  "backend (`JAX_PLATFORMS=cpu`), on:", "",
                  *[f"- {scene}: {device}" for scene, device in dict.fromkeys((r["scene"], r["device"]) for r in speed_rows)], "",
                  speed_markdown(speed_rows)]
    lines += stage_lines
    lines += ["## Where each record was made", "",
              "Every stage resumes from the records it finds, so stages may run apart, on several machines, and be assembled by the "
              f"report: `lgnn benchmark{' --full' if p.name == 'full' else ''} --stage train|evaluate|speed|mass|report "
              "[--scene S] [--job J] [--chunk N]`. `+dirty` marks a record written while the working tree had uncommitted "
              "changes. Each record also holds the versions (`benchmark/summary.csv.gz`).", "",
              *_provenance_lines(*records, speed_rows, mass_records, out), ""]
    lines += ["## Files", "", "| file | what |", "|---|---|",
              "| `benchmark/summary.csv.gz` | tidy summary: scene, model, seed, metric, statistic, value, commit, versions, device |",
              f"| `benchmark/curves.csv.gz` | per-frame geometric means and 95% bands (every {CURVE_DT:g} s; provenance: the matching `summary.csv.gz` rows) |",
              "| `benchmark/speed_error.csv`, `.md` | speed against error |",
              *(["| `performance.md` | the speed records read as ratios to MuJoCo C at equal accuracy, each 3D chain beside the planar one, "
                 "and cost against chain length in 2D and 3D |"] if speed_rows else []),
              "| `benchmark/mass_matrix.csv` | learned mass matrix errors |",
              "| `benchmark/checkpoints/` | the trained models (`lgnn rollout --model ...` runs them) |",
              "| `benchmark/runs/` | the per-stage records the tables are made from (resumable) |"]
    lines += [f"| `figures/{name}` | figure |" for name in figures]
    if p.name == "full" and p.base is None:  # the repository's results/ beside the report
        lines += [
            "| `crosscheck.csv`, `.md` | ground-truth engines against each other (`lgnn crosscheck chain4 chain8 chain16 chain100 T1 T2 T3 --duration 0.1 --out-dir DIR`, float64 on a CPU: the table's header names the machine; 0.1 s, as MJX's CPU compile takes 15-25 s a scene) |",
            "| `engines_speed_error.csv`, `.md` | engines' steps/s and error at dt 1e-3..1e-5 (`lgnn crosscheck --speed chain4 chain16 chain100 T1 --out-dir results`) |",
            "| `stability.md`, `.csv` | hard cases: long horizons, 1000 links, large steps, near-singular geometry, diverging models (`lgnn stability --out results/stability.md`) |",
        ]
    return "\n".join(lines) + "\n"


