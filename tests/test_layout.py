"""The package's shape: imports run one way (pipelines -> stages -> execution -> files), no cycles, no huge files, a public API.

Imports are read with ``ast`` from the source, function-level imports included (they are
imports all the same, only later).
"""
from __future__ import annotations

import ast
from pathlib import Path

import pytest

PACKAGE = Path(__file__).resolve().parents[1] / "sekd_sfm"
#: The longest a source file may grow before it should be split (lines).
MAX_LINES = 700


def _module_name(path: Path) -> str:
    parts = list(path.relative_to(PACKAGE.parent).with_suffix("").parts)
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def _modules() -> dict[str, Path]:
    return {_module_name(path): path for path in sorted(PACKAGE.rglob("*.py"))}


def _imports(name: str, path: Path, modules: dict[str, Path]) -> set[str]:
    """The package's modules that ``name`` imports anywhere in its source."""
    package = name if path.name == "__init__.py" else name.rpartition(".")[0]
    found = set()
    for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
        if isinstance(node, ast.Import):
            found |= {alias.name for alias in node.names}
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = package.split(".")[: len(package.split(".")) - node.level + 1]
                target = ".".join(base + ([node.module] if node.module else []))
            else:
                target = node.module or ""
            found |= {f"{target}.{alias.name}" if f"{target}.{alias.name}" in modules else target
                      for alias in node.names}
    return {module for module in found if module in modules and module != name}


@pytest.fixture(scope="module")
def graph() -> dict[str, set[str]]:
    modules = _modules()
    return {name: _imports(name, path, modules) for name, path in modules.items()}


def _cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """Strongly connected components of more than one module (Tarjan)."""
    index, low, stack, on_stack, found = {}, {}, [], set(), []

    def visit(node: str) -> None:
        index[node] = low[node] = len(index)
        stack.append(node)
        on_stack.add(node)
        for other in graph[node]:
            if other not in index:
                visit(other)
                low[node] = min(low[node], low[other])
            elif other in on_stack:
                low[node] = min(low[node], index[other])
        if low[node] == index[node]:
            component = []
            while True:
                member = stack.pop()
                on_stack.discard(member)
                component.append(member)
                if member == node:
                    break
            if len(component) > 1:
                found.append(sorted(component))

    for node in graph:
        if node not in index:
            visit(node)
    return found


def test_no_import_cycle(graph):
    assert _cycles(graph) == []


def _in(module: str, *packages: str) -> bool:
    return any(module == f"sekd_sfm.{p}" or module.startswith(f"sekd_sfm.{p}.") for p in packages)


#: Each layer and what it must never import: the data flow's later steps, and the layers above it.
FORBIDDEN = {
    "files": ("execution", "stages", "pipelines", "features", "model", "train", "bench", "cli"),
    "execution": ("stages", "pipelines", "features", "model", "train", "bench", "cli"),
    "model": ("execution", "stages", "pipelines", "train", "bench", "cli"),
    "evaluation": ("execution", "stages.extract", "stages.match", "stages.pairs", "pipelines", "train", "bench", "cli"),
    "stages": ("pipelines", "train", "bench", "cli"),
    "pipelines": ("train", "bench", "cli"),
}


@pytest.mark.parametrize("layer", sorted(FORBIDDEN))
def test_imports_run_one_way(graph, layer):
    wrong = sorted(f"{module} -> {other}" for module, others in graph.items() if _in(module, layer)
                   for other in others if _in(other, *FORBIDDEN[layer]))
    assert wrong == []


def test_training_does_not_need_the_benchmarks(graph):
    """Metrics and readers both use live in ``evaluation``; only the release tool runs a benchmark (its guard)."""
    wrong = sorted(f"{module} -> {other}" for module, others in graph.items() if _in(module, "train")
                   for other in others if _in(other, "bench"))
    assert all(name.startswith("sekd_sfm.train.ship -> ") for name in wrong), wrong


def test_stages_reach_ray_only_through_execution(graph):
    """No stage imports the Ray modules themselves: it hands a Stage to an executor."""
    wrong = sorted(f"{module} -> {other}" for module, others in graph.items() if not _in(module, "execution")
                   for other in others if other.startswith("sekd_sfm.execution.ray_"))
    assert wrong == [name for name in wrong if name.startswith("sekd_sfm.cli.doctor")]  # doctor reports Ray's state


def test_no_source_file_is_huge():
    sizes = {str(path.relative_to(PACKAGE.parent)): len(path.read_text(encoding="utf-8").splitlines())
             for path in PACKAGE.rglob("*.py")}
    assert {path: lines for path, lines in sizes.items() if lines > MAX_LINES} == {}


def test_public_api_is_importable_from_the_package():
    """``from sekd_sfm import X`` for every name of ``__all__`` (loaded on first use; modules may move)."""
    import sekd_sfm

    for name in sekd_sfm.__all__:
        assert getattr(sekd_sfm, name) is not None, name
    from sekd_sfm import extract_features
    from sekd_sfm.stages.extract import extract_features as defined

    assert extract_features is defined
    with pytest.raises(AttributeError):
        sekd_sfm.no_such_name  # noqa: B018


def test_the_package_imports_without_torch_until_a_name_is_used():
    """``import sekd_sfm`` (and so ``sekd --help``'s start) does not load the heavy libraries."""
    import subprocess
    import sys

    code = "import sys, sekd_sfm; print('torch' in sys.modules, sekd_sfm.__version__)"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout.split()
    assert out[0] == "False"
    assert out[1].count(".") == 2
