"""The user documentation is true: README.md, CHANGELOG.md, ARCHITECTURE.md and docs/*.md.

- every relative link (and every `#anchor` within a page) resolves;
- every `lgnn COMMAND --option` written in them is an option of that command's
  `--help`, and docs/cli.md names every option of every command;
- the README's first two commands are the install-and-run command and the test
  command that `.ci/run` runs;
- the README's headline table is copied cell by cell from `results/README.md`;
- the bring-your-own-model example of docs/models.md runs: its model files load, make
  parameters and accelerations of the right shape (zero at pinned nodes), the
  Lagrangian one equals the true dynamics at its truth, and one rollout runs;
- the user pages (README.md, docs/) name no commit, issue or machine path;
- the scene file of docs/scenes.md and the benchmark config of docs/benchmark.md load
  as written (the config names that scene and that model file).
"""

import contextlib
import io
import re
from functools import lru_cache
from pathlib import Path

import jax
import numpy as np
import pytest

import lgnn
from lgnn import physics
from lgnn.bench import profiles
from lgnn.cli import build_parser
from lgnn.learn import models

ROOT = Path(__file__).resolve().parent.parent
PAGES = sorted([ROOT / "README.md", ROOT / "CHANGELOG.md", ROOT / "ARCHITECTURE.md", *(ROOT / "docs").glob("*.md")])
# The section of results/README.md the README's headline table is copied from.
HEADLINE_SECTION = "## Rollout error against the Lagrangian ground truth (planar: trained on chain4, chain4-varied, chain4-drag)"
FIRST_COMMANDS = (
    "python3 -m venv .venv && . .venv/bin/activate && pip install -e . && lgnn benchmark",
    "python3 -m venv .venv && . .venv/bin/activate && pip install -e '.[test]' && pytest -n auto --dist loadfile",
)

LINK = re.compile(r"!?\[[^\]]*\]\(([^)\s]+)\)")
CODE_BLOCK = re.compile(r"^```[a-z]*\n(.*?)^```", re.S | re.M)
INLINE_CODE = re.compile(r"`([^`]+)`")
OPTION = re.compile(r"(?<![\w-])--[a-z][a-z0-9-]*")


def _without_code_blocks(text: str) -> str:
    return CODE_BLOCK.sub("", text)


def _anchor(heading: str) -> str:
    """GitHub's anchor of a heading: lower case, punctuation dropped, spaces to hyphens."""
    return re.sub(r"[^\w\- ]", "", heading.strip().lower()).replace(" ", "-")


def _anchors(page: Path) -> set[str]:
    return {_anchor(line.lstrip("#")) for line in _without_code_blocks(page.read_text()).splitlines() if line.startswith("#")}


@pytest.mark.parametrize("page", PAGES, ids=lambda page: page.relative_to(ROOT).as_posix())
def test_every_relative_link_resolves(page):
    for target in LINK.findall(_without_code_blocks(page.read_text())):
        if re.match(r"[a-z]+:", target):
            continue  # http(s), mailto: not checked offline
        path, _, anchor = target.partition("#")
        resolved = (page.parent / path).resolve() if path else page
        assert resolved.exists(), f"{page.name}: link {target!r} names no file"
        if anchor and resolved.suffix == ".md":
            assert anchor in _anchors(resolved), f"{page.name}: link {target!r} names no heading"


@lru_cache(maxsize=None)
def _help(command: tuple[str, ...]) -> str:
    """`lgnn COMMAND --help` (empty if `command` is not one)."""
    out = io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(io.StringIO()):
        try:
            build_parser().parse_args([*command, "--help"])
        except SystemExit as stop:
            if stop.code:
                return ""
    return out.getvalue()


def _commands() -> list[str]:
    """The top-level commands, from `lgnn --help`."""
    listing = _help(()).split("positional arguments:")[1].split("options:")[0]
    return re.findall(r"^    ([a-z][a-z-]*)", listing, re.M)


