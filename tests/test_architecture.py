"""The package's shape: layers point one way, no import cycle, no private name used
across modules, and `import lgnn` changes nothing outside the package.

Layers, from the bottom (ARCHITECTURE.md): base utilities < scene < physics, integrate <
metrics < engines < learn < bench < cli. A module may import its own layer and the
layers below it, never above.
"""

from __future__ import annotations

import ast
import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

PACKAGE = Path(__file__).resolve().parents[1] / "lgnn"

LAYERS = (
    ("lgnn", "lgnn.errors", "lgnn.files", "lgnn.provenance", "lgnn.records", "lgnn.runtime", "lgnn.sharding"),
    ("lgnn.scene",),
    ("lgnn.trajectory",),
    ("lgnn.physics", "lgnn.integrate"),
    ("lgnn.metrics",),
    ("lgnn.engines",),
    ("lgnn.learn",),
    ("lgnn.bench",),
    ("lgnn.cli", "lgnn.__main__"),
)


def _module_name(path: Path) -> str:
    parts = path.relative_to(PACKAGE.parent).with_suffix("").parts
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


MODULES = {_module_name(path): path for path in sorted(PACKAGE.rglob("*.py"))}


def _layer(module: str) -> int:
    best = None
    for rank, prefixes in enumerate(LAYERS):
        for prefix in prefixes:
            if module == prefix or module.startswith(prefix + "."):
                if best is None or len(prefix) > best[0]:
                    best = (len(prefix), rank)
    assert best is not None, f"{module} belongs to no layer: add it to LAYERS and ARCHITECTURE.md"
    return best[1]


def _resolve(name: str) -> str | None:
    """The lgnn module an imported dotted name refers to (a module, or the module
    defining an imported name), or None outside lgnn."""
    while name:
        if name in MODULES:
            return name
        name = name.rpartition(".")[0]
    return None


def _imports(module: str) -> list[tuple[str, int, list[str]]]:
    """(imported lgnn module, line, names imported from it) for every import in the
    module, including those deferred into functions."""
    tree = ast.parse(MODULES[module].read_text())
    found = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            for alias in node.names:
                if (target := _resolve(alias.name)) is not None:
                    found.append((target, node.lineno, []))
        elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
            for alias in node.names:
                submodule = f"{node.module}.{alias.name}"
                if submodule in MODULES:
                    found.append((submodule, node.lineno, []))
                elif (target := _resolve(node.module)) is not None:
                    found.append((target, node.lineno, [alias.name]))
    return found


def test_layers_point_down():
    wrong = [
        f"{module}:{line} imports {target} (layer {_layer(target)} above {_layer(module)})"
        for module in MODULES
        for target, line, _ in _imports(module)
        if _layer(target) > _layer(module)
    ]
    assert not wrong, "\n".join(wrong)


def test_no_import_cycle():
    graph = {module: {target for target, _, _ in _imports(module) if target != module} for module in MODULES}
    state: dict[str, int] = {}
    path: list[str] = []

    def visit(module: str):
        state[module] = 1
        path.append(module)
        for target in sorted(graph[module]):
            if state.get(target) == 1:
                cycle = path[path.index(target):] + [target]
                pytest.fail("import cycle: " + " -> ".join(cycle))
            if target not in state:
                visit(target)
        path.pop()
        state[module] = 2

    for module in MODULES:
        if module not in state:
            visit(module)


def _private(name: str) -> bool:
    return name.startswith("_") and not name.startswith("__")


def test_no_private_name_across_modules():
    """`from lgnn.x import _name` and `x._name` on an imported lgnn module are both
    another module's internals."""
    wrong = []
    for module, path in MODULES.items():
        tree = ast.parse(path.read_text())
        aliases = {}
        for target, line, names in _imports(module):
            wrong += [f"{module}:{line} imports {target}.{name}" for name in names if _private(name) and target != module]
        for node in ast.walk(tree):
            if isinstance(node, (ast.Import, ast.ImportFrom)):
                for alias in node.names:
                    full = alias.name if isinstance(node, ast.Import) else f"{node.module}.{alias.name}"
                    if full in MODULES and full != module:
                        aliases[alias.asname or alias.name.split(".")[0] if isinstance(node, ast.Import) else alias.asname or alias.name] = full
        for node in ast.walk(tree):
            if isinstance(node, ast.Attribute) and isinstance(node.value, ast.Name) and node.value.id in aliases:
                if _private(node.attr):
                    wrong.append(f"{module}:{node.lineno} uses {aliases[node.value.id]}.{node.attr}")
        wrong += [f"{module}: private module {target}" for target, _, _ in _imports(module)
                  if any(_private(part) for part in target.split(".")) and not target.startswith(module)]
    assert not wrong, "\n".join(sorted(set(wrong)))


