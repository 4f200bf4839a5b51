"""``mds-ach py2to3``: original-style Python 2 programs become Python 3 programs that run against this package.

The programs in ``test/original_clients/py2/`` are written the way the original MDS-Ach examples and tools are
(print statements, golems' ``import ach``, ``raw_input``, ``except E, e``, ``<>``, ``has_key``, octal ``0644``):
they do not even compile under Python 3. Converted, they compile, run against this package's channels, do what
they did (a reference on mds-ref-filter) and print what Python 2 printed (but the space a trailing-comma print
leaves before the next newline).
"""

from __future__ import annotations

import shutil
import subprocess
import sys
from pathlib import Path

import pytest
from support import REPO, VENV_BIN

import mds_ach as mds
from mds_ach import ach
from mds_ach.robot.channels import StructChannel, make_channels
from mds_ach.tools import py2to3

PY2 = REPO / "test" / "original_clients" / "py2"


def _converted(tmp_path: Path, name: str) -> Path:
    """``mds-ach py2to3 -w`` on a copy of the program; returns the converted file."""
    target = tmp_path / name
    shutil.copy(PY2 / name, target)
    proc = subprocess.run([str(VENV_BIN / "mds-ach"), "py2to3", "-w", str(target)], capture_output=True, text=True,
                          timeout=60)
    assert proc.returncode == 0, proc.stderr
    assert (tmp_path / f"{name}.py2").read_text() == (PY2 / name).read_text(), "the original is kept"
    return target


@pytest.mark.parametrize("name", ["simple_demo.py", "state_reader.py"])
def test_the_original_style_programs_are_python_2(name: str) -> None:
    with pytest.raises(SyntaxError):
        compile((PY2 / name).read_text(), name, "exec")


def test_a_converted_demo_runs_and_prints_what_python_2_printed(clean_shm: None, tmp_path: Path) -> None:
    make_channels()
    program = _converted(tmp_path, "simple_demo.py")
    proc = subprocess.run([sys.executable, str(program), "7"], capture_output=True, text=True, timeout=60)
    assert proc.returncode == 0, proc.stderr
    # Python 2: `print 'a = ', x` wrote 'a = ' + ' ' + str(x); a trailing comma continued the line
    assert [line.rstrip() for line in proc.stdout.splitlines()] == [
        "state status =  5  framesize =  0",  # ACH_STALE_FRAMES: nothing published yet
        "LSP address =  0x5f  ref set to  -0.123",
        "joints: 0x5f 0x4f 0x4d",
        "0",
        "1",
        "mode 420",
    ]
    assert proc.stderr == "count =  7\n"
    with StructChannel(mds.MDS_CHAN_REF_FILTER_NAME, mds.MDS_REF, create=False) as rf:
        frame = rf.latest()
    assert frame is not None and frame.joint[mds.LSP].ref == -0.123


def test_a_converted_reader_reads_the_state(clean_shm: None, tmp_path: Path) -> None:
    make_channels()
    state = mds.MDS_STATE()
    state.joint[mds.LEP].pos = -1.25
    state.time = 12.5
    with StructChannel(mds.MDS_CHAN_STATE_NAME, mds.MDS_STATE) as ch:
        ch.put(state)
    program = _converted(tmp_path, "state_reader.py")
    proc = subprocess.run([sys.executable, str(program)], input="\n\nq\n", capture_output=True, text=True,
                          timeout=60)
    assert proc.returncode == 0, proc.stderr
    # ACH_EAGAIN: libach's name for status 5 (ACH_STALE_FRAMES)
    assert proc.stdout.splitlines() == ["pos =  -1.25 \ttime =  12.5", "no new state ( ACH_EAGAIN )"]
    assert ach.exists(mds.MDS_CHAN_STATE_NAME)


@pytest.mark.parametrize(("py2", "py3"), [
    ("print 'a', b\n", "print('a', b)\n"),
    ("print\n", "print()\n"),
    ("print x,\n", 'print(x, end=" ")\n'),
    ("print >>sys.stderr, 'e', x\n", "print('e', x, file=sys.stderr)\n"),
    ("print('already')\n", "print('already')\n"),
    ("print (a, b)\n", "print (a, b)\n"),  # one parenthesized expression: left alone
    ("if x: print 'y'; print 'z'\n", "if x: print('y'); print('z')\n"),
    ("print 'a', \\\n    b  # c\n", "print('a', b)  # c\n"),
    ("print foo(1, 2), [3, 4]\n", "print(foo(1, 2), [3, 4])\n"),
    ("x = raw_input('>')\n", "x = input('>')\n"),
    ("for i in xrange(n): pass\n", "for i in range(n): pass\n"),
    ("try:\n    f()\nexcept (A, B), e:\n    pass\n", "try:\n    f()\nexcept (A, B) as e:\n    pass\n"),
    ("os.chmod(p, 0777)\n", "os.chmod(p, 0o777)\n"),
    ("if a <> b: pass\n", "if a != b: pass\n"),
    ("if d.has_key(k): pass\n", "if (k in d): pass\n"),
    ("import ach\n", "from mds_ach import ach\n"),
    ("if x:\n  import ach as A  # golems\n", "if x:\n  from mds_ach import ach as A  # golems\n"),
    ("import mds_ach as mds\n", "import mds_ach as mds\n"),
    ("obj.xrange(3)\n", "obj.xrange(3)\n"),  # an attribute of that name is not the builtin
])
def test_conversions(py2: str, py3: str) -> None:
    result = py2to3.convert(py2)
    assert result.source == py3 and result.error == ""


def test_what_cannot_be_decided_is_reported() -> None:
    result = py2to3.convert("x = a / b\ny = `x`\n")
    assert "line 1: '/' divides integers to a float in Python 3 (use // for the Python 2 result)" in result.notes
    assert "line 2: backquotes (repr): write repr(...)" in result.notes and result.error
    proc = subprocess.run([str(VENV_BIN / "mds-ach"), "py2to3", str(PY2 / "simple_demo.py"), "/nonexistent.py"],
                          capture_output=True, text=True, timeout=60)
    assert proc.returncode == 2 and "several files need -w" in proc.stderr
