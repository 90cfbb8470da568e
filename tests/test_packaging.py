"""Packaging that cannot silently drop a module or a dependency (issue #42, part 4).

Fast (default): every third-party import of ``sekd_sfm`` is declared in ``pyproject.toml`` (a runtime
dependency or an extra), and the packages of the extras (Ray, plotly, OpenVINO/NNCF) are imported only
inside functions, so a plain install imports every module.

Slow (``python -m pytest -q -m slow tests/test_packaging.py``, a step of ``.ci/run``): the wheel is built
from a copy of the tree, installed NON-editably and WITHOUT extras into a fresh virtual environment
(no system site-packages; torch is the release the host runs, the local CPU wheel), and there:
the wheel holds every file of the source package, every module imports, every command and
subcommand of ``sekd`` (enumerated from the click group) answers ``--help``, and the README's quick
start (``sekd reconstruct`` on fountain-P11 at 640 px, then ``sekd export``) runs, recording the
package's version in its output files. The editable dev install of the other tests has every extra
and scipy besides, so it cannot see a missing dependency; this can.
"""
from __future__ import annotations

import ast
import json
import os
import re
import shutil
import subprocess
import sys
import time
import zipfile
from importlib import metadata
from pathlib import Path

import pytest
import tomllib
from conftest import ROOT, SHARED

PACKAGE = "sekd_sfm"
# The packages behind the optional extras: never imported when a module is imported (only inside the
# function that needs them), so a plain install imports every module and names the extra on use.
EXTRA_PACKAGES = {"ray": "ray", "plotly": "viz", "openvino": "int8", "nncf": "int8"}
# Modules that cannot be imported without an extra, with the reason; none today (keep it that way).
NEEDS_EXTRA: dict[str, str] = {}
# Import names whose distribution is named otherwise, for when the distribution is not installed here.
KNOWN_DISTRIBUTIONS = {"PIL": "pillow", "cv2": "opencv-python-headless", "yaml": "pyyaml", "sklearn": "scikit-learn"}


def _norm(name: str) -> str:
    return re.sub(r"[-_.]+", "-", name).lower()


def _requirement_name(requirement: str) -> str:
    return _norm(re.split(r"[\s<>=!~;\[(]", requirement.strip(), maxsplit=1)[0])


def _project(root: Path = ROOT) -> dict:
    return tomllib.loads((root / "pyproject.toml").read_text())["project"]


def _imports(path: Path) -> list[tuple[str, bool]]:
    """(top-level module, imported when the module is imported) of every absolute import in ``path``."""
    found = []

    def visit(node: ast.AST, at_import: bool) -> None:
        for child in ast.iter_child_nodes(node):
            lazy = isinstance(child, (ast.FunctionDef, ast.AsyncFunctionDef, ast.Lambda))
            if isinstance(child, ast.If) and "TYPE_CHECKING" in ast.unparse(child.test):
                lazy = True
            if isinstance(child, ast.Import):
                found.extend((alias.name.split(".")[0], at_import) for alias in child.names)
            elif isinstance(child, ast.ImportFrom) and not child.level and child.module:
                found.append((child.module.split(".")[0], at_import))
            visit(child, at_import and not lazy)

    visit(ast.parse(path.read_text(encoding="utf-8")), True)
    return found


def _third_party_imports() -> dict[str, list[tuple[str, bool]]]:
    """Top-level module -> [(file, imported at import time)] for every non-stdlib, non-own import."""
    own = {PACKAGE} | {p.name for p in ROOT.iterdir() if (p / "__init__.py").is_file()}
    imports: dict[str, list[tuple[str, bool]]] = {}
    for path in sorted((ROOT / PACKAGE).rglob("*.py")):
        for top, at_import in _imports(path):
            if top in sys.stdlib_module_names or top in own or top == "__future__":
                continue
            imports.setdefault(top, []).append((str(path.relative_to(ROOT)), at_import))
    return imports


def _distributions(top: str, installed: dict[str, list[str]]) -> set[str]:
    names = installed.get(top) or [KNOWN_DISTRIBUTIONS.get(top, top)]
    return {_norm(n) for n in names}


