"""The layout's rules (docs/architecture.md), checked on the source:

* imports point down the layers ``kernels`` -> ``core`` -> ``collision`` -> ``sim`` -> ``scenes``
  -> ``benchmarks``, function-level imports included;
* the module graph has no cycle;
* no private name (``_x``) is imported from another module or read through a module
  (``module._x``);
* every package folder has an ``__init__.py``;
* no block of 12 or more code lines is repeated, no file is over 600 lines unless it holds one
  idea, and docs/architecture.md names files that exist;
* ``warp._src`` is used in one adapter module only, written for the Warp version that
  ``constraints.txt`` pins, and the installed Warp is that version.
"""

from __future__ import annotations

import ast
import os
import re

import pytest

REPO = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
LAYERS = ("kernels", "core", "collision", "sim", "scenes", "benchmarks")
"""Lowest first: a module may import its own layer and the layers before it."""
ADAPTER = "core.warp_adapter"


def _modules() -> dict[str, str]:
    """Module name -> file, for every package of :data:`LAYERS`."""
    out = {}
    for top in LAYERS:
        for folder, dirs, files in os.walk(os.path.join(REPO, top)):
            dirs[:] = [d for d in dirs if not d.startswith((".", "__")) and d != "results"]
            for f in files:
                if f.endswith(".py"):
                    rel = os.path.relpath(os.path.join(folder, f), REPO)[:-3].split(os.sep)
                    if rel[-1] == "__init__":
                        rel = rel[:-1]
                    out[".".join(rel)] = os.path.join(folder, f)
    return out


MODULES = _modules()


def _imports(name: str, path: str):
    """(imported module, imported name or None, line) of every import statement in ``path``."""
    tree = ast.parse(open(path).read(), path)
    package = name if path.endswith("__init__.py") else name.rpartition(".")[0]
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            for alias in node.names:
                yield alias.name, None, node.lineno
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = package.split(".")
                base = base[: len(base) - node.level + 1]
                module = ".".join(base + ([node.module] if node.module else []))
            else:
                module = node.module or ""
            for alias in node.names:
                full = f"{module}.{alias.name}"
                if full in MODULES:  # ``from pkg import submodule``
                    yield full, None, node.lineno
                else:
                    yield module, alias.name, node.lineno


def _layer(module: str) -> int | None:
    top = module.split(".")[0]
    return LAYERS.index(top) if top in LAYERS else None


EDGES = {name: list(_imports(name, path)) for name, path in MODULES.items()}


def test_the_layout_has_every_layer():
    for top in LAYERS:
        assert top in MODULES, f"package {top} is missing"


def test_no_import_goes_up_a_layer():
    bad = []
    for name, edges in EDGES.items():
        for module, _, line in edges:
            target = _layer(module)
            if target is not None and target > _layer(name):
                bad.append(f"{MODULES[name]}:{line} imports {module}")
    assert not bad, "imports that go up a layer:\n" + "\n".join(bad)


def test_the_module_graph_has_no_cycle():
    graph = {name: sorted({m for m, _, _ in edges if m in MODULES and m != name}) for name, edges in EDGES.items()}
    state: dict[str, int] = {}
    stack: list[str] = []

    def visit(node):
        state[node] = 1
        stack.append(node)
        for nxt in graph[node]:
            if state.get(nxt) == 1:
                cycle = stack[stack.index(nxt):] + [nxt]
                raise AssertionError("import cycle: " + " -> ".join(cycle))
            if nxt not in state:
                visit(nxt)
        stack.pop()
        state[node] = 2

    for node in sorted(graph):
        if node not in state:
            visit(node)


def test_no_private_name_is_imported_from_another_module():
    bad = []
    for name, edges in EDGES.items():
        for module, imported, line in edges:
            if imported and imported.startswith("_") and not imported.startswith("__") and _layer(module) is not None:
                bad.append(f"{MODULES[name]}:{line} imports {imported} from {module}")
    assert not bad, "private names imported across modules:\n" + "\n".join(bad)


def test_no_private_name_of_another_module_is_read():
    """``module._x`` where ``module`` is one of the project's modules imported by name (``import
    a.b as m``, ``from a import b``): a private name read across modules, as good as imported."""
    bad = []
    for name, path in MODULES.items():
        tree = ast.parse(open(path).read(), path)
        aliases = set()
        for node in ast.walk(tree):
            if isinstance(node, ast.Import):
                for alias in node.names:
                    if alias.name in MODULES and alias.name != name:
                        aliases.add(alias.asname or alias.name)  # ``import a.b``: read as ``a.b._x``
            elif isinstance(node, ast.ImportFrom) and not node.level and node.module:
                for alias in node.names:
                    if f"{node.module}.{alias.name}" in MODULES:
                        aliases.add(alias.asname or alias.name)
        for node in ast.walk(tree):
            if isinstance(node, ast.Attribute) and node.attr.startswith("_") and not node.attr.startswith("__"):
                try:
                    owner = ast.unparse(node.value)
                except Exception:  # noqa: BLE001 - an expression that is no dotted name
                    continue
                if owner in aliases:
                    bad.append(f"{path}:{node.lineno} reads {owner}.{node.attr}")
    assert not bad, "private names read from another module:\n" + "\n".join(bad)


