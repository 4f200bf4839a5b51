"""Programs written for the original MDS-Ach run against this stack (issue #18 §3 header, §6 Python): a C client
that includes only ``mds.h`` (built against include/mds.h and the project's libach), and the paper's Python
examples with exactly one line changed (``import ach`` -> ``from mds_ach import ach``). Each is checked by the
motion it caused on the simulated robot (measured positions on mds-state), not by its own output.

The programs are in test/original_clients/ (see its README.md).
"""

from __future__ import annotations

import difflib
import os
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest
from support import REPO, VENV_BIN, libach, wait_for
from support.system import arm_pos, chain_fk, joint_pos, running_system

CLIENTS = REPO / "test" / "original_clients"
ORIGINAL_IMPORT = "import ach"
DROP_IN_IMPORT = "from mds_ach import ach"
TARGET = np.array([0.3, 0.2, 0.0])  # the paper's IK target for the left hand


@pytest.fixture(scope="module")
def system(tmp_path_factory: pytest.TempPathFactory) -> Iterator[dict[str, str]]:
    with running_system(tmp_path_factory.mktemp("original")) as env:
        yield env


def left_hand() -> np.ndarray:
    return chain_fk(arm_pos("left"), "left")[0]


def port(name: str, dest: Path) -> Path:
    """The listing with its one changed line; asserts that nothing else differs."""
    original = (CLIENTS / name).read_text().splitlines(keepends=True)
    assert original.count(ORIGINAL_IMPORT + "\n") == 1, f"{name}: expected one '{ORIGINAL_IMPORT}' line"
    ported = [DROP_IN_IMPORT + "\n" if line == ORIGINAL_IMPORT + "\n" else line for line in original]
    changed = [d for d in difflib.unified_diff(original, ported, n=0) if d[:1] in "+-" and d[:3] not in ("+++", "---")]
    assert changed == ["-" + ORIGINAL_IMPORT + "\n", "+" + DROP_IN_IMPORT + "\n"], changed
    out = dest / name
    out.write_text("".join(ported))
    return out


def run_python(env: dict[str, str], script: Path) -> subprocess.CompletedProcess:
    """Run as a user would: the venv's python, from the script's own directory (not the checkout)."""
    return subprocess.run([str(VENV_BIN / "python"), str(script)], env=env, cwd=script.parent, capture_output=True,
                          text=True, timeout=120)


@pytest.mark.slow
def test_original_c_client_builds_and_moves_the_elbow(system: dict[str, str], tmp_path: Path) -> None:
    """`#include "mds.h"` alone, then ach_open/ach_get/ach_put and `H_ref.joint[LEP].ref = -0.2`: compiled
    unchanged (warnings are errors) against include/mds.h + `pkg-config --cflags --libs ach`."""
    exe = libach.build(CLIENTS / "mds_demo.c", tmp_path / "mds_demo", f"-I{REPO / 'include'}")
    env = dict(system, LD_LIBRARY_PATH=f"{libach.prefix() / 'lib'}:{system.get('LD_LIBRARY_PATH', '')}")
    proc = subprocess.run([str(exe)], env=env, capture_output=True, text=True, timeout=60)
    assert proc.returncode == 0, proc.stdout + proc.stderr
    assert proc.stdout.startswith("LeftElbowFlex (LEP, 0x004c): pos = "), proc.stdout
    wait_for(lambda: abs(joint_pos("LEP") + 0.2) < 0.006, timeout=30, what="LEP at -0.2")


