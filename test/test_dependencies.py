"""Dependencies: the runtime requirements are what a running system imports.

torch and pytorch-kinematics (~750 MB) are test requirements only (the independent FK/Jacobian cross-check in
test/support/torch_kinematics.py): no executable's module imports them, requirements.txt and package.xml's
exec_depends do not list them, and test-only helpers (simulated hosts) are not part of the package.

The runtime venv (`make setup`) is requirements.txt, resolved by pip, plus requirements-nodeps.txt installed with
--no-deps (viser, yourdfpy, trimesh, python-fcl declare opencv-python, scipy, scikit-image, embreex, Cython...,
which no part of mds_ach uses). The tests here run in the dev venv, which has more installed (torch pulls scipy
and networkx): they compute the runtime set from the installed metadata and import with every other
distribution's modules blocked, so that what only the dev venv provides cannot hide a missing pin.
"""

from __future__ import annotations

import json
import os
import re
import subprocess
import sys
import xml.etree.ElementTree as ET
from functools import cache
from importlib.metadata import PackageNotFoundError, distribution, distributions, entry_points

import pytest
from packaging.requirements import Requirement
from packaging.utils import canonicalize_name
from support import REPO

TEST_ONLY = ("torch", "pytorch_kinematics")
# What the runtime venv must not contain: together ~500 MB that no node, the bridge or the viewer imports.
HEAVY = ("opencv-python", "scipy", "scikit-image", "embreex", "cython", "torch", "pytorch-kinematics")


def requirement_names(path: str) -> set[str]:
    names = set()
    for line in (REPO / path).read_text().splitlines():
        line = line.split("#", 1)[0].strip()
        if line:
            names.add(re.split(r"[\[=<>~! ]", line, maxsplit=1)[0].lower().replace("_", "-"))
    return names


def requirements(path: str) -> list[Requirement]:
    lines = (raw.split("#", 1)[0].strip() for raw in (REPO / path).read_text().splitlines())
    return [Requirement(line) for line in lines if line]


@cache
def runtime_distributions() -> frozenset[str]:
    """What `make setup` installs: requirements.txt and, through the installed metadata, everything it depends on
    (as pip resolves it), requirements-nodeps.txt without its dependencies, pip, setuptools, mds_ach and the
    interface packages."""
    found = {"pip", "setuptools", "mds-ach"}
    found |= {"mds-ach-interfaces", "control-msgs"}  # built from interfaces/ by make setup (tools/build-interfaces)
    found |= {canonicalize_name(r.name) for r in requirements("requirements-nodeps.txt")}
    todo = [(canonicalize_name(r.name), frozenset(r.extras)) for r in requirements("requirements.txt")]
    done: set[tuple[str, frozenset[str]]] = set()
    while todo:
        name, extras = todo.pop()
        if (name, extras) in done:
            continue
        done.add((name, extras))
        found.add(name)
        try:
            dist = distribution(name)
        except PackageNotFoundError:
            pytest.fail(f"{name} (a runtime dependency) is not installed: run `make dev`")
        for text in dist.requires or []:
            req = Requirement(text)
            if req.marker is None or any(req.marker.evaluate({"extra": e}) for e in (*extras, "")):
                todo.append((canonicalize_name(req.name), frozenset(req.extras)))
    return frozenset(found)


def top_level_names(dist_files: list[str]) -> set[str]:
    """The importable top-level names a distribution's files provide (packages, modules, extension modules)."""
    names = set()
    for path in dist_files:
        first, sep, _rest = path.partition("/")
        if first.startswith(("..", "__pycache__")) or first.endswith((".dist-info", ".egg-info", ".libs", ".data")):
            continue
        if sep:
            names.add(first)
        elif first.endswith((".py", ".so")):
            names.add(first.split(".", 1)[0])
    return names - {""}


def blocked_modules() -> list[str]:
    """Top-level modules that only distributions outside the runtime venv provide (the dev venv has them)."""
    runtime, theirs, ours = runtime_distributions(), set(), set()
    for dist in distributions():
        names = top_level_names([str(f) for f in dist.files or []])
        (ours if canonicalize_name(dist.metadata["Name"]) in runtime else theirs).update(names)
    return sorted(theirs - ours - set(sys.stdlib_module_names))


