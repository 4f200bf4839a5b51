"""Dependencies: the runtime requirements are what a running system imports.

torch and pytorch-kinematics (~750 MB) are test requirements only (the independent FK/Jacobian cross-check in
test/support/torch_kinematics.py): no executable's module imports them, requirements.txt and package.xml's
exec_depends do not list them, and test-only helpers (simulated hosts) are not part of the package.
"""

from __future__ import annotations

import re
import subprocess
import sys
import xml.etree.ElementTree as ET
from importlib.metadata import entry_points

import pytest
from support import REPO

TEST_ONLY = ("torch", "pytorch_kinematics")


def requirement_names(path: str) -> set[str]:
    names = set()
    for line in (REPO / path).read_text().splitlines():
        line = line.split("#", 1)[0].strip()
        if line:
            names.add(re.split(r"[\[=<>~! ]", line, maxsplit=1)[0].lower().replace("_", "-"))
    return names


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
