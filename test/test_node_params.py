"""ROS parameters of the six nodes: declared with descriptions and ranges, documented in docs/parameters.md exactly
as declared, refused with one line when out of range, and *read*: each test starts a node with ``--ros-args -p``
and checks the value through what the node does."""

from __future__ import annotations

import json
import signal
import subprocess
import time
from collections.abc import Iterator, Sequence
from contextlib import contextmanager

import numpy as np
import pytest
from support import REPO, VENV_BIN, wait_for

import mds_ach as mds
from mds_ach import ach, ik
from mds_ach.kinematics import model as kinematics
from mds_ach.kinematics.collision import load_model
from mds_ach.kinematics.ik import IKOptions
from mds_ach.nodes import collision, daemon, mux
from mds_ach.nodes import filter as filter_node
from mds_ach.nodes import ik as ik_node
from mds_ach.nodes.ik_client import IkClient
from mds_ach.nodes.mux import MDS_MUX_STATE
from mds_ach.nodes.pipeline import make_ref, ref_arrays
from mds_ach.nodes.rosnode import Param, parameter_table
from mds_ach.paths import bin_name
from mds_ach.robot.channels import StructChannel
from mds_ach.robot.joints import BY_SHORT, LEFT_ARM, RIGHT_ARM
from mds_ach.robot.msgs import daemon_status as ds
from mds_ach_bridge import node as bridge_node

N = mds.MDS_JOINT_COUNT
ZERO_MODE = np.zeros(N, dtype=np.int16)
L = [BY_SHORT[n].address for n in LEFT_ARM]
R = [BY_SHORT[n].address for n in RIGHT_ARM]
NODES: list[tuple[str, Sequence[Param]]] = [
    ("daemon", daemon.PARAMETERS), ("mux", mux.PARAMETERS), ("filter", filter_node.PARAMETERS),
    ("collision", collision.PARAMETERS), ("ik", ik_node.PARAMETERS), ("bridge", bridge_node.PARAMETERS),
]


def _put(name: str, ref: np.ndarray) -> None:
    with StructChannel(name, mds.MDS_REF) as ch:
        ch.put(make_ref(ref, ZERO_MODE))


@contextmanager
def running(*argv: str) -> Iterator[subprocess.Popen[str]]:
    """A node executable; stopped with SIGINT afterwards, which must end it cleanly (exit 0)."""
    proc = subprocess.Popen([str(VENV_BIN / bin_name(argv[0])), *argv[1:]], stdout=subprocess.PIPE,
                            stderr=subprocess.STDOUT, text=True)
    try:
        yield proc
    finally:
        proc.send_signal(signal.SIGINT)
        out, _ = proc.communicate(timeout=20)
    assert proc.returncode == 0, out
    assert "Traceback" not in out, out


# --------------------------------------------------------------------------------------------- declared


def test_docs_parameter_table_is_what_the_nodes_declare() -> None:
    """docs/parameters.md lists every parameter with the type, default and range the node declares, and no other."""
    doc = (REPO / "docs" / "parameters.md").read_text(encoding="utf-8")
    assert parameter_table(NODES) in doc, "docs/parameters.md table differs; regenerate with parameter_table()"


def test_every_parameter_is_described_and_numbers_have_ranges() -> None:
    for node, params in NODES:
        names = [p.name for p in params]
        assert len(names) == len(set(names)), node
        for p in params:
            assert len(p.description) > 20, (node, p.name)
            if p.type_name in ("integer", "double"):
                assert p.range is not None, (node, p.name)
            if p.range is not None:
                assert p.range[0] <= p.default <= p.range[1], (node, p.name)  # type: ignore[operator]