def test_import_changes_nothing_outside_the_package():
    """Importing lgnn and every one of its modules leaves the environment and JAX's
    settings as they were (what JAX and numpy set on their own import aside): runtime
    set-up is the explicit `lgnn.configure()`."""
    script = f"""
import importlib, json, os
import jax, numpy
before = dict(os.environ), jax.config.jax_enable_x64
for name in {sorted(set(MODULES) - {"lgnn.__main__"})!r}:  # that one runs the command
    importlib.import_module(name)
after = dict(os.environ), jax.config.jax_enable_x64
print(json.dumps([before == after, [k for k in set(before[0]) | set(after[0]) if before[0].get(k) != after[0].get(k)], after[1]]))
"""
    env = {key: value for key, value in os.environ.items() if key not in ("XLA_FLAGS", "OPENBLAS_NUM_THREADS", "JAX_ENABLE_X64")}
    out = subprocess.run([sys.executable, "-c", script], env=env, cwd=PACKAGE.parent, capture_output=True, text=True, check=True)
    unchanged, changed, x64 = json.loads(out.stdout.strip().splitlines()[-1])
    assert unchanged and not changed and not x64, (changed, x64)


def test_bare_import_loads_nothing_heavy():
    """`import lgnn` must not load numpy or JAX, so `lgnn.configure()` can still set the
    thread count OpenBLAS reads when numpy loads it."""
    script = "import sys, lgnn; print(sorted(m for m in ('numpy', 'jax', 'scipy') if m in sys.modules))"
    out = subprocess.run([sys.executable, "-c", script], cwd=PACKAGE.parent, capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "[]"


def test_configure_sets_up_the_process():
    script = "import os, lgnn; lgnn.configure(); import jax; print(os.environ['OPENBLAS_NUM_THREADS'], os.environ['XLA_FLAGS'], jax.config.jax_enable_x64)"
    env = {key: value for key, value in os.environ.items() if key not in ("XLA_FLAGS", "OPENBLAS_NUM_THREADS")}
    out = subprocess.run([sys.executable, "-c", script], env=env, cwd=PACKAGE.parent, capture_output=True, text=True, check=True)
    assert out.stdout.split() == ["1", "--xla_cpu_enable_concurrency_optimized_scheduler=false", "--xla_cpu_parallel_codegen_split_count=1", "True"]


def test_ray_is_imported_only_to_run_on_ray():
    """The command line, the benchmark's runner and even the Ray executor's module load
    no Ray: only a run with `--executor ray` imports it (`ray_executor.connected`)."""
    script = ("import sys, lgnn, lgnn.cli; lgnn.cli.build_parser(); import lgnn.bench.run, lgnn.bench.ray_executor; "
              "print('ray' in sys.modules)")
    out = subprocess.run([sys.executable, "-c", script], cwd=PACKAGE.parent, capture_output=True, text=True, check=True)
    assert out.stdout.strip().splitlines()[-1] == "False"


def _modules_in_layer_table() -> tuple[set[str], tuple[str, ...]]:
    """The modules ARCHITECTURE.md's layer table names: each `lgnn.X` of a row's modules
    cell, and the names after it, read as its modules (`name`, or `name/*` for a
    package and everything in it); names before any `lgnn.X` are `lgnn`'s own."""
    import re

    text = (PACKAGE.parent / "ARCHITECTURE.md").read_text()
    table = text.split("## Layers", 1)[1].split("\n## ", 1)[0]
    named, packages = set(), []
    for row in table.splitlines()[2:]:
        cells = row.split(" | ")
        if len(cells) < 3:
            continue
        parent = "lgnn"
        for token in re.findall(r"`([^`]+)`", cells[1]):
            if token.startswith("lgnn.") or token == "lgnn":
                parent = token
                named.add(token)
            elif token.endswith("/*"):
                packages.append(f"{parent}.{token[:-2].replace('/', '.')}")
            elif re.fullmatch(r"[a-z_][a-z0-9_/]*", token):
                named.add(f"{parent}.{token.replace('/', '.')}")
    return named, tuple(packages)


def test_the_layer_table_of_architecture_md_names_every_module():
    named, packages = _modules_in_layer_table()
    missing = [module for module in MODULES if module != "lgnn" and module not in named
               and not any(module == package or module.startswith(package + ".") for package in packages)]
    assert not missing, f"ARCHITECTURE.md's layer table does not name {missing}: add each to its layer's row"
