"""The package layout (docs/architecture.md): every import goes to the same or a lower layer,
module-level imports have no cycles, ``extract`` imports only the log, the mapping and the
planner interface (plus configuration, files and the execution layer), and ``deft_gym/`` holds
packages plus two cross-cutting modules (the third cross-cutting part, ``deft_gym.execution``, is a
package), each package either simulation code (in the code fingerprint) or named as not."""

from __future__ import annotations

import ast
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent

# lowest first; a module may import its own layer and those below it
LAYERS: list[tuple[str, ...]] = [
    # cross-cutting leaves: configuration files, atomic writes, the execution layer, the
    # command-line conventions
    ("deft_gym.config", "deft_gym.files", "deft_gym.execution", "deft_gym.cli.common", "deft_gym.models"),
    ("deft_gym.world",),
    ("deft_gym.bus",),
    ("deft_gym.record",),
    ("deft_gym.planner",),
    ("deft_gym.modules",),
    ("deft_gym.scenarios",),
    ("deft_gym.sim",),
    ("extract",),
    # the search support; an episode's log drawn (viz) or written in standard formats (export)
    ("deft_gym.search", "deft_gym.viz", "deft_gym.export"),
    # driving-quality metrics of an episode from its trace (issue 33): they read the trace and
    # the collision fault of deft_gym.search; the env, the baselines and the programs read them
    ("deft_gym.metrics",),
    ("deft_gym.envs",),
    # ASTAA, and its command (deft_gym.robustness.stress)
    ("deft_gym.robustness",),
    # the adversaries and their evaluation
    ("agents",),
    # DeFT's research questions
    ("deft_gym.experiments",),
    # the console script, the simulation's programs and the tools (the demo runs everything)
    ("deft_gym.cli",),
]
# what extract may import of deft_gym: the log (bus messages and their codec), the planner
# interface (and trajectory measures), configuration, file helpers and the execution layer
EXTRACT_MAY_IMPORT = ("deft_gym.bus.codec", "deft_gym.bus.ros1", "deft_gym.bus.messages", "deft_gym.planner.base",
                      "deft_gym.planner.trajectory", "deft_gym.config", "deft_gym.files", "deft_gym.execution",
                      "deft_gym.cli.common")
# the cross-cutting layer 0 imports nothing of deft_gym above it
LAYER0_MAY_IMPORT = ("deft_gym.config", "deft_gym.files", "deft_gym.execution", "deft_gym.cli.common")
TOP_LEVEL_MODULES = {"__init__.py", "config.py", "files.py"}
# the packages of deft_gym/ that code_fingerprint hashes (deft_gym.search.trace): a changed file
# in them makes cached reference runs and evaluation records stale; every other package is named
# in its _NOT_SIMULATION_PACKAGES
SIMULATION_PACKAGES = {"world", "bus", "record", "planner", "modules", "scenarios", "sim"}
OWN = ("deft_gym", "extract", "agents")


def layer(module: str) -> int | None:
    """The layer of the longest prefix that names ``module`` (``deft_gym.cli.common`` is in
    layer 0, the rest of ``deft_gym.cli`` higher up)."""
    best: tuple[int, int] | None = None
    for i, prefixes in enumerate(LAYERS):
        for p in prefixes:
            if (module == p or module.startswith(p + ".")) and (best is None or len(p) > best[0]):
                best = (len(p), i)
    return None if best is None else best[1]


def module_name(path: Path) -> str:
    parts = list(path.relative_to(ROOT).with_suffix("").parts)
    if parts[-1] == "__init__":
        parts.pop()
    return ".".join(parts)


def sources() -> list[Path]:
    return sorted(p for pkg in OWN for p in (ROOT / pkg).rglob("*.py"))


def imports(path: Path, top_level_only: bool = False) -> list[tuple[str, int]]:
    """``(module, line)`` of every import of the project's own packages in ``path``; with
    ``top_level_only`` only those run at import time (not in functions or TYPE_CHECKING)."""
    tree = ast.parse(path.read_text())
    nodes: list[ast.AST] = []
    if top_level_only:
        todo = list(tree.body)
        while todo:
            n = todo.pop()
            if isinstance(n, ast.If) and "TYPE_CHECKING" in ast.unparse(n.test):
                continue
            if isinstance(n, ast.If | ast.Try | ast.With):
                todo += [c for c in ast.iter_child_nodes(n) if isinstance(c, ast.stmt)]
            nodes.append(n)
    else:
        nodes = list(ast.walk(tree))
    out = []
    pkg = module_name(path) if path.name == "__init__.py" else module_name(path).rpartition(".")[0]
    for n in nodes:
        if isinstance(n, ast.Import):
            out += [(a.name, n.lineno) for a in n.names]
        elif isinstance(n, ast.ImportFrom):
            base = n.module or ""
            if n.level:
                base = ".".join(pkg.split(".")[: len(pkg.split(".")) - n.level + 1] + ([base] if base else []))
            out += [(f"{base}.{a.name}" if _is_module(f"{base}.{a.name}") else base, n.lineno) for a in n.names]
    return [(m, line) for m, line in out if m.split(".")[0] in OWN]