# Run with `python -c`: argv[1] the blocked top-level names (JSON), argv[2] the code to run as if they were not
# installed (every import finder is wrapped, so optional imports probed with importlib.util.find_spec see None too).
BLOCKING_RUNNER = """
import json, sys
blocked = frozenset(json.loads(sys.argv[1]))
class OnlyRuntime:
    def __init__(self, inner):
        self.inner = inner
    def find_spec(self, name, path=None, target=None):
        if name.partition(".")[0] in blocked:
            return None  # as if not installed: `import` raises, importlib.util.find_spec says None
        return self.inner.find_spec(name, path, target)
    def find_distributions(self, *args, **kwargs):
        return getattr(self.inner, "find_distributions", lambda *a, **k: ())(*args, **kwargs)
    def invalidate_caches(self):
        getattr(self.inner, "invalidate_caches", lambda: None)()
sys.meta_path[:] = [OnlyRuntime(finder) for finder in sys.meta_path]
exec(sys.argv[2])
"""


def run_with_runtime_only(code: str) -> None:
    out = subprocess.run([sys.executable, "-c", BLOCKING_RUNNER, json.dumps(blocked_modules()), code],
                         capture_output=True, text=True, timeout=180, cwd=REPO)
    assert out.returncode == 0, out.stderr[-3000:]


def executable_modules() -> list[str]:
    """The module of every console script the package installs (the nodes, the bridge, the tools)."""
    modules = sorted({ep.module for ep in entry_points(group="console_scripts")
                      if ep.module.split(".")[0] in ("mds_ach", "mds_ach_bridge")})
    assert {"mds_ach.nodes.daemon", "mds_ach.nodes.ik", "mds_ach_bridge.bridge"} <= set(modules), modules
    return modules


def test_runtime_requirements_have_no_torch() -> None:
    runtime, dev = requirement_names("requirements.txt"), requirement_names("requirements-dev.txt")
    assert not {"torch", "pytorch-kinematics"} & runtime
    assert {"torch", "pytorch-kinematics"} <= dev  # still installed for the tests' cross-check
    assert not runtime & dev, "a package pinned twice"


def test_package_xml_declares_torch_for_the_tests_only() -> None:
    root = ET.parse(REPO / "package.xml").getroot()
    exec_deps = {e.text for e in root.iter("exec_depend")}
    test_deps = {e.text for e in root.iter("test_depend")}
    assert not {d for d in exec_deps if "torch" in d}
    assert "python3-torch" in test_deps
    assert {"rclpy", "python3-numpy", "python3-can", "python3-fcl"} <= exec_deps


@pytest.mark.parametrize("module", executable_modules())
def test_executable_imports_no_torch(module: str) -> None:
    """Importing the module behind an executable (what `ros2 run mds_ach <node>` starts) loads no test-only
    package; ``-X importtime`` lists every module the import touched, nested ones included."""
    out = subprocess.run([sys.executable, "-X", "importtime", "-c", f"import {module}"], capture_output=True,
                         text=True, timeout=120)
    assert out.returncode == 0, out.stderr[-2000:]
    imported = {line.rsplit("|", 1)[-1].strip().split(".")[0] for line in out.stderr.splitlines()
                if line.startswith("import time:")}
    assert module.split(".")[0] in imported, "no -X importtime output"
    assert not set(TEST_ONLY) & imported, f"{module} imports {sorted(set(TEST_ONLY) & imported)}"


def test_test_only_modules_are_not_in_the_package() -> None:
    assert not (REPO / "mds_ach" / "netsim.py").exists()
    assert (REPO / "test" / "support" / "netsim.py").exists()
    product = [p for d in ("mds_ach", "mds_ach_bridge") for p in (REPO / d).rglob("*.py")]
    offenders = [str(p.relative_to(REPO)) for p in product
                 if re.search(r"^\s*(import|from)\s+(torch|pytorch_kinematics|support|netsim)\b", p.read_text(), re.M)]
    assert offenders == []