def _written_commands(text: str):
    """Each `lgnn COMMAND [SUBCOMMAND] ...` written in code (a code block's command or an
    inline code span) as (command words, the options written after them)."""
    spans = [segment for block in CODE_BLOCK.findall(text) for segment in block.replace("\\\n", " ").splitlines()]
    spans += INLINE_CODE.findall(_without_code_blocks(text).replace("\n", " "))
    for span in spans:
        for part in re.split(r"&&|\|\||;|\|(?= *lgnn)", span):
            words = part.split()
            if "lgnn" not in words:
                continue
            start = words.index("lgnn") + 1
            if start >= len(words) or words[start] not in _commands():
                continue
            command = (words[start],)
            if start + 1 < len(words) and _help((*command, words[start + 1])):
                command += (words[start + 1],)
            yield command, OPTION.findall(" ".join(words[start + len(command):]))


@pytest.mark.parametrize("page", PAGES, ids=lambda page: page.relative_to(ROOT).as_posix())
def test_every_written_option_is_one_of_its_commands(page):
    for command, options in _written_commands(page.read_text()):
        known = set(OPTION.findall(_help(command)))
        assert known, f"{page.name}: 'lgnn {' '.join(command)}' is not a command"
        for option in options:
            assert option in known, f"{page.name}: 'lgnn {' '.join(command)} {option}' is not in its --help"


def test_the_cli_page_names_every_option_of_every_command():
    page = (ROOT / "docs" / "cli.md").read_text()
    for command in _commands():
        text = _help((command,))
        subcommands = re.findall(r"^    ([a-z][a-z-]*)", text.split("positional arguments:")[-1].split("options:")[0], re.M)
        for words in [(command, sub) for sub in subcommands if _help((command, sub))] or [(command,)]:
            assert f"lgnn {' '.join(words)}" in page, f"docs/cli.md does not name 'lgnn {' '.join(words)}'"
            for option in set(OPTION.findall(_help(words))) - {"--help"}:
                assert option in page, f"docs/cli.md does not name 'lgnn {' '.join(words)} {option}'"


def test_the_readme_opens_with_the_commands_ci_runs():
    blocks = [block.strip() for block in CODE_BLOCK.findall((ROOT / "README.md").read_text()) if "lgnn benchmark" in block or "pytest" in block]
    assert tuple(blocks[:2]) == FIRST_COMMANDS
    assert FIRST_COMMANDS[1] in (ROOT / ".ci" / "run").read_text()


def _tables(lines: list[str]) -> list[list[list[str]]]:
    """The markdown tables in `lines`, each a list of rows of cells (separator rows left out)."""
    tables, rows = [], []
    for line in [*lines, ""]:
        if line.startswith("|"):
            cells = [cell.strip() for cell in line.strip().strip("|").split("|")]
            if not all(set(cell) <= set("-: ") for cell in cells):
                rows.append(cells)
        elif rows:
            tables.append(rows)
            rows = []
    return tables


def _section(text: str, heading: str) -> list[str]:
    lines = text.splitlines()
    start = lines.index(heading)
    end = next((k for k in range(start + 1, len(lines)) if lines[k].startswith("## ")), len(lines))
    return lines[start + 1:end]


def test_the_readme_headline_table_is_copied_from_the_committed_results():
    (readme_table,) = _tables(_section((ROOT / "README.md").read_text(), "## Headline result"))
    (results_table,) = _tables(_section((ROOT / "results" / "README.md").read_text(), HEADLINE_SECTION))
    results = {row[0]: dict(zip(results_table[0], row)) for row in results_table[1:]}
    header, *rows = readme_table
    assert header[0] == "scene" and len(rows) >= 5
    for row in rows:
        for column, cell in zip(header, row):
            assert cell == results[row[0]][column], f"README headline {row[0]} / {column}: {cell!r} is not results/README.md's"


@pytest.fixture(scope="module")
def model_dir(tmp_path_factory):
    """A folder holding docs/models.md's model files (its code blocks that open with
    `# NAME.py`), one for the module: a model name is registered once per process."""
    folder = tmp_path_factory.mktemp("own-models")
    for block in CODE_BLOCK.findall((ROOT / "docs" / "models.md").read_text()):
        first = block.splitlines()[0]
        if re.fullmatch(r"# \w+\.py", first):
            (folder / first[2:]).write_text(block)
    assert sorted(path.name for path in folder.iterdir()) == ["my_accel_model.py", "my_model.py"]
    return folder


