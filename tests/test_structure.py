"""The house's structure rules, enforced: no import circle and no arrow back up, the engine alone runs optimisers,
the package is subpackages (not loose modules), tests mirror it, and no function or module grows past its size."""

import ast
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
PACKAGE = ROOT / "lfgraph"


def _module_imports(path: Path) -> set[str]:
    """lfgraph modules imported anywhere in the file — at module level and inside functions (a lazy import hides a
    circle, it does not remove it) — except in TYPE_CHECKING blocks; ``from lfgraph.a import b`` counts as
    importing ``lfgraph.a`` and, where ``b`` is a submodule, ``lfgraph.a.b``."""
    tree = ast.parse(path.read_text(encoding="utf-8"))
    typing_only = {id(n) for node in ast.walk(tree)
                   if isinstance(node, ast.If) and "TYPE_CHECKING" in ast.dump(node.test) for n in ast.walk(node)}
    found = set()
    for node in ast.walk(tree):
        if id(node) in typing_only:
            continue
        if isinstance(node, ast.ImportFrom) and node.module and node.module.startswith("lfgraph"):
            found.add(node.module)
            found.update(f"{node.module}.{a.name}" for a in node.names)
        elif isinstance(node, ast.Import):
            found.update(a.name for a in node.names if a.name.startswith("lfgraph"))
    return found


def _all_imports(path: Path) -> set[str]:
    tree = ast.parse(path.read_text(encoding="utf-8"))
    names = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.ImportFrom) and node.module:
            names.add(node.module)
        elif isinstance(node, ast.Import):
            names.update(a.name for a in node.names)
    return names


def test_import_graph_has_no_circle_and_no_arrow_back_up():
    package = PACKAGE
    modules = {}
    for path in package.rglob("*.py"):
        name = ".".join(path.relative_to(ROOT).with_suffix("").parts).removesuffix(".__init__")
        modules[name] = path
    graph = {m: {i for i in _module_imports(p) if i in modules and i != m} for m, p in modules.items()}
    # allow-listed: the top (the CLI, ``python -m lfgraph``) and the package's lazy attribute table, which name
    # everything below them by design
    for top in [m for m in graph if m.startswith("lfgraph.cli") or m in ("lfgraph", "lfgraph.__main__")]:
        graph[top] = set()
    # the core never reaches up into the CLI or the viewer, and only lfgraph.viz imports rerun
    for m, p in modules.items():
        names = _all_imports(p)
        if not m.startswith("lfgraph.cli") and m != "lfgraph.__main__":  # python -m lfgraph runs the CLI
            assert not any(n.startswith("lfgraph.cli") for n in names), f"{m} imports the CLI"
            assert "argparse" not in names, f"{m} imports argparse"
        if not m.startswith("lfgraph.viz"):
            assert not any(n.split(".")[0] == "rerun" for n in names), f"{m} imports rerun"
        # the CLI and the demo (a CLI job) sit on top; figures (matplotlib) are a leaf any layer may use
        if not m.startswith(("lfgraph.viz", "lfgraph.cli", "lfgraph.cli.demo")):
            assert "lfgraph.viz.rerun_log" not in names, f"{m} (the core) imports the rerun logger"
    # no circle among module-level imports (depth-first search)
    state: dict[str, int] = {}

    def visit(m: str, stack: list[str]) -> None:
        state[m] = 1
        for n in graph[m]:
            if state.get(n) == 1:
                raise AssertionError("import circle: " + " -> ".join([*stack, m, n]))
            if n not in state:
                visit(n, [*stack, m])
        state[m] = 2

    for m in graph:
        if m not in state:
            visit(m, [])


MAX_FUNCTION_LINES = 80  # issue 26: a function longer than this does more than one thing
MAX_MODULE_LINES = 400  # ... and a module longer than this holds more than one subject