def test_warp_internals_are_used_in_the_adapter_only():
    users = sorted(name for name, path in MODULES.items() if "warp._src" in open(path).read() and name != ADAPTER)
    users += sorted(os.path.relpath(os.path.join(folder, f), REPO) for folder, _, files in os.walk(os.path.join(REPO, "tests"))
                    for f in files if f.endswith(".py") and f != "test_layers.py"
                    and "warp._src" in open(os.path.join(folder, f)).read())
    assert not users, f"warp._src is used outside {ADAPTER}: {users}"


def test_the_adapter_is_written_for_the_pinned_warp():
    import warp as wp

    from core.warp_adapter import WARP_VERSION, check_warp_version

    pins = re.findall(r"^warp-lang==([\w.]+)", open(os.path.join(REPO, "constraints.txt")).read(), re.M)
    assert pins == [WARP_VERSION], f"constraints.txt must pin warp-lang=={WARP_VERSION}, it pins {pins}"
    if wp.__version__ != WARP_VERSION:
        pytest.fail(f"warp-lang {wp.__version__} is installed; core/warp_adapter.py is written for {WARP_VERSION}")
    check_warp_version()


def test_a_wrong_warp_version_fails_with_a_clear_message(monkeypatch):
    import warp as wp

    from core.warp_adapter import check_warp_version

    monkeypatch.setattr(wp, "__version__", "0.0.1")
    with pytest.raises(RuntimeError, match=r"written for warp-lang .* but 0\.0\.1 is installed.*constraints\.txt"):
        check_warp_version()


DUPLICATE_LINES = 12
"""Longest run of identical code lines (comments, docstrings, imports and blank lines aside) two
places may share without a reason written beside them (``# duplicate: why``)."""

LONG_FILE_LINES = 600
ONE_IDEA = {
    "kernels/roots.py": "the robust root solver of the quadratic and the cubic with its mollified adjoint",
    "sim/contact/replay.py": "the taped replay of the collision response (ContactReplay), one launch sequence",
    "sim/builder.py": "ModelBuilder, one adder per kind of object and finalize()",
    "benchmarks/physics.py": "the physics validation suite: one check per classic closed form",
    "benchmarks/implicit_accuracy.py": "one benchmark: the implicit integrator against converged references",
}
"""Files longer than :data:`LONG_FILE_LINES` that hold one idea, and the idea."""


def _code_lines(path: str) -> list[tuple[int, str]]:
    """(line number, stripped text) of the lines of ``path`` that are code: docstrings, imports,
    comments and blank lines left out."""
    text = open(path).read()
    skip = set()
    for node in ast.walk(ast.parse(text)):
        if isinstance(node, ast.Expr) and isinstance(node.value, ast.Constant) and isinstance(node.value.value, str):
            skip.update(range(node.lineno, node.end_lineno + 1))
        if isinstance(node, (ast.Import, ast.ImportFrom)):
            skip.update(range(node.lineno, node.end_lineno + 1))
    out = []
    for number, line in enumerate(text.splitlines(), 1):
        stripped = line.strip()
        if number in skip or not stripped or stripped.startswith("#"):
            continue
        out.append((number, stripped))
    return out


def test_no_block_of_code_is_duplicated():
    lines = {name: _code_lines(path) for name, path in MODULES.items()}
    seen: dict[tuple, tuple[str, int]] = {}
    duplicates = set()
    for name, rows in sorted(lines.items()):
        for k in range(len(rows) - DUPLICATE_LINES + 1):
            window = tuple(text for _, text in rows[k:k + DUPLICATE_LINES])
            first = seen.setdefault(window, (name, k))
            if first != (name, k):
                other, j = first
                span = [number for number, _ in lines[other][j:j + DUPLICATE_LINES]]
                reason = any("# duplicate:" in line for line in
                             open(MODULES[other]).read().splitlines()[span[0] - 1:span[-1]])
                if not reason:
                    duplicates.add(f"{MODULES[name]}:{rows[k][0]} repeats {MODULES[other]}:{span[0]}")
    assert not duplicates, f"blocks of {DUPLICATE_LINES}+ identical code lines:\n" + "\n".join(sorted(duplicates))


