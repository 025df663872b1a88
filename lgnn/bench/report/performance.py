"""`performance.md` and the speed table: the speed records read as ratios to MuJoCo C at
equal accuracy, each 3D chain beside its planar twin, cost against chain length, and the
GPU tables of `lgnn crosscheck --speed` and `lgnn gpu-truth` under `gpu/`."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from lgnn.bench import crosscheck, gpu_truth
from lgnn.bench.grid import TRAINING_SCENES
from lgnn.bench.profiles import Profile
from lgnn.bench.stability import fit_exponent
from lgnn.bench.report.summary import DIMENSION_NAMES, number_cell, without_training_scene
from lgnn.bench.tables import escape_markdown_cell
from lgnn.scene import get_scene, is_pinned_chain


def _spread(r: dict) -> str:
    """`min..max (n runs)` of a speed row's timed runs; `1 run` for one (records made
    before the spread was kept hold one run)."""
    runs = r.get("runs", 1 if math.isfinite(r["wall_s_per_sim_s"]) else 0)
    if not runs:
        return "—"
    if runs == 1:
        return "1 run"
    return f"{number_cell(r['wall_s_min_per_sim_s'])}..{number_cell(r['wall_s_max_per_sim_s'])} ({runs} runs)"


def speed_markdown(rows: list[dict]) -> str:
    lines = ["| scene | solver | dt | wall s per simulated s (median) | spread | evaluations per simulated s | compile s | rollout error | note |",
             "|---" * 9 + "|"]
    for r in rows:
        compile_s = "—" if not math.isfinite(r["compile_s"]) else f"{r['compile_s']:.1f}"
        note = "; ".join(filter(None, (f"{r['form']} MJCF" if r.get("form") else "", r["note"])))
        lines.append(f"| {r['scene']} | {r['solver']} | {r['dt']:g} | {number_cell(r['wall_s_per_sim_s'])} | {_spread(r)} | {r['evaluations_per_sim_s']:.0f} | "
                     f"{compile_s} | {number_cell(r['rollout_error'])} | {note} |")
    return "\n".join(lines) + "\n"



# Issue 7's accuracy bar for comparing engines' speed: a step whose rollout error
# against the reference is at most this (the default settings' max node error).
ACCURATE = 1e-6


def _fastest_accurate(rows: list[dict], scene: str, solver: str) -> dict | None:
    """`solver`'s fastest row on `scene` whose error is within ACCURATE."""
    ok = [r for r in rows if r["scene"] == scene and r["solver"] == solver and math.isfinite(r["wall_s_per_sim_s"])
          and math.isfinite(r["rollout_error"]) and r["rollout_error"] <= ACCURATE]
    return min(ok, key=lambda r: r["wall_s_per_sim_s"]) if ok else None


def _gpu_section(out: Path) -> list[str]:
    """The GPU tables under `out/gpu/` (written by `lgnn crosscheck --speed` on a lent
    GPU machine, commands in their headers; `crosscheck.load_batched_rates`): batched
    throughput, Lagrangian over MJX where a table has both; and the LGNN training-time
    summary if present."""
    gpu = out / "gpu"
    rates = crosscheck.load_batched_rates(gpu)
    if not (sorted(gpu.glob("*.csv")) if gpu.is_dir() else []):
        return ["Not measured in this output directory (no `gpu/` tables)."]
    lines = ["Batched ground truth on GPUs, RK4 at dt 1e-3, from the tables in `gpu/` (each `.md` names its command, machine and "
             "versions; `h200x2_*`: one and two H200s of one host, the batch split over the devices by `jax.sharding`).", "",
             "| table | scene | batch | dtype | Lagrangian steps/s | MJX steps/s | Lagrangian / MJX | MuJoCo C steps/s |", "|---" * 8 + "|"]
    groups: dict[tuple[str, str, int], list] = {}
    for rate in rates:
        groups.setdefault((rate.table, rate.scene, rate.batch), []).append(rate)
    for (table, scene, batch), group in groups.items():
        rate = {r.engine: r.steps_per_s for r in group}
        dtype = next(r.dtype for r in group if r.engine == "lagrangian") if "lagrangian" in rate else "—"
        ratio = rate["lagrangian"] / rate["mjx"] if "lagrangian" in rate and "mjx" in rate else float("nan")
        lines.append(f"| {table} | {scene} | {batch} | {dtype} | {number_cell(rate.get('lagrangian', float('nan')))} | "
                     f"{number_cell(rate.get('mjx', float('nan')))} | {'—' if math.isnan(ratio) else f'{ratio:.3g}'} | {number_cell(rate.get('mujoco', float('nan')))} |")
    for path in sorted(gpu.glob("*training*.txt")):
        lines += ["", f"LGNN training on a GPU (`{path.name}`, written by `lgnn benchmark --full --stage train --job lgnn-chain4-s0` "
                  "in a fresh output directory, then `lgnn checkpoint ... --reference results/benchmark/checkpoints/lgnn-chain4-s0.npz`):",
                  "", "```", path.read_text().strip(), "```"]
    return lines