@pytest.mark.ros
@pytest.mark.parametrize(("argv", "param"), [
    (["daemon", "--nocan"], "rate:=0.0"),
    (["mux"], "state_rate:=5000.0"),
    (["filter"], "rate:=1e6"),
    (["collision"], "margin:=-0.1"),
    (["ik"], "max_iterations:=0"),
    (["bridge"], "ik_dof_left:=9"),
])
def test_out_of_range_parameters_stop_the_node_with_one_line(clean_shm: None, argv: list[str], param: str) -> None:
    res = subprocess.run([str(VENV_BIN / bin_name(argv[0])), *argv[1:], "--ros-args", "-p", param], capture_output=True,
                         text=True, timeout=60)
    assert res.returncode == 2, res.stdout + res.stderr
    lines = res.stderr.strip().splitlines()
    assert len(lines) == 1 and "out of range" in lines[0] and param.split(":=")[0] in lines[0], res.stderr
    assert not ach.exists(mds.MDS_CHAN_REF_NAME) and not ach.exists(mds.MDS_CHAN_STATE_NAME)


# --------------------------------------------------------------------------------------------- read and used


@pytest.mark.ros
def test_filter_output_rate_follows_rate(clean_shm: None) -> None:
    """The filter ticks at ``rate`` while its output moves (a new input is stepped at once; at rest it sleeps)."""
    _put(mds.MDS_CHAN_DAEMON_INPUT_NAME, np.zeros(N))
    with StructChannel(mds.MDS_CHAN_REF_SMOOTH_NAME, mds.MDS_REF) as smooth, \
            running("filter", "--rate", "50", "--ros-args", "-p", "rate:=4"):  # -p wins over the option
        wait_for(lambda: smooth.wait(timeout=0.5), 60, what="the first smoothed frame")
        target = np.zeros(N)
        target[mds.BY_SHORT["LSR"].address] = 2.5  # ~2 s at 1.57 rad/s and 4 rad/s^2: 8 ticks of 0.25 s
        _put(mds.MDS_CHAN_REF_MUX_NAME, target)
        stamps = []
        while len(stamps) < 7:
            if smooth.wait(timeout=2.0) is not None:
                stamps.append(time.monotonic())
    mean = (stamps[-1] - stamps[0]) / (len(stamps) - 1)
    assert 0.2 <= mean <= 0.3, f"mean period {mean:.3f} s, expected 0.25 s (rate 4 Hz)"


@pytest.mark.ros
def test_mux_state_period_follows_state_rate(clean_shm: None) -> None:
    _put(mds.MDS_CHAN_DAEMON_INPUT_NAME, np.zeros(N))
    with StructChannel(mds.MDS_CHAN_MUX_STATE_NAME, MDS_MUX_STATE) as state, \
            running("mux", "--ros-args", "-p", "state_rate:=2.0"):
        frames = [wait_for(lambda: state.wait(timeout=0.5), 60, what="the first mux state")]
        while len(frames) < 4:
            if (st := state.wait(timeout=2.0)) is not None:
                frames.append(st)
    gaps = [b.time - a.time for a, b in zip(frames, frames[1:], strict=False) if b.seq == a.seq + 1]
    assert gaps and min(gaps) >= 0.5 - 1e-6 and min(gaps) < 0.75, gaps  # 10 Hz by default: 0.1 s