def _is_module(dotted: str) -> bool:
    p = ROOT.joinpath(*dotted.split("."))
    return p.with_suffix(".py").exists() or (p / "__init__.py").exists() or any(p.parent.glob(p.name + ".*.so"))


def test_every_import_goes_to_the_same_or_a_lower_layer() -> None:
    bad = []
    for path in sources():
        me = module_name(path)
        if me == "deft_gym":  # the package root registers the Gymnasium envs (envs/__init__: gymnasium only)
            continue
        mine = layer(me)
        assert mine is not None, f"{me}: in no layer of tests/test_layout.py (and docs/architecture.md)"
        for target, line in imports(path):
            theirs = layer(target)
            assert theirs is not None, f"{me}:{line} imports {target}, which is in no layer"
            if theirs > mine:
                bad.append(f"{path.relative_to(ROOT)}:{line}: {me} (layer {mine}) imports {target} (layer {theirs})")
    assert bad == []


def test_extract_imports_only_the_log_the_mapping_and_the_planner_interface() -> None:
    bad = [f"{p.relative_to(ROOT)}:{line}: {t}" for p in sorted((ROOT / "extract").rglob("*.py"))
           for t, line in imports(p) if t.startswith("deft_gym") and not t.startswith(EXTRACT_MAY_IMPORT)]
    assert bad == []


def test_no_import_cycles_between_modules() -> None:
    graph = {module_name(p): {t for t, _ in imports(p, top_level_only=True)} for p in sources()}
    graph = {m: {t for t in ts if t in graph and t != m} for m, ts in graph.items()}
    state: dict[str, int] = {}
    cycles: list[list[str]] = []

    def visit(m: str, stack: list[str]) -> None:
        state[m] = 1
        for t in sorted(graph[m]):
            if state.get(t) == 1:
                cycles.append([*stack[stack.index(t):], t])
            elif t not in state:
                visit(t, [*stack, t])
        state[m] = 2

    for m in sorted(graph):
        if m not in state:
            visit(m, [m])
    # a package's __init__ re-exporting its own modules is no cycle
    cycles = [c for c in cycles if not all(x == c[0] or x.startswith(c[0] + ".") or c[0].startswith(x + ".")
                                          for x in c)]
    assert cycles == []


def test_execution_layer_imports_only_config_and_files() -> None:
    bad = [f"{p.relative_to(ROOT)}:{line}: {t}" for p in sorted((ROOT / "deft_gym" / "execution").rglob("*.py"))
           for t, line in imports(p) if not t.startswith(LAYER0_MAY_IMPORT)]
    assert bad == []


def test_deft_gym_top_level_holds_packages_and_two_cross_cutting_modules() -> None:
    pkg = ROOT / "deft_gym"
    modules = {p.name for p in pkg.iterdir() if p.is_file() and p.suffix in {".py", ".c"}}
    assert modules == TOP_LEVEL_MODULES
    for d in sorted(p for p in pkg.iterdir() if p.is_dir() and p.name != "__pycache__"):
        init = d / "__init__.py"
        assert init.exists(), f"{d.name}: not a package"
        doc = ast.get_docstring(ast.parse(init.read_text()))
        assert doc and len(doc) > 40, f"deft_gym/{d.name}/__init__.py: no docstring saying what it holds"
    from deft_gym.search.trace import _NOT_SIMULATION_PACKAGES

    packages = {p.name for p in pkg.iterdir() if (p / "__init__.py").exists()}
    unnamed = packages - SIMULATION_PACKAGES - set(_NOT_SIMULATION_PACKAGES)
    assert unnamed == set(), (f"packages of deft_gym/ {sorted(unnamed)}: simulation code (SIMULATION_PACKAGES here) or not "
                              "(deft_gym.search.trace._NOT_SIMULATION_PACKAGES, outside the code fingerprint)?")
    assert not SIMULATION_PACKAGES & set(_NOT_SIMULATION_PACKAGES)