def _gpu_truth_section(out: Path) -> list[str]:
    """The GPU ground-truth tables under `out/gpu/truth/` (`lgnn gpu-truth`) read as
    issue 14's goal: the float32 Lagrangian against the fastest MuJoCo GPU engine that
    is finite and agrees with the reference, per scene and batch (`gpu_truth.against_mujoco`)."""
    rows = gpu_truth.against_mujoco(gpu_truth.load(out / "gpu" / "truth"))
    if not rows:
        return ["Not measured in this output directory (no `gpu/truth/` tables)."]
    lines = [f"lgnn's Lagrangian engine in float32 against the fastest MuJoCo GPU engine (MJX, MuJoCo Warp; either MJCF form) "
             f"that stayed finite in every world and within {gpu_truth.AGREEMENT_MAX:g} of the float64 reference, from the tables in `gpu/truth/` (`lgnn gpu-truth`: RK4 at dt 1e-3, 100 steps; "
             f"commands, machine and versions in each table and in `gpu/truth/README.md`). Error: max node error after the last "
             f"step against the float64 Lagrangian engine. The goal is a ratio of at least {gpu_truth.GOAL_RATIO:g}. Each ratio is "
             "within one run; the machine column says which GPU ran it.", "",
             "| scene | batch | Lagrangian f32 steps/s | its error | fastest agreeing MuJoCo GPU engine | its steps/s | its error | "
             f"ratio | >= {gpu_truth.GOAL_RATIO:g}? | tables | machine | left out |", "|---" * 12 + "|"]
    for r in rows:
        ratio = "—" if math.isnan(r["ratio"]) else f"{r['ratio']:.3g}"
        goal = "—" if math.isnan(r["ratio"]) else ("yes" if r["meets_goal"] else "no")
        lines.append(f"| {r['scene']} | {r['batch']} | {number_cell(r['lagrangian_steps_per_s'])} | {number_cell(r['lagrangian_error'])} | "
                     f"{r['mujoco_engine'] or '—'} | {number_cell(r['mujoco_steps_per_s'])} | {number_cell(r['mujoco_error'])} | {ratio} | {goal} | "
                     f"{r['tables']} | {r['machine'] or '—'} | {escape_markdown_cell(r['note']) or '—'} |")
    return lines


def _form(row: dict) -> str:
    """A MuJoCo speed row's MJCF form; records made before rows kept it say so."""
    return row.get("form") or "not recorded"


def _planar_twin(scene: str, scenes) -> str | None:
    """The planar scene among `scenes` that 3D `scene` adds a dimension to: a pinned chain
    of as many links (chain16 for chain16-3d); None for others."""
    structure = get_scene(scene)
    if structure.dim != 3 or not is_pinned_chain(structure):
        return None
    for other in scenes:
        twin = get_scene(other)
        if twin.dim == 2 and is_pinned_chain(twin) and twin.n_links == structure.n_links:
            return other
    return None