def test_every_third_party_import_is_declared():
    """A dependency or an extra for every import (what ../shared/tools/undeclared.py checks)."""
    project = _project()
    runtime = {_requirement_name(r) for r in project["dependencies"]}
    extras = {_requirement_name(r) for reqs in project.get("optional-dependencies", {}).values() for r in reqs}
    installed = metadata.packages_distributions()
    undeclared = {top: files[0][0] for top, files in _third_party_imports().items()
                  if not _distributions(top, installed) & (runtime | extras)}
    assert not undeclared, f"imported but declared nowhere in pyproject.toml: {undeclared}"


def test_only_the_extras_packages_are_optional():
    """Whatever a module imports when it is imported is a runtime dependency, not only an extra."""
    project = _project()
    runtime = {_requirement_name(r) for r in project["dependencies"]}
    installed = metadata.packages_distributions()
    for package, extra in EXTRA_PACKAGES.items():
        assert _norm(package) in {_requirement_name(r) for r in project["optional-dependencies"][extra]}
    eager_optional = {}
    for top, files in _third_party_imports().items():
        if _distributions(top, installed) & runtime:
            continue
        for file, at_import in files:
            module = file.removesuffix(".py").removesuffix("/__init__").replace("/", ".")
            if at_import and module not in NEEDS_EXTRA:
                eager_optional.setdefault(top, []).append(file)
    assert not eager_optional, ("modules import an optional package when they are imported (import it inside "
                                f"the function that needs it, or list the module in NEEDS_EXTRA): {eager_optional}")


# --- a non-editable install without extras in a fresh virtual environment (slow) -------------------

class Venv:
    """The fresh environment, the wheel and the copy of the tree it was built from (one snapshot: the
    working tree may change while the test runs)."""

    def __init__(self, path: Path, src: Path, wheel: Path, work: Path, timings: dict[str, float]):
        self.path, self.src, self.wheel, self.work, self.timings = path, src, wheel, work, timings
        self.version = re.search(r'^__version__ = "([^"]+)"', (src / PACKAGE / "__init__.py").read_text(), re.M)[1]
        self.python = path / "bin/python"
        self.env = {k: v for k, v in os.environ.items()
                    if k not in {"PYTHONPATH", "PYTHONHOME", "PYTHONSTARTUP", "VIRTUAL_ENV", "PYTHONSAFEPATH"}}
        self.env.update(VIRTUAL_ENV=str(path), PATH=f"{path / 'bin'}{os.pathsep}{os.environ.get('PATH', '')}",
                        SEKD_SHARED=str(SHARED), MPLCONFIGDIR=str(work / "mpl"), PIP_NO_INPUT="1")

    def run(self, *args, timeout: float = 600, check: bool = True) -> subprocess.CompletedProcess:
        done = subprocess.run(list(map(str, args)), cwd=self.work, env=self.env, capture_output=True, text=True,
                              timeout=timeout, stdin=subprocess.DEVNULL)
        if check and done.returncode != 0:
            pytest.fail(f"{' '.join(map(str, args))} exited {done.returncode}\n{done.stdout[-4000:]}\n{done.stderr[-4000:]}")
        return done

    def python_json(self, script: str, timeout: float = 600):
        return json.loads(self.run(self.python, "-c", script, timeout=timeout).stdout.strip().splitlines()[-1])


def _copy_source(dest: Path) -> Path:
    """What a build from a checkout reads: the top-level files and the package (no caches, no .git)."""
    dest.mkdir()
    for path in ROOT.iterdir():
        if path.is_file():
            shutil.copy2(path, dest / path.name)
    shutil.copytree(ROOT / PACKAGE, dest / PACKAGE, ignore=shutil.ignore_patterns("__pycache__", "*.pyc"))
    return dest


