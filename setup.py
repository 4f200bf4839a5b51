"""ament_python package `mds_ach`: library, nodes and the `mds-ach` front-end.

Executable names: a venv's or a prefix's ``bin/`` is on users' PATH, so there every executable carries the
``mds-ach-`` prefix (``mds-ach-daemon``, ``mds-ach-read``: nothing that shadows the shell builtin ``read`` or a
common command such as ``daemon``). ``lib/mds_ach/`` is private to ``ros2 run``, so there (the ament install, see
setup.cfg) the same scripts get the node names ``ros2 run mds_ach daemon`` expects: ``AmentScripts`` strips the
prefix.
"""

import os
from glob import glob

from setuptools import Extension, find_packages, setup
from setuptools.command.install_scripts import install_scripts

PACKAGE = "mds_ach"
BIN_PREFIX = "mds-ach-"


class AmentScripts(install_scripts):
    """Entry-point scripts written into ``<prefix>/lib/mds_ach`` (colcon/ament) lose the ``mds-ach-`` prefix."""

    def write_script(self, script_name: str, contents: str, mode: str = "t", *ignored: object) -> None:
        lib_dir = os.path.normpath(self.install_dir)
        if os.path.basename(lib_dir) == PACKAGE and os.path.basename(os.path.dirname(lib_dir)) == "lib":
            script_name = script_name.removeprefix(BIN_PREFIX)
        super().write_script(script_name, contents, mode, *ignored)


def tree(src: str) -> list[tuple[str, list[str]]]:
    """data_files entries installing every file under ``src`` to share/mds_ach/<src>, keeping sub-folders."""
    entries = []
    for root, _dirs, files in os.walk(src):
        paths = [os.path.join(root, f) for f in sorted(files) if not f.endswith((".pyc", "~"))]
        if paths:
            entries.append((os.path.join("share", PACKAGE, root), paths))
    return entries


setup(
    name=PACKAGE,
    version="0.1.0",
    packages=find_packages(include=["mds_ach", "mds_ach.*", "mds_ach_bridge", "mds_ach_bridge.*"]),
    # The original's module name for the IK functions (`import mds_ik as ik`), an alias of mds_ach.kinematics.ik.
    # There is deliberately no top-level `ach`: the Ach binding is `from mds_ach import ach`, so a real py_ach
    # installed next to this package is never shadowed.
    py_modules=["mds_ik"],
    data_files=[
        ("share/ament_index/resource_index/packages", ["resource/" + PACKAGE]),
        ("share/" + PACKAGE, ["package.xml"]),
        *tree("urdf"),
        *tree("config"),
        *tree("launch"),
        ("share/" + PACKAGE + "/include", glob("include/*.h")),
        ("include", glob("include/*.h")),
    ],
    # The C fast path of mds_ach.ach, the SIGBUS guard for mapped channel files (a truncated channel must not
    # kill its users); both optional: without a compiler the pure-Python code is used, unguarded.
    ext_modules=[Extension("mds_ach.ach._achfast", ["mds_ach/ach/_achfast.c"], depends=["mds_ach/ach/achcore.h"],
                           extra_compile_args=["-O2", "-Wall"], optional=True),
                 Extension("mds_ach.ach._shmguard", ["mds_ach/ach/_shmguard.c"], extra_compile_args=["-O2", "-Wall"],
                           optional=True),
                 # The collision gate's per-configuration screen (FK, poses, exact/conservative pair tests);
                 # without it mds_ach.kinematics.collision runs the numpy path, with the same answers. -O3 and
                 # -fno-math-errno (sqrt as one instruction, same correctly rounded result; no -ffast-math): 7 %
                 # off the pair list's tail, which its EPA and GJK make.
                 Extension("mds_ach.kinematics._collfast", ["mds_ach/kinematics/_collfast.c"],
                           extra_compile_args=["-O3", "-fno-math-errno", "-Wall"], optional=True),
                 # The IK searches (FK, Jacobian, damped least squares, restarts) in one call; without it
                 # mds_ach.kinematics.ik runs the same steps in Python (slower, same tolerance).
                 Extension("mds_ach.kinematics._iksearch", ["mds_ach/kinematics/_iksearch.c"],
                           extra_compile_args=["-O2", "-Wall"], optional=True)],
    install_requires=["setuptools"],
    zip_safe=False,
    maintainer="mds_ach developers",
    maintainer_email="mds-ach@example.org",
    description="ROS 2 Jazzy + Ach-compatible middleware for the Xitome MDS humanoid upper body",
    license="BSD-3-Clause",
    extras_require={"test": ["pytest"]},
    cmdclass={"install_scripts": AmentScripts},
    entry_points={
        "console_scripts": [
            # bin/: these names; lib/mds_ach/ (ros2 run): without the prefix (daemon, filter, ...), see AmentScripts
            "mds-ach-daemon = mds_ach.nodes.daemon:main",
            "mds-ach-filter = mds_ach.nodes.filter:main",
            "mds-ach-mux = mds_ach.nodes.mux:main",
            "mds-ach-ik = mds_ach.nodes.ik:main",
            "mds-ach-collision = mds_ach.nodes.collision:main",
            "mds-ach-bridge = mds_ach_bridge.bridge:main",
            "mds-ach-console = mds_ach.tools.console:main",
            "mds-ach-read = mds_ach.tools.read:main",
            "mds-ach = mds_ach.tools.cli:main",
        ],
    },
)
