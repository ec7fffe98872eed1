"""The package as a stranger gets it: top-level names, shipped data, no path outside the
repository."""

import re
import subprocess
from pathlib import Path

import pytest

import bfpsf
from bfpsf.data import MEASURED, measured_path, measured_sets
from bfpsf.errors import BFPSFInputError

ROOT = Path(__file__).resolve().parents[1]


@pytest.mark.parametrize("name", sorted(set(bfpsf.__all__) - {"__version__"}))
def test_every_exported_name_resolves(name):
    assert getattr(bfpsf, name) is not None


def test_measured_sets_ship_with_their_sources_and_are_small():
    assert list(measured_sets()) == list(MEASURED)
    total = 0
    for name in MEASURED:
        folder = measured_path(name)
        assert (folder / "SOURCE.md").is_file(), name
        files = [path for path in folder.iterdir() if path.is_file()]
        assert len(files) >= 2, name
        total += sum(path.stat().st_size for path in files)
    assert (measured_path("itl3800c002").parent / "INDEX.md").is_file()
    assert total < 200_000


def test_every_shipped_set_states_its_licence_and_citation():
    """Each folder of bfpsf/data/measured (every one, listed in MEASURED or not) has a
    SOURCE.md with a 'Licence:' and a 'Citation:' paragraph that says something."""
    root = measured_path("itl3800c002").parent
    folders = sorted(path for path in root.iterdir() if path.is_dir())
    assert {path.name for path in folders} == {folder for folder, _ in MEASURED.values()}
    for folder in folders:
        text = (folder / "SOURCE.md").read_text()
        for label in ("Licence", "Citation"):
            found = re.search(rf"^{label}: (.+)$", text, flags=re.MULTILINE)
            assert found and len(found.group(1)) > 20, (folder.name, label)
        citation = re.search(r"^Citation: ((?:.+\n)+)", text, flags=re.MULTILINE).group(1)
        assert re.search(r"https://github\.com/\S+", citation), folder.name
        assert re.search(r"commit\s[0-9a-f]{40}", citation), folder.name


def test_measured_path_by_folder_name_and_errors():
    assert measured_path("lage_BF_Kernel_ITL3800C002") == measured_path("itl3800c002")
    with pytest.raises(BFPSFInputError, match="unknown measured data set 'nosuch'"):
        measured_path("nosuch")
    with pytest.raises(BFPSFInputError, match="measured data set 'poisson_ccd' has no file"):
        measured_path("poisson_ccd", "nosuch.txt")


def test_no_file_reads_a_path_outside_the_repository():
    listed = subprocess.run(["git", "ls-files", "*.py", "*.md", "*.toml"], cwd=ROOT,
                            capture_output=True, text=True, check=False)
    if listed.returncode != 0:
        pytest.skip("not a git checkout")  # an installed copy has no tests to check
    outside = re.compile(r"\.\./shared|parents\[2\]|\"\.\.\", \"\.\.\", \"shared\"")
    offenders = [name for name in listed.stdout.split()
                 if (ROOT / name).is_file() and name != "tests/test_package.py"
                 and outside.search((ROOT / name).read_text(errors="replace"))]
    assert offenders == []


def _module_imports(inside_functions=False):
    """{module: the bfpsf modules it imports at module level} (with ``inside_functions``, also
    those it imports when a function runs: the documented optional dependencies and the
    plug-ins' late imports)."""
    import ast

    paths = {}
    for path in (ROOT / "bfpsf").rglob("*.py"):
        parts = path.relative_to(ROOT).with_suffix("").parts
        paths[".".join(parts[:-1] if parts[-1] == "__init__" else parts)] = path
    graph = {}
    for module, path in paths.items():
        package = module if path.name == "__init__.py" else module.rpartition(".")[0]
        edges = set()
        for node in ast.walk(ast.parse(path.read_text())):
            top = inside_functions or getattr(node, "col_offset", None) == 0
            names = []
            if isinstance(node, ast.ImportFrom) and top:
                base = node.module or ""
                if node.level:
                    base = ".".join(package.split(".")[:len(package.split(".")) - node.level + 1]
                                    + ([node.module] if node.module else []))
                names = [f"{base}.{alias.name}" for alias in node.names] + [base]
            elif isinstance(node, ast.Import) and top:
                names = [alias.name for alias in node.names]
            edges |= {name for name in names if name in paths and name != module}
        graph[module] = edges
    return graph, paths


