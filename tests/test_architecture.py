"""The package's shape (docs/architecture.md), measured from the code: layers that import only
downward, no import inside a function, modules and functions small enough to read, a trainer
that knows nothing of quadrotors, two actor updates that share only TD3's core, and one
compiled epoch that a reader follows through a handful of files (traced, not read off a doc)."""

from __future__ import annotations

import ast
import json
import pathlib
import subprocess
import sys

import pytest

PACKAGE = pathlib.Path(__file__).resolve().parent.parent / "ttd3_jax"
# each module's layer: a module may import only modules of its own or a lower layer
LAYERS = {"checks": 0, "sim": 1, "control": 2, "td3": 3, "run": 4, "interop": 5, "cli": 6}
ENTRY = 7  # the thin entry points ttd3_jax/train.py, evaluate.py, export.py (python -m ttd3_jax.X)
MAX_MODULE_LINES, MAX_FUNCTION_LINES = 600, 60
# one compiled epoch of fast / fast_dpg enters at most this many package files, at most this deep
MAX_EPOCH_FILES, MAX_EPOCH_DEPTH = 12, 12


def modules():
    for path in sorted(PACKAGE.rglob("*.py")):
        name = ".".join(("ttd3_jax", *path.relative_to(PACKAGE).with_suffix("").parts)).removesuffix(
            ".__init__"
        )
        yield name, path, ast.parse(path.read_text(), str(path))


NAMES = {name for name, _, _ in modules()}


def layer(module: str) -> int:
    parts = module.split(".")
    return LAYERS.get(parts[1], ENTRY) if len(parts) > 1 else ENTRY


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


def test_each_actor_update_is_its_own_path_on_td3s_core():
    """``td3/dpg.py`` (the paper's ∂Q/∂a) and ``td3/model_based.py`` (through the simulator)
    import neither each other nor the trainer: each builds on ``td3/core.py`` alone, and
    ``td3/trainer.py`` is the one module that names both (the choice, made once)."""
    imports = {name: {t for _, t in package_imports(tree)} for name, _, tree in modules()}
    dpg, mb, core = "ttd3_jax.td3.dpg", "ttd3_jax.td3.model_based", "ttd3_jax.td3.core"
    for a, b in ((dpg, mb), (mb, dpg)):
        assert b not in imports[a] and "ttd3_jax.td3.trainer" not in imports[a] and core in imports[a]
    assert [n for n, i in imports.items() if dpg in i and mb in i] == ["ttd3_jax.td3.trainer"]


def traced_epoch(preset: str) -> tuple[list[str], int]:
    """The package files one compiled epoch of ``preset`` (at a tiny size) enters while it is
    traced, and the deepest nesting of package function calls (``sys.setprofile`` around
    ``jax.make_jaxpr`` of the trainer's epoch)."""
    code = f"""
import json, os, sys, jax
sys.path.insert(0, {str(ROOT / "tests")!r})
from tiny import tiny
from ttd3_jax.run import spec as sp
pkg = os.path.dirname(sp.__file__).rsplit(os.sep, 1)[0] + os.sep
s = tiny(**({{"model_horizon": 2}} if {preset!r} == "fast" else {{}}))
t = sp.trainer_for(s)
ts = jax.eval_shape(t.init, jax.random.PRNGKey(0), s.hp)
files, depth, deepest = set(), [0], [0]
def profile(frame, event, arg):
    if frame.f_code.co_filename.startswith(pkg):
        if event == "call":
            files.add(os.path.relpath(frame.f_code.co_filename, pkg))
            depth[0] += 1
            deepest[0] = max(deepest[0], depth[0])
        elif event == "return":
            depth[0] -= 1
sys.setprofile(profile)
jax.make_jaxpr(t.epoch)(ts, s.hp)
sys.setprofile(None)
print(json.dumps([sorted(files), deepest[0]]))
"""
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True, cwd=ROOT)
    files, depth = json.loads(out.stdout.strip().splitlines()[-1])
    return files, depth


@pytest.mark.parametrize("preset", ["fast", "fast_dpg"])
def test_one_epoch_runs_through_a_handful_of_files(preset):
    """The model-based (``fast``) and the paper's (``fast_dpg``) epoch: env step → buffer →
    loss → optax update in at most 12 package files, at a call depth of at most 12."""
    files, depth = traced_epoch(preset)
    assert len(files) <= MAX_EPOCH_FILES and depth <= MAX_EPOCH_DEPTH, (len(files), depth, files)
    assert "td3/core.py" in files and ("td3/model_based.py" in files) == (preset == "fast")
    assert ("td3/dpg.py" in files) == (preset == "fast_dpg") and "sim/env.py" in files