def test_the_models_page_python_example_runs(model_dir, capsys, monkeypatch):
    (example,) = [block for block in CODE_BLOCK.findall((ROOT / "docs" / "models.md").read_text()) if "load_spec" in block and "print(" in block]
    monkeypatch.chdir(model_dir)  # the page runs it beside the model file
    exec(compile(example, "docs/models.md", "exec"), {})
    assert capsys.readouterr().out.split() == ["(9,", "2)"]


@pytest.mark.parametrize("reference", ["my_model.py:SPEC", "my_accel_model.py:SPEC"])
def test_the_models_page_models_step_and_roll_out(model_dir, reference):
    spec = models.load_spec(reference, base=model_dir)
    scene = lgnn.get_scene("chain8")
    config = models.ModelConfig.for_scene(spec.name, scene)
    params = models.init(jax.random.PRNGKey(0), config)
    q, qd = scene.initial_state
    qdd = np.asarray(models.acceleration_fn(config, params, scene)(q, qd))
    assert qdd.shape == (scene.n_nodes, scene.dim) and np.isfinite(qdd).all()
    assert np.all(qdd[list(scene.pinned)] == 0)  # the pinned-node rule the page states
    if spec.is_lagrangian:
        # At its truth (both scales 1) the example model is the true dynamics.
        truth = {"log_scale": jax.numpy.zeros(2)}
        np.testing.assert_allclose(models.acceleration_fn(config, truth, scene)(q, qd), physics.true_acceleration_fn(scene)(q, qd), atol=1e-10)
    trajectory = models.rollout(config, params, scene, lgnn.SimulationConfig(dt=1e-3, frame_dt=1e-3, duration=2e-3))
    assert trajectory.q.shape == (3, scene.n_nodes, scene.dim) and np.isfinite(trajectory.q).all()


def _blocks(page: str, language: str) -> list[str]:
    text = (ROOT / "docs" / page).read_text()
    return re.findall(rf"^```{language}\n(.*?)^```", text, re.S | re.M)


def test_the_scene_file_and_benchmark_config_examples_load(model_dir):
    (scene_json,) = _blocks("scenes.md", "json")
    (config,) = _blocks("benchmark.md", "toml")
    (model_dir / "my-scene.json").write_text(scene_json)
    (model_dir / "my.toml").write_text(config)
    scene = lgnn.get_scene(str(model_dir / "my-scene.json"))
    assert (scene.n_nodes, scene.n_links, scene.pinned, float(scene.gravity)) == (3, 2, (0,), 10.0)
    # The overrides its first line shows, as `--set` gives them.
    profile = profiles.load_profile(model_dir / "my.toml", ["training.train.epochs=50", "seeds=[0,1,2]"])
    (entry,) = profile.grid
    assert entry.model == "my-scaled-truth" and entry.train_scene == "chain4"
    assert profile.seeds == (0, 1, 2) and profile.training.train.epochs == 50
    assert profile.stages == ("train", "evaluate", "report")


@pytest.mark.parametrize("page", [ROOT / "README.md", *sorted((ROOT / "docs").glob("*.md"))], ids=lambda page: page.relative_to(ROOT).as_posix())
def test_user_pages_hold_no_history_or_machine_paths(page):
    """History (commits, issues) belongs in CHANGELOG.md or beside a result; a path of one
    machine helps no reader."""
    text = page.read_text()
    commits = [word for word in re.findall(r"\b[0-9a-f]{7,40}\b", text) if re.search(r"[a-f]", word) and re.search(r"\d", word)]
    assert not commits, f"{page.name} names commits {commits}"
    assert not re.search(r"\bissues? #?\d+|(?<![\w/])#\d+\b", text, re.I), f"{page.name} names an issue"
    assert not re.search(r"(?<![\w.])/(work|home|Users|tmp)/", text), f"{page.name} names a machine path"