def test_no_file_is_long_unless_it_holds_one_idea():
    long = []
    for name, path in MODULES.items():
        rel = os.path.relpath(path, REPO)
        n = sum(1 for _ in open(path))
        if n > LONG_FILE_LINES and rel not in ONE_IDEA:
            long.append(f"{rel}: {n} lines")
    assert not long, f"files over {LONG_FILE_LINES} lines (split them, or name their one idea in ONE_IDEA):\n" + \
        "\n".join(long)
    for rel in ONE_IDEA:
        assert os.path.exists(os.path.join(REPO, rel)), f"ONE_IDEA names a missing file {rel}"


def test_the_architecture_document_names_files_that_exist():
    """docs/architecture.md describes this tree: every file or folder it names exists, and every
    package of the layout has its row."""
    text = open(os.path.join(REPO, "docs", "architecture.md")).read()
    paths = set(re.findall(r"`((?:kernels|core|collision|sim|scenes|benchmarks|tests)/[\w/.]*)`", text))
    folders = {"kernels", "core", "collision", "sim", "scenes", "benchmarks"}
    # bare file names in the kernels table belong to kernels/
    in_kernels = text[text.index("## Kernels by idea"):text.index("## One substep")]
    paths |= {f"kernels/{name}" for name in re.findall(r"`(\w+\.py)`", in_kernels)}
    missing = sorted(p for p in paths if not os.path.exists(os.path.join(REPO, p)))
    assert not missing, f"docs/architecture.md names files that do not exist: {missing}"
    for folder in folders:
        assert f"`{folder}/`" in text, f"docs/architecture.md has no row for {folder}/"
    assert "docs/architecture.md" in open(os.path.join(REPO, "README.md")).read()


def test_every_package_folder_is_a_regular_package():
    """Each folder of the library layers has an ``__init__.py``: ``pip install`` (setuptools'
    package discovery) leaves a folder without one out of the installed package."""
    missing = []
    for top in ("kernels", "core", "collision", "sim", "scenes"):
        for folder, dirs, files in os.walk(os.path.join(REPO, top)):
            dirs[:] = [d for d in dirs if not d.startswith((".", "__"))]
            if any(f.endswith(".py") for f in files) and "__init__.py" not in files:
                missing.append(os.path.relpath(folder, REPO))
    assert not missing, f"folders without __init__.py: {missing}"


_TAPE_CHECK_SCRIPT = '''
import json, os, sys
os.environ["WARP_CACHE_PATH"] = sys.argv[1]
import warp as wp
wp.config.quiet = True
wp.config.verify_autograd_array_access = True
from core.warp_adapter import reuse_cached_binaries_while_verifying
counts = reuse_cached_binaries_while_verifying()

@wp.kernel
def double(a: wp.array(dtype=float), b: wp.array(dtype=float)):
    i = wp.tid()
    b[i] = 2.0 * a[i]

@wp.kernel
def overwrite(a: wp.array(dtype=float)):
    a[wp.tid()] = 1.0

a = wp.full(4, 3.0, dtype=float, requires_grad=True)
b = wp.zeros(4, dtype=float, requires_grad=True)
with wp.Tape():
    wp.launch(double, 4, inputs=[a], outputs=[b])
    wp.launch(overwrite, 4, inputs=[a])  # the check's warning goes to stderr
print(json.dumps({"b": b.numpy().tolist(), **counts}))
'''


def test_the_tape_check_loads_cached_binaries_and_still_checks(tmp_path):
    """Warp compiles every module again while it checks tapes; the tests' set-up copies the
    binary from the cache instead (:func:`core.warp_adapter.reuse_cached_binaries_while_verifying`).
    A second process with the same cache copies instead of compiling, its kernels compute the same
    values, and the check still catches an array written after a taped launch read it."""
    import json
    import subprocess
    import sys

    script = tmp_path / "tape_check.py"
    script.write_text(_TAPE_CHECK_SCRIPT)
    env = {**os.environ, "PYTHONPATH": REPO + os.pathsep + os.environ.get("PYTHONPATH", "")}
    runs, errors = [], []
    for _ in range(2):
        proc = subprocess.run([sys.executable, str(script), str(tmp_path / "cache")], cwd=tmp_path, env=env,
                              capture_output=True, text=True, timeout=300)
        assert proc.returncode == 0, proc.stderr[-2000:]
        runs.append(json.loads(proc.stdout.splitlines()[-1]))
        errors.append(proc.stderr)
    first, second = runs
    assert (first["compiled"], first["copied"]) == (1, 0)
    assert (second["compiled"], second["copied"]) == (0, 1)
    assert first["b"] == second["b"] == [6.0] * 4
    assert all("is being written to but has already been read from" in err for err in errors)
