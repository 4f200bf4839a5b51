"""No traceback from the CLI: numeric options are finite and bounded, robot names and hosts are checked, each
bad value is a one-line usage error with exit status 2 (issue #25, item 9)."""

from __future__ import annotations

import argparse

import pytest

from mds_ach.argtypes import bounded, count, seconds
from mds_ach.net.remote import SshTunnel, destination_problem
from mds_ach.tools import cli

LONG_NAME = "a" * 5000

CASES = [
    (["hold", "--timeout", "1e308"], "argument --timeout: 1e308 is out of range"),
    (["hold", "--timeout", "-1"], "argument --timeout: -1 is out of range"),
    (["hold", "--timeout", "nan"], "argument --timeout: nan is not a finite number"),
    (["resume", "--timeout", "inf"], "argument --timeout: inf is not a finite number"),
    (["hold", "--timeout", "0"], "more than 0 and at most 3600 s"),
    (["changerobot", LONG_NAME], "a robot name has at most 64 characters (got 5000)"),
    (["changerobot", "-- x"], "invalid robot name"),
    (["changerobot", "/" + LONG_NAME + ".xml"], "path too long or invalid"),
    (["remote", "--ssh=-oProxyCommand=touch /tmp/owned"], "--ssh wants USER@HOST"),
    (["remote", "--ssh", "user@-oProxyCommand=touch /tmp/owned"], "invalid host '-oProxyCommand"),
    (["remote", "--ssh", "user@robot", "--ssh-port", "99999999"], "argument --ssh-port: 99999999 is out of range"),
    (["remote", "robot", "--wait", "1e308"], "argument --wait: 1e308 is out of range"),
    (["remote", "robot", "--dead-after", "nan"], "argument --dead-after: nan is not a finite number"),
    (["remote", "robot", "--port", "0"], "argument --port: 0 is out of range"),
    (["remote", LONG_NAME], "invalid host"),
    (["start", "--timeout", "-5"], "argument --timeout: -5 is out of range"),
    (["stop", "--grace", "inf"], "argument --grace: inf is not a finite number"),
    (["status", "--window", "1e9"], "argument --window: 1e9 is out of range"),
    (["resetbus", "--timeout", "nan"], "argument --timeout: nan is not a finite number"),
    (["repair", "--timeout", "-0.5"], "argument --timeout: -0.5 is out of range"),
    (["dump", "mds-ref", "--wait", "nan"], "argument --wait: nan is not a finite number"),
    (["check-log", "x.asc", "--rate", "0"], "argument --rate: 0 is out of range"),
    (["check-log", "x.asc", "--max", "-3"], "argument --max: -3 is out of range"),
    (["check-log", "x.asc", "--max", "1.5"], "argument --max: '1.5' is not a whole number"),
    (["sim", "--port", "70000"], "argument --port: 70000 is out of range"),
    (["sim", "--rate", "nan"], "argument --rate: nan is not a finite number"),
    (["make", "--mode", "7777777"], "argument --mode: 7777777 is out of range"),
    (["make", "--mode", "8"], "argument --mode: '8' is not an octal mode"),
]


@pytest.mark.parametrize(("argv", "message"), CASES, ids=[" ".join(a)[:40] for a, _ in CASES])
def test_a_bad_value_is_a_one_line_usage_error(argv: list[str], message: str, capsys) -> None:
    try:
        status = cli.main(argv)
    except SystemExit as exc:  # argparse's usage error
        status = exc.code
    out, err = capsys.readouterr()
    assert status == 2, (out, err)
    assert "Traceback" not in out + err
    last = err.strip().splitlines()[-1]
    assert message in last and last.startswith("mds-ach"), err
    assert len(last) < 300, last  # a 5,000-character value is not echoed back


def test_the_shared_type_is_finite_bounded_and_typed() -> None:
    t = seconds(10.0)
    assert t("2.5") == 2.5 and t("10") == 10.0
    for bad in ("0", "-1", "nan", "inf", "-inf", "10.01", "1e308", "x", ""):
        with pytest.raises(argparse.ArgumentTypeError):
            t(bad)
    assert seconds(zero=True)("0") == 0.0
    n = count(1, 5)
    assert n("3") == 3 and isinstance(n("3"), int)
    for bad in ("0", "6", "2.0", "0x3"):
        with pytest.raises(argparse.ArgumentTypeError):
            n(bad)
    assert bounded(-1.0, 1.0)("-1") == -1.0


def test_node_options_use_their_ros_parameter_range() -> None:
    from mds_ach.nodes import filter as filter_node

    with pytest.raises(SystemExit) as exc:
        filter_node._build_parser().parse_args(["--rate", "nan"])
    assert exc.value.code == 2
    assert filter_node._build_parser().parse_args(["--rate", "100"]).rate == 100.0


def test_ssh_never_reads_the_host_as_an_option() -> None:
    assert destination_problem("mds@robot.local", ssh=True) is None
    assert destination_problem("mds@10.0.0.2", ssh=True) is None
    assert destination_problem("robot", ssh=False) is None
    for bad in ("-oProxyCommand=x", "mds@-oProxyCommand=x", "@robot", "-l@robot", "mds@rob ot"):
        assert destination_problem(bad, ssh=True), bad
    with pytest.raises(ValueError, match="invalid host"):
        SshTunnel("mds@-oProxyCommand=x")
    cmd = SshTunnel("mds@robot").command()
    assert cmd[-2:] == ["--", "mds@robot"]