def _cycles(graph):
    """The strongly connected components of more than one node (Tarjan)."""
    index, low, stack, found = {}, {}, [], []

    def visit(node):
        index[node] = low[node] = len(index)
        stack.append(node)
        for other in graph.get(node, ()):
            if other not in index:
                visit(other)
                low[node] = min(low[node], low[other])
            elif other in stack:
                low[node] = min(low[node], index[other])
        if low[node] == index[node]:
            component = []
            while component[-1:] != [node]:
                component.append(stack.pop())
            if len(component) > 1:
                found.append(sorted(component))

    for node in list(graph):
        if node not in index:
            visit(node)
    return found


def test_house_rules_files_and_imports():
    """Issue 24's house rules, kept: a README of at most 200 lines, no module of bfpsf over
    500 lines, no import circle
    between its modules, not even through an import inside a function, and no cycle between
    its subpackages (module-level imports; a package's ``__init__`` re-exports are not
    edges)."""
    readme = (Path(__file__).resolve().parents[1] / "README.md").read_text().splitlines()
    assert len(readme) <= 200, f"README.md has {len(readme)} lines: a guide, not the evidence"
    graph, paths = _module_imports()
    long = {module: n for module, path in paths.items()
            if (n := len(path.read_text().splitlines())) > 500}
    assert not long, f"modules over 500 lines: {long}"

    def between_modules(graph):
        return {module: {other for other in edges if paths[other].name != "__init__.py"}
                for module, edges in graph.items() if paths[module].name != "__init__.py"}

    modules = between_modules(graph)
    assert not _cycles(modules), _cycles(modules)
    when_called = between_modules(_module_imports(inside_functions=True)[0])
    assert not _cycles(when_called), _cycles(when_called)
    packages = {}
    for module, edges in modules.items():
        for other in edges:
            ends = [".".join(name.split(".")[:2]) for name in (module, other)]
            if ends[0] != ends[1] and all(name in paths and paths[name].name == "__init__.py"
                                          for name in ends):
                packages.setdefault(ends[0], set()).add(ends[1])
    assert not _cycles(packages), _cycles(packages)


#: Modules a bfpsf module may import inside a function (docs/DESIGN.md, "Data flow").
LATE_IMPORTS = {"galsim", "photutils", "matplotlib", "piff", "dask", "distributed", "resource"}


def test_imports_at_the_top():
    """Issue 24: a module of bfpsf imports at its top, except what docs/DESIGN.md names: GalSim,
    photutils, matplotlib, the optional extras and ``resource``; the package's modules that
    import GalSim, marked "only when used"; a private module behind a ``try``; the commands
    of ``bfpsf.cli``. Before: 85 imports of astropy, scipy, tqdm and the standard library
    inside functions."""
    import ast

    late = []
    for path in sorted((ROOT / "bfpsf").rglob("*.py")):
        if "cli" in path.relative_to(ROOT / "bfpsf").parts[:1]:
            continue
        source = path.read_text()
        lines = source.splitlines()
        tree = ast.parse(source)
        for function in ast.walk(tree):
            if not isinstance(function, (ast.FunctionDef, ast.AsyncFunctionDef)):
                continue
            guarded = {id(node) for block in ast.walk(function) if isinstance(block, ast.Try)
                       for node in ast.walk(block)}
            for node in ast.walk(function):
                if not isinstance(node, (ast.Import, ast.ImportFrom)) or id(node) in guarded:
                    continue
                if isinstance(node, ast.ImportFrom):
                    name = "bfpsf" if node.level else node.module
                else:
                    name = node.names[0].name
                top = name.split(".")[0]
                if top in LATE_IMPORTS or (top == "bfpsf"
                                           and "only when used" in lines[node.lineno - 1]):
                    continue
                late.append(f"{path.relative_to(ROOT)}:{node.lineno} {name}")
    assert not late, late