def _third_dimension_lines(rows: list[dict], dt: float) -> list[str]:
    """The speed records' 3D chains beside their planar twins (`_planar_twin`): each
    engine and learned model at the evaluation step `dt`, wall s per simulated s in 2D
    and 3D and their ratio (a model: the median over its seeds, each dimension's own
    grid's model)."""
    scenes = list(dict.fromkeys(r["scene"] for r in rows))
    pairs = [(twin, scene) for scene in scenes if (twin := _planar_twin(scene, scenes)) is not None]
    if not pairs:
        return []

    def cost(scene: str) -> dict[str, tuple[float, str]]:
        """`{solver: (median wall s per simulated s, MJCF form)}` at `dt` on `scene`."""
        trained_on = TRAINING_SCENES[get_scene(scene).dim]
        timed: dict[str, list[dict]] = {}
        for r in rows:
            if r["scene"] == scene and math.isclose(r["dt"], dt) and math.isfinite(r["wall_s_per_sim_s"]):
                timed.setdefault(without_training_scene(r["solver"], trained_on), []).append(r)
        return {solver: (float(np.median([r["wall_s_per_sim_s"] for r in group])), _form(group[0])) for solver, group in timed.items()}

    def device(scene: str) -> str | None:
        return next((r.get("device") for r in rows if r["scene"] == scene), None)

    lines = ["", f"## The third dimension's cost (single trajectory, RK4 at dt {dt:g})", "",
             "Each 3D chain beside the planar chain of as many links: wall s per simulated s in each and their ratio. A learned "
             "model's cell is the median over its seeds, each trained on its own dimension's chain4 (— : not in that dimension's "
             "grid; MJX in the MJCF form it picks, maximal past tree depth 8). MuJoCo's joints: hinges in the plane (one DOF "
             "a link), balls in 3D (three). The two cells of a row come from two records (two processes; commits and machines "
             "in `README.md`), so a ratio carries their run-to-run noise (`benchmark/speed_error.md` gives each record's spread); "
             "a pair timed on different machines says so.",
             "", "| chains | solver | planar: wall s per simulated s | 3D: wall s per simulated s | 3D / planar | MJCF form (planar, 3D) |",
             "|---|---|---|---|---|---|"]
    for planar, spatial in pairs:
        flat, deep = cost(planar), cost(spatial)
        machines = "" if device(planar) == device(spatial) else " (different machines)"
        for solver in [s for s in ("lagrangian", "mujoco", "mjx") if s in flat or s in deep] + [
                s for s in dict.fromkeys([*flat, *deep]) if s not in ("lagrangian", "mujoco", "mjx")]:
            a, b = flat.get(solver, (math.nan, "")), deep.get(solver, (math.nan, ""))
            ratio = "—" if math.isnan(a[0]) or math.isnan(b[0]) else f"{b[0] / a[0]:.3g}{machines}"
            forms = f"{a[1] or '—'}, {b[1] or '—'}" if solver in ("mujoco", "mjx") else "—"
            cells = ("—" if math.isnan(x) else f"{x:.3g}" for x in (a[0], b[0]))
            lines.append(f"| {planar}, {spatial} | {solver} | {' | '.join(cells)} | {ratio} | {forms} |")
    return lines


def _size_lines(size: list[dict], dt: float) -> list[str]:
    """The scaling record's size rows: per solver, a row of seconds per step against
    chain length for each dimension, its fitted exponent, and a `3D / planar` row of
    their ratios. A row without `dim` is planar (records made before 3D rows held only
    planar chains: their key is that of no `spatial_lengths`, `scaling.scaling_key`)."""
    lengths, dims = sorted({r["n_links"] for r in size}), sorted({r.get("dim", 2) for r in size})
    lines = ["", f"## Cost per step against chain length (single trajectory, RK4 at dt {dt:g}, fitted exponent over "
             f"n = {', '.join(map(str, lengths))} links)", ""]
    if len(dims) > 1:
        lines += ["Planar chains and 3D chains of as many links, each with the LGNN of its own dimension's grid; the "
                  "`3D / planar` rows read off the third dimension's cost at each length.", ""]
    lines += ["| solver | chains | " + " | ".join(f"n = {n}: s per step" for n in lengths) + " | exponent | compile s (largest n) |",
              "|---" * (len(lengths) + 4) + "|"]
    for solver in dict.fromkeys(r["solver"] for r in size):
        per_dim = {}
        for dim in dims:
            timed = [r for r in size if r["solver"] == solver and r.get("dim", 2) == dim and math.isfinite(r["s_per_step"])]
            costs = per_dim[dim] = {r["n_links"]: r["s_per_step"] for r in timed}
            if not timed and not any(r["solver"] == solver and r.get("dim", 2) == dim for r in size):
                continue
            exponent = f"{fit_exponent(costs):.2f} (n = {min(costs)}..{max(costs)})" if len(costs) > 1 else "—"
            compile_s = f"{max(timed, key=lambda r: r['n_links'])['compile_s']:.1f}" if timed else "—"
            lines.append(f"| {solver} | {DIMENSION_NAMES.get(dim, f'{dim}D')} | " + " | ".join(f"{costs[n]:.3g}" if n in costs else "—" for n in lengths)
                         + f" | {exponent} | {compile_s} |")
        if per_dim.get(2) and per_dim.get(3):
            lines.append(f"| {solver} | 3D / planar | " + " | ".join(
                f"{per_dim[3][n] / per_dim[2][n]:.3g}" if n in per_dim[2] and n in per_dim[3] else "—" for n in lengths) + " | — | — |")
    lines += [f"- {r['solver']} on {r['scene']}: {r['note']}" for r in size if r.get("note")]
    return lines