@pytest.fixture(scope="module")
def venv(tmp_path_factory) -> Venv:
    import torch

    base = tmp_path_factory.mktemp("packaging")
    timings: dict[str, float] = {}
    pip_env = {**os.environ, "PIP_NO_INPUT": "1"}
    pip_env.pop("PYTHONPATH", None)

    def step(name, args):
        start = time.monotonic()
        done = subprocess.run(list(map(str, args)), cwd=base, env=pip_env, capture_output=True, text=True,
                              timeout=1200, stdin=subprocess.DEVNULL)
        timings[name] = round(time.monotonic() - start, 1)
        if done.returncode != 0:
            pytest.fail(f"{name}: {' '.join(map(str, args))} exited {done.returncode}\n"
                        f"{done.stdout[-4000:]}\n{done.stderr[-4000:]}")

    src = _copy_source(base / "src")
    step("wheel", [sys.executable, "-m", "pip", "wheel", "--no-deps", "-w", base / "dist", src])
    (wheel,) = (base / "dist").glob("*.whl")
    step("venv", [sys.executable, "-m", "venv", base / "venv"])  # no --system-site-packages
    python = base / "venv/bin/python"
    # The torch this host runs, by its exact version (2.13.0+cpu: the local CPU wheel; never PyPI's CUDA build).
    step("torch", [python, "-m", "pip", "install", f"torch=={torch.__version__}"])
    step("install", [python, "-m", "pip", "install", wheel])  # non-editable, no extras
    work = base / "work"
    work.mkdir()
    yield Venv(base / "venv", src, wheel, work, timings)
    print(f"\nfresh-venv timings (s): {timings}")
    shutil.rmtree(base, ignore_errors=True)  # ~1.5 GB


@pytest.mark.slow
@pytest.mark.timeout(2400)
def test_wheel_holds_every_file_of_the_package(venv):
    __version__ = venv.version
    source = {str(p.relative_to(venv.src)) for p in (venv.src / PACKAGE).rglob("*")
              if p.is_file() and "__pycache__" not in p.parts and p.suffix != ".pyc"}
    with zipfile.ZipFile(venv.wheel) as wheel:
        names = set(wheel.namelist())
        info = next(n for n in names if n.endswith(".dist-info/METADATA"))
        meta = wheel.read(info).decode()
    assert not source - names, f"files of {PACKAGE}/ missing from the wheel: {sorted(source - names)}"
    assert venv.wheel.name.startswith(f"sekd_sfm-{__version__}-"), venv.wheel.name
    assert f"\nVersion: {__version__}\n" in meta
    runtime = {_requirement_name(r[len("Requires-Dist: "):]) for r in meta.splitlines()
               if r.startswith("Requires-Dist: ") and "extra ==" not in r}
    assert runtime == {_requirement_name(r) for r in _project(venv.src)["dependencies"]}


@pytest.mark.slow
@pytest.mark.timeout(2400)
def test_fresh_venv_has_the_dependencies_and_no_extra(venv):
    venv.run(venv.python, "-m", "pip", "check")
    found = venv.python_json("import importlib.util, json; print(json.dumps({m: importlib.util.find_spec(m) is not None "
                             f"for m in {sorted(EXTRA_PACKAGES) + ['pytest']}}}))")
    assert not any(found.values()), f"the fresh venv is not without extras: {found}"
    assert venv.run(venv.python, "-m", "pip", "show", "sekd-sfm").stdout.count("Editable project location") == 0


IMPORT_ALL = r"""
import importlib, json, sys, traceback
from pathlib import Path
import sekd_sfm
root = Path(sekd_sfm.__file__).parent
names = sorted(".".join(("sekd_sfm",) + p.relative_to(root).with_suffix("").parts).removesuffix(".__init__")
               for p in root.rglob("*.py"))
failed = {}
for name in names:
    try:
        importlib.import_module(name)
    except BaseException as exc:
        failed[name] = "".join(traceback.format_exception_only(exc)).strip()
print(json.dumps({"file": sekd_sfm.__file__, "version": sekd_sfm.__version__, "modules": names, "failed": failed,
                  "extras_loaded": sorted(m for m in EXTRAS if m in sys.modules)}))
"""


