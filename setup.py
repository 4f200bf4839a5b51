"""ament_python package `mds_ach`: library, nodes and the `mds-ach` front-end."""

import os
from glob import glob

from setuptools import Extension, find_packages, setup

PACKAGE = "mds_ach"


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
    data_files=[
        ("share/ament_index/resource_index/packages", ["resource/" + PACKAGE]),
        ("share/" + PACKAGE, ["package.xml"]),
        *tree("urdf"),
        *tree("config"),
        ("share/" + PACKAGE + "/include", glob("include/*.h")),
        ("include", glob("include/*.h")),
    ],
    # The C fast path of mds_ach.ach, the SIGBUS guard for mapped channel files (a truncated channel must not
    # kill its users); both optional: without a compiler the pure-Python code is used, unguarded.
    ext_modules=[Extension("mds_ach.ach._achfast", ["mds_ach/ach/_achfast.c"], extra_compile_args=["-O2", "-Wall"],
                           optional=True),
                 Extension("mds_ach.ach._shmguard", ["mds_ach/ach/_shmguard.c"], extra_compile_args=["-O2", "-Wall"],
                           optional=True),
                 # The collision gate's per-configuration screen (FK, poses, exact/conservative pair tests);
                 # without it mds_ach.kinematics.collision runs the numpy path, with the same answers.
                 Extension("mds_ach.kinematics._collfast", ["mds_ach/kinematics/_collfast.c"],
                           extra_compile_args=["-O2", "-Wall"], optional=True)],
    install_requires=["setuptools"],
    zip_safe=False,
    maintainer="mds_ach developers",
    maintainer_email="mds-ach@example.org",
    description="ROS 2 Jazzy + Ach-compatible middleware for the Xitome MDS humanoid upper body",
    license="BSD-3-Clause",
    extras_require={"test": ["pytest"]},
    entry_points={
        "console_scripts": [
            "daemon = mds_ach.nodes.daemon:main",
            "filter = mds_ach.nodes.filter:main",
            "mux = mds_ach.nodes.mux:main",
            "ik = mds_ach.nodes.ik:main",
            "collision = mds_ach.nodes.collision:main",
            "bridge = mds_ach_bridge.bridge:main",
            "console = mds_ach.tools.console:main",
            "read = mds_ach.tools.read:main",
            "mds-ach = mds_ach.tools.cli:main",
        ],
    },
)