@pytest.mark.ros
@pytest.mark.slow
def test_collision_margin_decides_where_the_hand_stops(clean_shm: None, tmp_path) -> None:
    """With margin 0.08 the gate holds the left hand 8 cm above a table (the default 0.02 stops it at ~2 cm)."""
    table = {"objects": [{"name": "table", "shape": "box", "size": [0.6, 1.4, 0.04], "xyz": [0.6, 0.0, -0.42]}]}
    world = tmp_path / "world.yaml"
    world.write_text(json.dumps(table))  # JSON is YAML
    home = np.zeros(N)
    for name, value in {"RSP": -0.445, "RSR": -1.18, "REP": -1.25, "RSY": 0.15, "LSP": -0.45, "LSR": 1.2,
                        "LEP": -1.25, "LSY": -0.25, "LWR": -0.28}.items():
        home[BY_SHORT[name].address] = value
    res = ik.solve([0.40, 0.25, -0.50], "p-x p-y p-z", "left", home[L])
    assert res.success, res.message
    into_table = home.copy()
    into_table[L] = res.q
    _put(mds.MDS_CHAN_DAEMON_INPUT_NAME, home)
    with StructChannel(mds.MDS_CHAN_REF_SMOOTH_NAME, mds.MDS_REF) as smooth, \
            StructChannel(mds.MDS_CHAN_DAEMON_INPUT_NAME, mds.MDS_REF) as out, \
            StructChannel(mds.MDS_CHAN_COLLIDE_NAME, mds.MDS_COLLIDE) as collide, \
            running("collision", "--world", str(world), "--ros-args", "-p", "margin:=0.08"):
        wait_for(lambda: collide.latest(), 60, what="the gate's first report")
        out.latest()

        def held() -> bool:
            smooth.put(make_ref(into_table, ZERO_MODE))  # unsmoothed: the gate's speed bound paces it
            time.sleep(0.025)
            c = collide.latest()
            return c is not None and c.isCollide == 1 and bool(c.joint[mds.COLLIDE_L_HAND].isCollide)

        wait_for(held, 60, interval=0, what="the left arm to be held above the table")
        got = ref_arrays(wait_for(lambda: out.latest(), 5, what="a gated reference"))[0]
    model = load_model(world=table)
    poses = model.primitive_poses(model.q_from_ref(got))
    torso = model.tree.link_pose("torso", np.zeros(17))
    k = [p.name for p in model.primitives].index("left_hand_link")
    hand = (np.linalg.inv(torso) @ poses[k])[:3, 3]
    assert hand[2] - 0.1 >= -0.40 + 0.08 - 1e-9, hand  # the hand's lowest point, the table top, the margin
    assert hand[2] - 0.1 < -0.40 + 0.08 + 0.05, hand  # and it did move down to there


@pytest.mark.ros
@pytest.mark.slow
def test_ik_tolerance_and_max_iterations_decide_a_borderline_request(clean_shm: None) -> None:
    """A target 4 cm beyond the left hand's reach: with tolerance 0.2 m it is solved (the best reach is within
    0.2 m), which the default 1 mm would refuse; max_iterations 1 caps the search at max_iterations x seeds steps
    (``IKOptions.seeds``), polish included."""
    seed = np.zeros(N)
    seed[L] = [-0.2, 0.3, 0.0, -1.0, 0.0, 0.0]
    seed[R] = [-0.2, -0.3, 0.0, -1.0, 0.0, 0.0]
    st = mds.MDS_STATE()
    for a in range(N):
        st.joint[a].ref = seed[a]
    with StructChannel(mds.MDS_CHAN_STATE_NAME, mds.MDS_STATE) as ch:
        ch.put(st)
    hanging = kinematics.fk_matrix([0.0] * 6, "left")[:3, 3]  # the arm straight down: the hand at full reach
    target = (hanging + [0.0, 0.0, -0.04]).tolist()
    with running("ik", "--ros-args", "-p", "max_iterations:=1", "-p", "tolerance:=0.2",
                 "-p", "collision_check:=false") as proc, IkClient() as client:
        reply = None
        deadline = time.monotonic() + 60
        while reply is None:
            try:
                reply = client.request("left", 3, target, timeout=2.0)
            except TimeoutError:
                assert proc.poll() is None and time.monotonic() < deadline, "the ik node did not answer"
    assert reply.success, reply.message
    seeds = IKOptions().seeds
    assert 0.03 < reply.error < 0.2 and reply.iterations <= 1 * seeds, (reply.error, reply.iterations)
    assert np.allclose(kinematics.fk_matrix(list(reply.q), "left")[:3, 3], target, atol=0.2)


@pytest.mark.ros
@pytest.mark.slow
def test_daemon_rate_parameter_sets_the_loop_rate(clean_shm: None) -> None:
    with StructChannel(mds.MDS_CHAN_DAEMON_STATUS_NAME, ds.MDS_DAEMON_STATUS) as status, \
            running("daemon", "--nocan", "--ros-args", "-p", "rate:=20"):  # an integer is fine for a double
        st = wait_for(lambda: status.latest(), 60, what="the daemon status")
        assert st.rate_hz == 20.0