def performance_markdown(profile: Profile, rows: list[dict], scaling_record: dict | None = None, out: Path | None = None) -> str:
    """`performance.md`: the speed records read as issue 7's ratios, the scaling record
    as cost against size and batched throughput, and the GPU tables."""
    lines = [
        "# Performance: ground truth and learned rollouts against MuJoCo",
        "",
        f"Written by the benchmark's report stage (`lgnn benchmark{' --full' if profile.name == 'full' else ''} --stage report`) "
        "from the speed-against-error records (`benchmark/runs/speed-error/`, made by `--stage speed`) and the scaling record "
        "(`benchmark/runs/scaling.json`, made by `--stage scaling`); nothing here is edited by hand. Every ratio but the third "
        "dimension's (two records, said there) compares rows timed in the same process on the same machine, compile apart; MuJoCo C is timed on its stepping alone (not the map "
        "from its joint coordinates to node states). Machines per record in `README.md`.",
        "",
        f"## Ground truth against MuJoCo C at equal accuracy (rollout error <= {ACCURATE:g} against the reference)",
        "",
        f"Single trajectory, {rows[0]['horizon_s']:g} s simulated." if rows else "No speed records.",
        "",
        "| scene | Lagrangian: dt, wall s per simulated s | MuJoCo C: dt, wall s per simulated s | Lagrangian / MuJoCo | "
        "Lagrangian compile s | MuJoCo C MJCF form |",
        "|---|---|---|---|---|---|",
    ]
    for scene in dict.fromkeys(r["scene"] for r in rows):
        ours, theirs = _fastest_accurate(rows, scene, "lagrangian"), _fastest_accurate(rows, scene, "mujoco")
        if ours is None or theirs is None:
            lines.append(f"| {scene} | {'—' if ours is None else ours['dt']} | {'—' if theirs is None else theirs['dt']} | — | — | — |")
            continue
        lines.append(f"| {scene} | {ours['dt']:g}, {ours['wall_s_per_sim_s']:.3g} | {theirs['dt']:g}, {theirs['wall_s_per_sim_s']:.3g} | "
                     f"{ours['wall_s_per_sim_s'] / theirs['wall_s_per_sim_s']:.3g} | {ours['compile_s']:.1f} | {_form(theirs)} |")
    lines += _third_dimension_lines(rows, profile.evaluate.dt)
    if scaling_record is not None:
        srows = scaling_record["rows"]
        batch = [r for r in srows if r["kind"] == "batch"]
        env = scaling_record.get("environment", {})
        lines += ["", f"## Batched ground truth against MuJoCo C ({batch[0]['batch'] if batch else 0} initial conditions at once, "
                  f"dt {profile.evaluate.dt:g}, {env.get('device', 'unknown device')})", "",
                  "| scene | Lagrangian steps/s | MuJoCo C steps/s (2 threads) | Lagrangian / MuJoCo |", "|---|---|---|---|"]
        for scene in dict.fromkeys(r["scene"] for r in batch):
            rate = {r["solver"]: r["batch"] / r["s_per_step"] for r in batch if r["scene"] == scene}
            lines.append(f"| {scene} | {rate['lagrangian']:.3g} | {rate['mujoco']:.3g} | {rate['lagrangian'] / rate['mujoco']:.3g} |")
        lines += _size_lines([r for r in srows if r["kind"] == "size"], profile.evaluate.dt)
    lines += [
        "",
        "## Learned rollouts",
        "",
        f"Every learned model is integrated with RK4 at dt {profile.evaluate.dt:g} (4 evaluations a step), not the paper's Verlet at "
        "1e-5; its wall time per simulated second and rollout error are the `learned` rows of `benchmark/speed_error.md`. "
        "LGNN's mass matrix couples only nearby nodes, so its solve uses coloured Hessian-vector products and, on long chains, "
        "the linear-time block elimination; LGN's is low rank plus local (`physics.MassStructure`).",
        "",
        "## GPUs",
        "",
        *(_gpu_section(out) if out is not None else ["Not measured."]),
        "",
        "## Ground truth on GPUs against MuJoCo's GPU engines",
        "",
        *(_gpu_truth_section(out) if out is not None else ["Not measured."]),
        "",
    ]
    return "\n".join(lines)