def test_no_function_over_80_lines_and_no_module_over_400():
    too_long = []
    for path in PACKAGE.rglob("*.py"):
        text = path.read_text(encoding="utf-8")
        if text.count("\n") > MAX_MODULE_LINES:
            too_long.append(f"{path.relative_to(ROOT)}: {text.count(chr(10))} lines")
        for node in ast.walk(ast.parse(text)):
            if isinstance(node, ast.FunctionDef | ast.AsyncFunctionDef):
                n = node.end_lineno - node.lineno + 1
                if n > MAX_FUNCTION_LINES:
                    too_long.append(f"{path.relative_to(ROOT)}:{node.lineno} {node.name}: {n} lines")
    assert not too_long, "; ".join(too_long)


MAX_TOP_MODULES = 10  # issue 39: modules directly in lfgraph/ (the rest live in subpackages named after their job)
# the GTSAM names that run an optimisation or read a posterior: only lfgraph.engine may call them
ENGINE_ONLY = {"LevenbergMarquardtOptimizer", "GaussNewtonOptimizer", "DoglegOptimizer", "NonlinearOptimizer",
               "LevenbergMarquardtParams", "GaussNewtonParams", "DoglegParams", "Marginals", "ISAM2"}


def test_the_package_is_subpackages_each_saying_what_it_holds():
    top = sorted(p.name for p in PACKAGE.glob("*.py"))
    assert len(top) <= MAX_TOP_MODULES, f"{len(top)} modules directly in lfgraph/: {top}"
    for init in PACKAGE.glob("*/__init__.py"):
        assert ast.get_docstring(ast.parse(init.read_text(encoding="utf-8"))), f"{init.relative_to(ROOT)}: no docstring"


def test_only_the_engine_runs_an_optimiser_or_reads_marginals():
    offenders = []
    for path in PACKAGE.rglob("*.py"):
        if path.is_relative_to(PACKAGE / "engine"):
            continue
        for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
            name = node.attr if isinstance(node, ast.Attribute) else node.name if isinstance(node, ast.alias) else None
            if name in ENGINE_ONLY:
                offenders.append(f"{path.relative_to(ROOT)}:{node.lineno} {name}")
    assert not offenders, "; ".join(offenders)


def test_tests_mirror_the_package():
    packages = {p.name for p in PACKAGE.iterdir() if (p / "__init__.py").exists()} | {"benchmarks"}
    folders = {p.name for p in (ROOT / "tests").iterdir() if p.is_dir() and p.name not in ("data", "__pycache__")}
    assert folders <= packages, f"test folders naming no package: {sorted(folders - packages)}"


MAX_FILES_NAMING_A_LENS = 3  # outside the lens package, interop (file formats name models) and cli (their flags)
LENS_EDGES = ("lenses", "interop", "cli")


def _names_a_lens(path: Path, names: set[str], identifiers: set[str]) -> bool:
    """Whether the module names a lens model: its name or its GTSAM class as a string, an attribute (``gtsam.Cal3DS2``)
    or one of the models' name constants (``RADTAN``)."""
    for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
        if isinstance(node, ast.Constant) and isinstance(node.value, str) and node.value in names:
            return True
        if isinstance(node, ast.Attribute) and (node.attr in names or node.attr in identifiers):
            return True
        if isinstance(node, ast.Name | ast.alias) and getattr(node, "id", getattr(node, "name", None)) in identifiers:
            return True
    return False


def test_a_lens_model_is_named_in_few_files():
    """Adding a lens is one module in `lfgraph.lenses` and one registration line: the rest asks the registry. Only a
    few places choose among models by name (the lens choice, a wide-board detector's rough fisheye, a named scene)."""
    from lfgraph.lenses import lens_model, lens_names

    names = set(lens_names()) | {lens_model(n).gtsam_name for n in lens_names()}
    identifiers = {n.upper() for n in lens_names()}
    naming = sorted(str(p.relative_to(ROOT)) for p in PACKAGE.rglob("*.py")
                    if p.relative_to(PACKAGE).parts[0] not in LENS_EDGES and _names_a_lens(p, names, identifiers))
    assert len(naming) <= MAX_FILES_NAMING_A_LENS, naming