def test_the_notebook_takes_a_model_file_to_its_leaderboard_row(tmp_path, monkeypatch, capsys):
    """docs/notebooks/your_model_on_the_leaderboard.ipynb, its code cells run in order
    (as a kernel would, without Jupyter): the model written to its own file trains and
    is ranked beside the built-in GNS, and its rows are in the run's tables."""
    import json
    import sys

    notebook = json.loads((ROOT / "docs" / "notebooks" / "your_model_on_the_leaderboard.ipynb").read_text())
    monkeypatch.chdir(tmp_path)
    monkeypatch.syspath_prepend(str(tmp_path))  # the model file, imported by `my_model.py:SPEC`
    namespace = {"__name__": "__notebook__"}
    for cell in notebook["cells"]:
        if cell["cell_type"] == "code":
            exec(compile("".join(cell["source"]), "notebook", "exec"), namespace)
    sys.modules.pop("my_model", None)
    printed = capsys.readouterr().out
    assert "my-notebook-model" in printed and "gns" in printed
    summary = namespace["summary"]
    assert {"my-notebook-model", "gns"} <= set(summary[summary["metric"] == "rollout_error"]["model"])
    leaderboard = (tmp_path / "tiny-out" / "LEADERBOARD.md").read_text()
    assert "my-notebook-model" in leaderboard and "| gns" in leaderboard


def test_the_license_and_citation_files_say_what_the_package_and_readme_say():
    """LICENSE is the MIT licence pyproject.toml names; CITATION.cff is valid CFF naming
    the suite and the paper the README cites."""
    import tomllib

    yaml = pytest.importorskip("yaml")
    root = Path(__file__).resolve().parents[1]
    project = tomllib.loads((root / "pyproject.toml").read_text())["project"]
    assert project["license"] == "MIT" and (root / "LICENSE").read_text().startswith("MIT License")
    citation = yaml.safe_load((root / "CITATION.cff").read_text())
    assert citation["cff-version"] == "1.2.0" and citation["version"] == project["version"] and citation["license"] == "MIT"
    paper = citation["preferred-citation"]
    assert paper["title"] in (root / "README.md").read_text() and paper["year"] == 2022
    assert [a["family-names"] for a in paper["authors"]] == ["Bhattoo", "Ranu", "Krishnan"]


def test_the_benchmark_pages_metric_example_registers_a_metric_that_scores(monkeypatch):
    """docs/benchmark.md's own metric, run as written: it lands in the registry and
    `score_rollouts` scores it (a prediction that is the truth: zero error, floored)."""
    from lgnn import metrics
    from lgnn.engines.base import SimulationConfig
    from lgnn.engines.lagrangian import simulate

    (example,) = [block for block in CODE_BLOCK.findall((ROOT / "docs" / "benchmark.md").read_text()) if "register_metric" in block]
    monkeypatch.setattr(metrics, "METRICS", dict(metrics.METRICS))  # the test's registration leaves with it
    exec(compile(example, "docs/benchmark.md", "exec"), {})
    assert "momentum_error" in metrics.METRICS
    scene = lgnn.get_scene("chain4")
    run = simulate(scene, SimulationConfig(dt=1e-3, duration=0.02, frame_dt=5e-3), progress=False)
    truth = metrics.trajectory_of(scene, run.t, np.asarray(run.q)[None], np.asarray(run.qd)[None])
    shifted = metrics.trajectory_of(scene, run.t, truth.q, truth.qd * 1.01)
    assert (metrics.score_rollouts(scene, truth, truth, names=("momentum_error",)).errors["momentum_error"] == metrics.ERROR_FLOOR).all()
    # Velocities 1 % larger: the momentum's relative error 0.01 / 2.01 wherever it moves.
    moving = metrics.score_rollouts(scene, shifted, truth, names=("momentum_error",)).errors["momentum_error"]
    np.testing.assert_allclose(moving, 0.01 / 2.01, rtol=1e-9)
