"""ROS 2 params files (issue #19 item 4): ``config/params.yaml`` is what the nodes declare, ``mds-ach start`` passes
it (or ``--params FILE``) to every node, a bad file is refused before anything starts, and every node takes its
values from a file (checked through the node's parameter service and, for the daemon, its loop rate)."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
import yaml
from support import REPO, wait_for
from support.system import mds_ach, running_system, system_env

import mds_ach as mds
from mds_ach import ach
from mds_ach.robot.channels import StructChannel
from mds_ach.robot.msgs import daemon_status as ds
from mds_ach.tools import launcher, params
from mds_ach.tools.params import ParamsFileError, check, load, render

ALL = params.nodes()
ROS_NAME = {n.name: n.ros_name for n in ALL}


def test_shipped_params_file_is_generated_from_the_declarations() -> None:
    """config/params.yaml lists every declared parameter of every node, with its default (so it never drifts)."""
    shipped = (REPO / "config" / "params.yaml").read_text(encoding="utf-8")
    assert shipped == render(ALL), "config/params.yaml differs; regenerate: python -m mds_ach.tools.params --write"
    for node in ALL:
        for p in node.params:
            assert f"    {p.name}: " in shipped or f"    # {p.name}: " in shipped, (node.name, p.name)


def test_shipped_params_file_loads_with_the_defaults() -> None:
    values = load(params.default_path())
    assert set(values) == {n.ros_name for n in ALL}
    for node in ALL:
        for name, value in values[node.ros_name].items():
            assert value == next(p for p in node.params if p.name == name).default, (node.name, name)
    assert "nocan" not in values[ROS_NAME["daemon"]]  # the start's mode decides it
    assert "rate" not in values[ROS_NAME["filter"]]  # config/filter.yaml decides it


@pytest.mark.parametrize(("doc", "expected"), [
    ({"daemon": {"ros__parameters": {"rate": 20.0}}}, "unknown node 'daemon' (its ROS node name is 'mds_daemon')"),
    ({"/*/filter": {"ros__parameters": {"rate": 20.0}}}, "this wildcard is not supported here; use /** (every node)"),
    ({"/**": {"ros__parameters": {"rat": 20.0}}}, "/**: unknown parameter 'rat': no node declares it"),
    ({"/**": {"ros__parameters": {"rate": 5.0}}}, "/**: rate: 5.0 is out of range [10 … 1000] (for mds_daemon)"),
    ({"/1robot/filter": {"ros__parameters": {"rate": 20.0}}}, "'/1robot' is not a ROS namespace"),
    ({"filter": {"ros__parameters": {"rat": 20.0}}}, "filter: unknown parameter 'rat'; filter declares: config, rate"),
    ({"filter": {"ros__parameters": {"rate": "fast"}}}, "filter: rate: must be a double, got str 'fast'"),
    ({"filter": {"ros__parameters": {"rate": True}}}, "filter: rate: must be a double, got bool True"),
    ({"ik": {"ros__parameters": {"max_iterations": 2.5}}}, "ik: max_iterations: must be an integer, got float 2.5"),
    ({"ik": {"ros__parameters": {"robot": 1}}}, "ik: robot: must be a string, got int 1 (quote it)"),
    ({"mux": {"ros__parameters": {"state_rate": 5000.0}}}, "mux: state_rate: 5000.0 is out of range [0.1 … 1000]"),
    ({"collision": {"ros__parameters": {"margin": -0.1}}}, "collision: margin: -0.1 is out of range [0 … 0.5]"),
    ({"/mds_bridge": {"ros__parameters": {"ik_dof_left": 9}}}, "/mds_bridge: ik_dof_left: 9 is out of range [1 … 6]"),
    ({"mds_bridge": {"ros__parameters": {}}}, "ros__parameters must map parameter names to values"),
    ({"mds_bridge": {"ik_dof_left": 3}}, "expected exactly one key, ros__parameters"),
    ([1, 2], "expected a mapping of node names"),
])
def test_a_bad_file_is_refused_with_the_reason(doc: object, expected: str) -> None:
    with pytest.raises(ParamsFileError) as err:
        check(doc, ALL)
    assert expected in str(err.value)


def test_every_problem_is_listed_and_integers_are_doubles() -> None:
    doc = {"filter": {"ros__parameters": {"rate": 1e6, "config": 3}}, "mux": {"ros__parameters": {"x": 1}}}
    with pytest.raises(ParamsFileError) as err:
        check(doc, ALL)
    assert len(str(err.value).splitlines()) == 3, err.value
    assert check({"mds_daemon": {"ros__parameters": {"rate": 25}}}, ALL) == {"mds_daemon": {"rate": 25}}


def test_wildcard_and_namespace_sections_reach_the_nodes_of_their_namespace_in_file_order() -> None:
    """rcl's matching (issue #27 item 3): /** every node that declares the parameter, /**/NODE that node in any
    namespace, /NS/NODE only in NS; a later section wins; another namespace's section is checked but not applied;
    a bare NODE section cannot reach namespaced nodes and is refused for them."""
    doc = {"/**": {"ros__parameters": {"rate": 20.0}},
           "/**/mds_daemon": {"ros__parameters": {"rate": 30.0}},
           "/robot1/mds_daemon": {"ros__parameters": {"rate": 40.0}},
           "/robot2/filter": {"ros__parameters": {"rate": 50.0}}}
    assert check(doc, ALL) == {"mds_daemon": {"rate": 30.0}, "filter": {"rate": 20.0}}
    assert check(doc, ALL, "/robot1") == {"mds_daemon": {"rate": 40.0}, "filter": {"rate": 20.0}}
    assert check(doc, ALL, "/robot2") == {"mds_daemon": {"rate": 30.0}, "filter": {"rate": 50.0}}
    with pytest.raises(ParamsFileError, match="write /\\*\\*/filter: \\(any namespace\\) or /robot1/filter:"):
        check({"filter": {"ros__parameters": {"rate": 20.0}}}, ALL, "/robot1")
    assert set(load(params.default_path(), namespace="/robot1")) == {n.ros_name for n in ALL}  # the shipped file


def test_a_file_that_is_not_yaml_or_missing_names_the_file(tmp_path: Path) -> None:
    bad = tmp_path / "bad.yaml"
    bad.write_text("filter:\n  ros__parameters: [\n")
    with pytest.raises(ParamsFileError, match=f"params file {bad}: not valid YAML"):
        load(bad)
    with pytest.raises(ParamsFileError, match="cannot read it"):
        load(tmp_path / "missing.yaml")


def test_launcher_passes_the_file_and_its_own_options_win(tmp_path: Path) -> None:
    assert launcher.node_args("collision", True, "/w.yaml", params="/p.yaml") == [
        "--world", "/w.yaml", "--ros-args", "--params-file", "/p.yaml", "-p", "world:=/w.yaml"]
    assert launcher.node_args("daemon", True, None, params="/p.yaml") == [
        "--nocan", "--ros-args", "--params-file", "/p.yaml"]
    assert launcher.params_choice(None) == str(params.default_path())  # the shipped file by default
    assert launcher.params_choice(None, no_params=True) is None
    assert launcher.params_choice(str(tmp_path / "mine.yaml")) == str(tmp_path / "mine.yaml")


@pytest.mark.parametrize(("content", "expected"), [
    ({"filter": {"ros__parameters": {"rate": 0.0}}}, "filter: rate: 0.0 is out of range"),
    ({"mds_daemon": {"ros__parameters": {"nocan": False}}}, "mds_daemon nocan: false, but this start is on the "
                                                             "simulated bus"),
])
def test_start_refuses_a_bad_file_before_anything_starts(clean_shm: None, tmp_path: Path, content: dict,
                                                         expected: str) -> None:
    env = system_env(tmp_path)
    path = tmp_path / "params.yaml"
    path.write_text(json.dumps(content))  # JSON is YAML
    for verb in ("start", "run"):
        res = mds_ach(verb, "nocan", "--params", str(path), env=env)
        assert res.returncode == 1, res.stdout + res.stderr
        assert expected in res.stderr and "nothing was started" in res.stderr, res.stderr
        assert not ach.exists(mds.MDS_CHAN_STATE_NAME) and not ach.exists(mds.MDS_CHAN_REF_NAME)
        assert not list(tmp_path.glob("*.pid")), verb


# --------------------------------------------------------------------------------------------- taken by the nodes


FILE_VALUES: dict[str, dict[str, object]] = {  # launcher node -> {parameter: a value that is not the default}
    "daemon": {"rate": 20.0, "nocan": True},
    "mux": {"state_rate": 4.0},
    "filter": {"rate": 20.0},
    "collision": {"margin": 0.05},
    "ik": {"max_iterations": 77, "tolerance": 0.002},
    "bridge": {"ik_dof_left": 5, "stale_timeout": 0.7},
}


def _get_parameters(node: str, names: list[str]) -> list[object]:
    """The values of ``names`` from ``/<node>/get_parameters`` (what ``ros2 param get`` asks)."""
    import rclpy
    from rcl_interfaces.srv import GetParameters
    from rclpy.context import Context
    from rclpy.parameter import parameter_value_to_python

    context = Context()
    rclpy.init(context=context)
    try:
        probe = rclpy.create_node("params_test_probe", context=context)
        client = probe.create_client(GetParameters, f"/{node}/get_parameters")
        assert client.wait_for_service(timeout_sec=60), f"no parameter service of {node}"
        future = client.call_async(GetParameters.Request(names=names))
        from rclpy.executors import SingleThreadedExecutor

        executor = SingleThreadedExecutor(context=context)
        executor.add_node(probe)
        executor.spin_until_future_complete(future, timeout_sec=30)
        assert future.done(), f"{node} did not answer get_parameters"
        return [parameter_value_to_python(v) for v in future.result().values]
    finally:
        rclpy.try_shutdown(context=context)


def _pid_cmdline(runtime: Path, node: str) -> list[str]:
    pid = int((runtime / f"{node}.pid").read_text().split()[0])
    return Path(f"/proc/{pid}/cmdline").read_bytes().decode().rstrip("\0").split("\0")


@pytest.mark.ros
@pytest.mark.slow
def test_every_node_takes_its_values_from_the_params_file(tmp_path: Path) -> None:
    path = tmp_path / "mine.yaml"
    path.write_text(yaml.safe_dump({ROS_NAME[n]: {"ros__parameters": v} for n, v in FILE_VALUES.items()}))
    runtime = tmp_path / "rt"
    with running_system(runtime, extra=["--params", str(path)]):
        for name, values in FILE_VALUES.items():
            argv = _pid_cmdline(runtime, name)
            assert argv[-3:] == ["--ros-args", "--params-file", str(path)], argv
            got = _get_parameters(ROS_NAME[name], list(values))
            assert got == list(values.values()), (name, got)
        with StructChannel(mds.MDS_CHAN_DAEMON_STATUS_NAME, ds.MDS_DAEMON_STATUS) as status:
            st = wait_for(lambda: status.latest(), 60, what="the daemon status")
            assert st.rate_hz == 20.0  # the loop runs at the file's rate (default 10 Hz)
