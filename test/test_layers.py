"""The package's layers (issue #16): no lower sub-package imports a higher one, and no import cycle between them.

Order, bottom up: ach < bus < robot < kinematics < net, nodes < tools, record (recordings: check-log reads them,
their plots use check-log). The top-level helper modules (``paths``, ``procs``, ``logformat``) import nothing of
the package and may be used anywhere; ``mds_ach/__init__`` re-exports the public names (from robot) and
``mds_ach.ik`` is an alias of ``kinematics.ik``.
"""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

PACKAGE = Path(__file__).resolve().parents[1] / "mds_ach"
RANK = {"ach": 0, "bus": 1, "robot": 2, "kinematics": 3, "net": 4, "nodes": 4, "tools": 5, "record": 5}
BASE = {"paths", "procs", "logformat"}  # import nothing of mds_ach; usable from every layer


def _imports(path: Path) -> set[str]:
    """Every ``mds_ach.<x>`` this module imports, ``mds_ach`` itself included (as '')."""
    out: set[str] = set()
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            parts = node.module.split(".")
            if parts[0] != "mds_ach":
                continue
            if len(parts) > 1:
                out.add(parts[1])
            else:
                out.update(alias.name for alias in node.names)
        elif isinstance(node, ast.Import):
            for alias in node.names:
                parts = alias.name.split(".")
                if parts[0] == "mds_ach":
                    out.add(parts[1] if len(parts) > 1 else "")
    return out


def _layer(path: Path) -> str:
    rel = path.relative_to(PACKAGE).parts
    return rel[0] if len(rel) > 1 else Path(rel[0]).stem


MODULES = sorted(p for p in PACKAGE.rglob("*.py"))


@pytest.mark.parametrize("path", MODULES, ids=lambda p: str(p.relative_to(PACKAGE)))
def test_no_module_imports_a_higher_layer(path: Path) -> None:
    layer = _layer(path)
    if layer not in RANK:  # __init__, the ik alias, base helpers
        if layer in BASE:
            assert not _imports(path), f"{path.name} must import nothing of mds_ach"
        return
    higher = sorted(x for x in _imports(path) if x in RANK and RANK[x] > RANK[layer])
    assert not higher, f"{path.relative_to(PACKAGE)} ({layer}) imports the higher layer(s) {higher}"
    if "ik" in _imports(path) and RANK[layer] < RANK["kinematics"]:
        raise AssertionError(f"{path.relative_to(PACKAGE)} imports mds_ach.ik (kinematics) from {layer}")