@pytest.mark.slow
@pytest.mark.timeout(2400)
def test_every_module_imports_without_extras(venv):
    __version__ = venv.version
    report = venv.python_json(f"EXTRAS = {sorted(EXTRA_PACKAGES)!r}\n" + IMPORT_ALL)
    assert Path(report["file"]).is_relative_to(venv.path), f"sekd_sfm imported from {report['file']}, not the venv"
    assert report["version"] == __version__
    source = {".".join((PACKAGE,) + p.relative_to(venv.src / PACKAGE).with_suffix("").parts).removesuffix(".__init__")
              for p in (venv.src / PACKAGE).rglob("*.py")}
    assert set(report["modules"]) == source
    unexpected = {m: e for m, e in report["failed"].items() if m not in NEEDS_EXTRA}
    assert not unexpected, f"modules that do not import in a plain install: {unexpected}"
    assert not report["extras_loaded"]


HELP_ALL = r"""
import json
import click
from click.testing import CliRunner
from sekd_sfm.cli.main import sekd

def walk(command, path):
    yield path
    if isinstance(command, click.Group):
        ctx = click.Context(command, info_name="sekd")
        for name in command.list_commands(ctx):
            yield from walk(command.get_command(ctx, name), path + [name])

runner = CliRunner()
results = {}
for path in walk(sekd, []):
    out = runner.invoke(sekd, path + ["--help"], prog_name="sekd")
    results[" ".join(path)] = {"exit": out.exit_code, "usage": out.output[:200],
                               "options": "Show this message and exit." in out.output,
                               "error": None if out.exception is None or isinstance(out.exception, SystemExit)
                               else repr(out.exception)}
print(json.dumps(results))
"""


@pytest.mark.slow
@pytest.mark.timeout(2400)
def test_every_command_answers_help(venv):
    __version__ = venv.version
    top = venv.run("sekd", "--help").stdout  # the installed console script
    assert "Usage: sekd" in top
    assert __version__ in venv.run("sekd", "--version").stdout
    results = venv.python_json(HELP_ALL)
    assert {"extract", "pairs", "match", "reconstruct", "export", "doctor", "bench"} <= set(results)
    assert any(" " in name for name in results), "no subcommand of a group was found"
    bad = {name: r for name, r in results.items() if r["exit"] != 0 or r["error"]
           or not r["usage"].startswith(f"Usage: sekd {name}".rstrip()) or not r["options"]}
    assert not bad, f"commands whose --help fails in a plain install: {bad}"


@pytest.mark.slow
@pytest.mark.timeout(2400)
def test_quick_start_runs_in_a_plain_install(venv):
    __version__ = venv.version
    images = SHARED / "data/sfm/fountain-P11/images"
    if not images.is_dir():
        pytest.skip(f"{images} not found (set SEKD_SHARED)")
    doctor = venv.run("sekd", "doctor").stdout
    assert re.search(rf"^sekd_sfm\s+{re.escape(__version__)}$", doctor, re.M), doctor
    assert str(venv.path) in doctor  # the embedded model is read from the installed package

    out = venv.work / "fountain"
    start = time.monotonic()
    venv.run("sekd", "reconstruct", images, "-o", out, "--resize-max", "640", "--no-progress", timeout=1200)
    venv.timings["reconstruct"] = round(time.monotonic() - start, 1)
    venv.run("sekd", "export", out / "model", "-o", out / "points.ply", "--format", "ply")
    # A command that needs an extra names it, in one line, instead of a traceback.
    html = venv.run("sekd", "export", out / "model", "-o", out / "model.html", "--format", "html", check=False)
    assert html.returncode == 1 and 'pip install "sekd-sfm[viz]"' in html.stderr, html.stderr
    assert "Traceback" not in html.stderr

    stats = json.loads((out / "stats.json").read_text())
    assert stats["status"] == "ok", stats.get("failure")
    assert stats["model"]["registered_images"] >= 9, stats["model"]  # 11 of 11 at 640 px
    assert stats["refine"], "the default keypoint refinement (scipy) did not run"
    assert (out / "points.ply").stat().st_size > 1000
    # The version of the package is recorded in the output files.
    assert stats["versions"]["sekd_sfm"] == __version__
    recorded = venv.python_json(
        "import h5py, json; print(json.dumps({n: str(h5py.File(f'fountain/{n}', 'r').attrs.get('versions', ''))"
        " for n in ('features.h5', 'matches.h5')}))")
    for name, versions in recorded.items():
        assert f'"sekd_sfm": "{__version__}"' in versions, (name, versions)