def test_runtime_venv_has_no_heavy_package() -> None:
    """opencv-python, scipy, scikit-image, embreex (viser's and yourdfpy's declared dependencies), Cython
    (python-fcl's build tool) and torch stay out of `make setup`: they made the venv 908 MB."""
    runtime = runtime_distributions()
    assert not runtime & set(HEAVY), f"the runtime venv would contain {sorted(runtime & set(HEAVY))}"
    assert {"viser", "yourdfpy", "trimesh", "python-fcl", "ros-jazzy-rclpy", "numpy"} <= runtime


def test_setup_installs_the_nodeps_list_without_dependencies() -> None:
    """The check above holds only if `make setup` installs requirements-nodeps.txt with --no-deps, and the two lists
    do not overlap (a package in requirements.txt would bring its declared dependencies back)."""
    makefile = (REPO / "Makefile").read_text()
    assert re.search(r"pip install -q --no-deps -r requirements-nodeps\.txt", makefile)
    resolved = {canonicalize_name(r.name) for r in requirements("requirements.txt")}
    assert not resolved & {canonicalize_name(r.name) for r in requirements("requirements-nodeps.txt")}
    assert all(str(r.specifier).startswith("==") for f in ("requirements.txt", "requirements-nodeps.txt")
               for r in requirements(f)), "every runtime requirement is pinned"


def test_blocking_runner_blocks() -> None:
    """The runner below really hides what the runtime venv lacks (scipy comes with torch in the dev venv)."""
    assert "scipy" in blocked_modules() and "torch" in blocked_modules()
    with pytest.raises(AssertionError, match="No module named 'scipy'"):
        run_with_runtime_only("import scipy")


@pytest.mark.parametrize("module", executable_modules())
def test_executable_imports_only_runtime_packages(module: str) -> None:
    run_with_runtime_only(f"import {module}")


def test_viewer_runs_with_only_runtime_packages() -> None:
    """The viewer (`mds-ach viewer`) loads viser, yourdfpy, trimesh and python-fcl, installed without their declared
    dependencies: building its whole scene (robot, ghost, collision primitives, world) on a server must work."""
    run_with_runtime_only(
        "from mds_ach.tools import viewer\n"
        "v = viewer.Viewer(viewer.ViewerOptions(port=viewer.free_port('127.0.0.1')))\n"
        "try:\n    v.tick()\nfinally:\n    v.close()\n"
    )


def test_importing_mds_ach_starts_no_blas_threads() -> None:
    """OpenBLAS worker threads take process-directed signals from the main thread: a console blocked in readline
    then missed Ctrl-C and SIGTERM (a flaky pty test). ``import mds_ach`` before numpy keeps BLAS to one thread."""
    env = {k: v for k, v in os.environ.items() if not k.endswith("_NUM_THREADS")}
    code = "import os, mds_ach, numpy; print(len(os.listdir('/proc/self/task')))"
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env, timeout=60)
    assert proc.returncode == 0 and proc.stdout.strip() == "1", proc.stdout + proc.stderr


def test_make_drops_only_the_resolver_lines_of_the_no_deps_packages() -> None:
    """Issue 28: every fresh `make test` printed pip's "dependency resolver … viser requires …" ERROR for the
    dependencies requirements-nodeps.txt leaves out on purpose. The Makefile drops exactly those lines; a real
    conflict still shows."""
    dry = subprocess.run(["make", "-n", "-W", "requirements-dev.txt", "dev"], cwd=REPO, capture_output=True,
                         text=True, timeout=60)
    line = next(x for x in dry.stdout.splitlines() if "-r requirements-dev.txt" in x)
    pip_filter = line.split("2>&1 |", 1)[1].strip()
    noise = ("ERROR: pip's dependency resolver does not currently take into account all the packages that are "
             "installed. This behaviour is the source of the following dependency conflicts.\n"
             "viser 1.0.0 requires nodeenv<2.0.0,>=1.8.0, which is not installed.\n"
             "viser 1.0.0 requires opencv-python<5.0.0,>=4.0.0.21, which is not installed.\n"
             "trimesh 4.12.2 requires numpy>=1.20, which is not installed.\n")
    real = "rclpy 9.0.0 requires numpy>=2, but you have numpy 1.26.4 which is incompatible.\n"
    out = subprocess.run(["bash", "-c", pip_filter], input=noise + real, capture_output=True, text=True, timeout=30)
    assert out.stdout == real, out.stdout