@pytest.mark.slow
def test_the_c_client_put_again_sends_the_elbow_back_after_another_controller_moved_it(
        system: dict[str, str], tmp_path: Path) -> None:
    """Issue 26: the same C client run again writes the same frame (LEP -0.2) after the IK controller moved LEP:
    every put on mds-ref-filter is a command, so the elbow goes back, as on the original (it stayed before)."""
    import mds_ach as mds
    from mds_ach.nodes.mux import load_config
    from mds_ach.nodes.pipeline import make_ref, ref_arrays
    from mds_ach.robot.channels import StructChannel
    from mds_ach.robot.msgs import MDS_MUX_STATE

    exe = libach.build(CLIENTS / "mds_demo.c", tmp_path / "mds_demo", f"-I{REPO / 'include'}")
    env = dict(system, LD_LIBRARY_PATH=f"{libach.prefix() / 'lib'}:{system.get('LD_LIBRARY_PATH', '')}")

    def run_client() -> None:
        proc = subprocess.run([str(exe)], env=env, capture_output=True, text=True, timeout=60)
        assert proc.returncode == 0, proc.stdout + proc.stderr

    run_client()
    wait_for(lambda: abs(joint_pos("LEP") + 0.2) < 0.006, timeout=30, what="LEP at -0.2")
    lep = mds.BY_SHORT["LEP"].address
    with StructChannel(mds.MDS_CHAN_REF_IK_NAME, mds.MDS_REF) as ik, \
            StructChannel(mds.MDS_CHAN_REF_MUX_NAME, mds.MDS_REF) as out:
        base = ik.latest() or out.latest()  # change LEP only, compared with what 'ik' wrote before
        assert base is not None
        ref, mode = ref_arrays(base)
        ref[lep] = -0.5
        ik.put(make_ref(ref, mode))
    wait_for(lambda: abs(joint_pos("LEP") + 0.5) < 0.006, timeout=30, what="LEP at -0.5 (moved by 'ik')")
    names = [c.name for c in load_config()["controllers"]]
    with StructChannel(mds.MDS_CHAN_MUX_STATE_NAME, MDS_MUX_STATE) as states:
        def ik_stale() -> bool:
            st = states.wait(1.0)
            return st is not None and bool(st.stale[names.index("ik")])
        wait_for(ik_stale, 15, what="'ik' stale")
    run_client()  # the same frame again
    wait_for(lambda: abs(joint_pos("LEP") + 0.2) < 0.006, timeout=30, what="LEP back at -0.2")


@pytest.mark.slow
def test_paper_simple_joint_demo(system: dict[str, str], tmp_path: Path) -> None:
    proc = run_python(system, port("mds_simple_demo_python.py", tmp_path))
    assert proc.returncode == 0, proc.stdout + proc.stderr
    assert proc.stdout.count(f"Address =  {0x5F}") == 2, proc.stdout
    wait_for(lambda: abs(joint_pos("LSP") + 0.123) < 0.006, timeout=30, what="LSP at -0.123")


@pytest.mark.slow
def test_paper_ik_solver_api_example(system: dict[str, str], tmp_path: Path) -> None:
    """mds_ik.getIK solved locally (`import mds_ik as ik`), the joints written to mds-ref-filter."""
    assert np.linalg.norm(left_hand() - TARGET) > 0.1, "the hand must start away from the target"
    proc = run_python(system, port("mds_ik_solver_example.py", tmp_path))
    assert proc.returncode == 0, proc.stdout + proc.stderr
    assert "N-3 DOF IK Solution - for  left  arm" in proc.stdout, proc.stdout
    wait_for(lambda: np.linalg.norm(left_hand() - TARGET) < 0.02, timeout=30, what="left hand at (0.3, 0.2, 0.0)")


@pytest.mark.slow
def test_paper_ik_one_target(system: dict[str, str], tmp_path: Path) -> None:
    """A 3-DOF request on mds-ik, solved by the IK node. The hand is first moved away through the console."""
    console = [str(VENV_BIN / "mds-ach"), "console", "-c", "goto LEP -0.3 wait", "-c", "goto LSP 0.0 wait"]
    proc = subprocess.run(console, env=system, capture_output=True, text=True, timeout=120)
    assert proc.returncode == 0, proc.stdout + proc.stderr
    assert np.linalg.norm(left_hand() - TARGET) > 0.1, "the hand must start away from the target"
    proc = run_python(system, port("mds_ik_one.py", tmp_path))
    assert proc.returncode == 0, proc.stdout + proc.stderr
    wait_for(lambda: np.linalg.norm(left_hand() - TARGET) < 0.03, timeout=30, what="left hand at (0.3, 0.2, 0.0)")


def test_listings_need_the_one_change_only() -> None:
    """Unchanged, the Python listings import a top-level `ach`, which this package never installs (a real py_ach
    may be there); the drop-in line is the only difference."""
    for name in ("mds_simple_demo_python.py", "mds_ik_one.py", "mds_ik_solver_example.py"):
        lines = (CLIENTS / name).read_text().splitlines()
        assert lines.count(ORIGINAL_IMPORT) == 1 and DROP_IN_IMPORT not in lines, name
    assert os.path.basename(sys.executable).startswith("python")
