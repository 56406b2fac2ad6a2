"""The package's shape (docs/architecture.md): layers that import only downward, no import
inside a function, modules and functions small enough to read, a trainer that knows nothing
of quadrotors, one choice of actor update, and a walk of one transition that is true."""

from __future__ import annotations

import ast
import pathlib
import re
import subprocess
import sys

PACKAGE = pathlib.Path(__file__).resolve().parent.parent / "ttd3_jax"
# each module's layer: a module may import only modules of its own or a lower layer
LAYERS = {"checks": 0, "sim": 1, "control": 2, "td3": 3, "train": 5, "evaluate": 5, "export": 5}
APP = 4  # everything else at the top level: spec, runs, checkpoint, runner, sharding, report, cache
MAX_MODULE_LINES, MAX_FUNCTION_LINES = 450, 60


def modules():
    for path in sorted(PACKAGE.rglob("*.py")):
        name = ".".join(("ttd3_jax", *path.relative_to(PACKAGE).with_suffix("").parts)).removesuffix(
            ".__init__"
        )
        yield name, path, ast.parse(path.read_text(), str(path))


NAMES = {name for name, _, _ in modules()}


def layer(module: str) -> int:
    parts = module.split(".")
    return LAYERS.get(parts[1], APP) if len(parts) > 1 else APP


def package_imports(tree: ast.AST):
    """``(node, imported module)`` for every import of a ``ttd3_jax`` module."""
    for node in ast.walk(tree):
        if isinstance(node, ast.ImportFrom) and node.module and node.module.startswith("ttd3_jax"):
            for a in node.names:  # "from ttd3_jax.sim import env" imports the module ttd3_jax.sim.env
                full = f"{node.module}.{a.name}"
                yield node, full if full in NAMES else node.module
        elif isinstance(node, ast.Import):
            yield from ((node, a.name) for a in node.names if a.name.startswith("ttd3_jax"))


def test_imports_only_go_down_the_layers_and_never_hide_in_functions():
    wrong, hidden = [], []
    for name, _, tree in modules():
        top = set(map(id, tree.body))
        for node, target in package_imports(tree):
            if layer(target) > layer(name):
                wrong.append(f"{name} (layer {layer(name)}) imports {target} (layer {layer(target)})")
            if id(node) not in top:
                hidden.append(f"{name}:{node.lineno} imports {target} inside a function")
    assert not wrong, "\n".join(wrong)
    assert not hidden, "\n".join(hidden)


def test_no_import_cycle():
    graph = {name: set() for name in NAMES}
    for name, _, tree in modules():
        graph[name] |= {t for _, t in package_imports(tree) if t in graph and t != name}
    done, stack = set(), []

    def visit(m):
        if m in stack:
            raise AssertionError("import cycle: " + " -> ".join(stack[stack.index(m) :] + [m]))
        if m not in done:
            stack.append(m)
            for n in sorted(graph[m]):
                visit(n)
            stack.pop()
            done.add(m)

    for m in sorted(graph):
        visit(m)


def test_modules_and_functions_are_small():
    long_modules, long_functions = [], []
    for name, path, tree in modules():
        n = len(path.read_text().splitlines())
        if n > MAX_MODULE_LINES:
            long_modules.append(f"{name}: {n} lines")
        for node in ast.walk(tree):
            if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
                length = node.end_lineno - node.lineno + 1
                if length > MAX_FUNCTION_LINES:
                    long_functions.append(f"{name}.{node.name}: {length} lines")
    assert not long_modules, long_modules
    assert not long_functions, long_functions


ROOT = PACKAGE.parent


def test_the_trainer_knows_nothing_about_quadrotors():
    """``ttd3_jax.td3`` imports no other part of the package (but the value checks of layer 0),
    and importing the trainer loads neither Brax nor MuJoCo."""
    outside = [f"{name} imports {target}" for name, _, tree in modules() if name.startswith("ttd3_jax.td3")
               for _, target in package_imports(tree)
               if not target.startswith("ttd3_jax.td3") and target != "ttd3_jax.checks"]  # fmt: skip
    assert not outside, outside
    code = (
        "import sys, ttd3_jax.td3.trainer; print(sorted(m for m in ('brax', 'mujoco') if m in sys.modules))"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True, cwd=ROOT)
    assert out.stdout.strip() == "[]", out.stdout


def test_the_actor_update_is_chosen_once():
    """The paper's step reads nothing of the model-based one: ``model_horizon`` appears once
    in the trainer (the choice) and never in ``td3/dpg.py``."""
    assert (PACKAGE / "td3" / "trainer.py").read_text().count("model_horizon") <= 2
    assert "model_horizon" not in (PACKAGE / "td3" / "dpg.py").read_text()


def _defined(path: pathlib.Path) -> set[str]:
    """Every function of ``path``, methods as ``Class.method``."""
    names = set()
    for node in ast.parse(path.read_text()).body:
        if isinstance(node, ast.FunctionDef):
            names.add(node.name)
        elif isinstance(node, ast.ClassDef):
            names |= {f"{node.name}.{f.name}" for f in node.body if isinstance(f, ast.FunctionDef)}
    return names


def test_the_walk_of_one_transition_in_the_docs_is_true():
    """docs/architecture.md's table of one transition names at most 6 files, and every
    function it names is defined in the file its row names."""
    doc = (ROOT / "docs" / "architecture.md").read_text()
    section = doc.split("## One transition through the code")[1].split("\n## ")[0]
    rows = [r for r in section.splitlines() if re.match(r"\| \d+ \|", r)]
    files, missing = set(), []
    for row in rows:
        cells = [c.strip() for c in row.strip("|").split("|")]
        path, functions = cells[1].strip("`"), re.findall(r"`([\w.]+)`", cells[2])
        files.add(path)
        missing += [f"{path}: {f}" for f in functions if f not in _defined(ROOT / path)]
    assert len(rows) >= 10 and len(files) <= 6, (len(rows), sorted(files))
    assert not missing, missing
