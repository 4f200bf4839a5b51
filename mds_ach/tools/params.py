"""ROS 2 parameters files for the six nodes: ``config/params.yaml`` and the ones given to ``mds-ach start --params``.

The file is the standard ROS 2 format (``<node name>: ros__parameters: {name: value}``), passed to each node as
``--ros-args --params-file FILE``. rclpy alone would ignore a misspelt node or parameter and stop only the one node
whose value is out of range, after the others started; ``load`` checks the whole file against what the nodes
declare (their ``PARAMETERS``) so that a bad file is refused before anything starts.

``config/params.yaml`` is generated from those declarations (``render``; ``python -m mds_ach.tools.params --write``)
and a test compares it with them, so it never drifts from the code. Two kinds of parameters are written as comments:
those whose default comes from a node's own config file (``Param.default_doc``: an active line would silently
override that file) and those the launcher sets from its own options (``LAUNCHER_SET``).
"""

from __future__ import annotations

import argparse
import importlib
import math
import sys
import textwrap
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from mds_ach.nodes.rosnode import Param, ParamValue
from mds_ach.paths import config_path

PARAMS_FILE = "params.yaml"  # in config/
# launcher node name -> the module that declares its NODE_NAME and PARAMETERS (imported on first use: rclpy)
NODE_MODULES: dict[str, str] = {
    "daemon": "mds_ach.nodes.daemon",
    "mux": "mds_ach.nodes.mux",
    "filter": "mds_ach.nodes.filter",
    "collision": "mds_ach.nodes.collision",
    "ik": "mds_ach.nodes.ik",
    "bridge": "mds_ach_bridge.node",
}
# (launcher node, parameter) -> why a params file used by `mds-ach start` does not choose it
LAUNCHER_SET: dict[tuple[str, str], str] = {
    ("daemon", "nocan"): "chosen by `mds-ach start nocan` / `mds-ach run nocan` (`make run`); a file that sets it "
                         "must agree with that choice",
}


class ParamsFileError(ValueError):
    """A params file that does not fit the nodes' declarations; the message has one line per problem."""


@dataclass(frozen=True)
class NodeParams:
    """One node's parameters: its launcher name (``mds-ach start --only``), ROS node name and declarations."""

    name: str
    ros_name: str
    params: Sequence[Param]


def nodes() -> list[NodeParams]:
    """Every node's declared parameters, in start order (imports the node modules, hence rclpy)."""
    out = []
    for name, module_name in NODE_MODULES.items():
        module = importlib.import_module(module_name)
        out.append(NodeParams(name, module.NODE_NAME, tuple(module.PARAMETERS)))
    return out


def default_path() -> Path:
    """The shipped file, ``config/params.yaml`` (the launcher uses it when it exists)."""
    return config_path(PARAMS_FILE)


# --------------------------------------------------------------------------------------------- render


def _yaml_value(value: ParamValue) -> str:
    """A value as YAML that rcl and PyYAML both read back with the same type (a double always has a '.')."""
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, int):
        return str(value)
    if isinstance(value, float):
        text = repr(value)
        if "e" in text and "." not in text.split("e")[0]:
            mantissa, exp = text.split("e")
            text = f"{mantissa}.0e{exp}"
        return text
    return "'" + value.replace("'", "''") + "'"


def _comment(text: str, indent: str) -> list[str]:
    return textwrap.wrap(text, width=116, initial_indent=indent + "# ", subsequent_indent=indent + "# ")


HEADER = """\
# ROS 2 parameters of the MDS-Ach nodes (standard format: <node name>: ros__parameters: {...}).
# `mds-ach start` and `mds-ach run` (so `make run`) pass this file to every node (--ros-args --params-file) when it
# exists; `--params FILE` uses another one, `--no-params` none. The file is checked against what the nodes declare
# before anything starts: an unknown node or parameter, a wrong type or a value out of range is refused.
# With `ros2 run`: ros2 run mds_ach filter --ros-args --params-file config/params.yaml
#
# GENERATED from the nodes' PARAMETERS (python -m mds_ach.tools.params --write); test_params.py keeps it in step.
# Values are the defaults. Commented lines: the default comes from the node's own config file (an active line would
# override that file), or `mds-ach start` sets the parameter itself. Reference: docs/parameters.md.
"""


def render(all_nodes: Sequence[NodeParams] | None = None) -> str:
    """The text of ``config/params.yaml`` for ``all_nodes`` (default: every node), with every declared parameter."""
    lines = [HEADER.rstrip("\n")]
    for node in all_nodes if all_nodes is not None else nodes():
        lines += ["", f"{node.ros_name}:  # mds-ach start --only {node.name}", "  ros__parameters:"]
        for p in node.params:
            why = LAUNCHER_SET.get((node.name, p.name))
            if why is None and p.default_doc is not None:
                why = f"left out so that the node's config file decides: {p.default_doc.replace('`', '')}"
            kind = p.type_name + (f", {p.doc_range()}" if p.range is not None else "")
            lines += _comment(p.description, "    ")
            line = f"{p.name}: {_yaml_value(p.default)}  # {kind}"
            if why:
                lines += _comment(f"({why})", "    ") + [f"    # {line}"]
            else:
                lines.append(f"    {line}")
    return "\n".join(lines) + "\n"


# --------------------------------------------------------------------------------------------- load and check


def _flatten(prefix: str, value: Any, out: dict[str, Any]) -> None:
    """ROS reads nested mappings under ros__parameters as dotted names (``a: {b: 1}`` is ``a.b``)."""
    if isinstance(value, Mapping):
        for key, sub in value.items():
            _flatten(f"{prefix}.{key}" if prefix else str(key), sub, out)
    else:
        out[prefix] = value


def check_value(param: Param, value: Any) -> str | None:
    """Why ``value`` cannot be ``param``'s (wrong type, out of range), or None when it can."""
    kind = param.type_name
    ok_type = {"bool": isinstance(value, bool),
               "integer": isinstance(value, int) and not isinstance(value, bool),
               "double": isinstance(value, int | float) and not isinstance(value, bool),
               "string": isinstance(value, str)}[kind]
    if not ok_type:
        got = "a list" if isinstance(value, list) else ("empty (null)" if value is None else
                                                         f"{type(value).__name__} {value!r}")
        hint = " (quote it)" if kind == "string" else ""
        return f"must be {'a ' + kind if kind != 'integer' else 'an integer'}, got {got}{hint}"
    if param.range is not None and kind in ("integer", "double"):
        lo, hi = param.range
        if not (isinstance(value, int | float) and math.isfinite(value) and lo <= value <= hi):
            return f"{value!r} is out of range [{param.doc_range()}]"
    return None


def _node_key(key: str, by_ros: Mapping[str, NodeParams], by_name: Mapping[str, NodeParams]) -> str | None:
    """The problem with a top-level key, or None if it names a node."""
    bare = key[1:] if key.startswith("/") else key
    if bare in by_ros:
        return None
    if "*" in key:
        return f"{key!r}: wildcard sections are not supported here; give each node its own section"
    hint = f" (its ROS node name is {by_name[bare].ros_name!r})" if bare in by_name else ""
    return f"unknown node {key!r}{hint}; nodes: {', '.join(n.ros_name for n in by_ros.values())}"


def check(doc: Any, all_nodes: Sequence[NodeParams] | None = None) -> dict[str, dict[str, ParamValue]]:
    """``{ROS node name: {parameter: value}}`` from a parsed params file; ParamsFileError listing every problem."""
    known = list(all_nodes) if all_nodes is not None else nodes()
    by_ros = {n.ros_name: n for n in known}
    by_name = {n.name: n for n in known}
    if doc is None:
        raise ParamsFileError("the file is empty (give at least one node section, or use --no-params)")
    if not isinstance(doc, Mapping):
        raise ParamsFileError("expected a mapping of node names (<node>: ros__parameters: {...})")
    problems: list[str] = []
    result: dict[str, dict[str, ParamValue]] = {}
    for key, section in doc.items():
        key = str(key)
        why = _node_key(key, by_ros, by_name)
        if why is not None:
            problems.append(why)
            continue
        node = by_ros[key.lstrip("/")]
        if not isinstance(section, Mapping) or set(section) != {"ros__parameters"}:
            problems.append(f"{key}: expected exactly one key, ros__parameters")
            continue
        given = section["ros__parameters"]
        if not isinstance(given, Mapping) or not given:
            problems.append(f"{key}: ros__parameters must map parameter names to values (rcl refuses an empty one)")
            continue
        flat: dict[str, Any] = {}
        _flatten("", given, flat)
        declared = {p.name: p for p in node.params}
        values = result.setdefault(node.ros_name, {})
        for name, value in flat.items():
            param = declared.get(name)
            if param is None:
                problems.append(f"{key}: unknown parameter {name!r}; {node.ros_name} declares: "
                                f"{', '.join(declared)}")
                continue
            why = check_value(param, value)
            if why is not None:
                problems.append(f"{key}: {name}: {why}")
                continue
            values[name] = value
    if problems:
        raise ParamsFileError("\n".join(problems))
    return result


def load(path: str | Path, all_nodes: Sequence[NodeParams] | None = None) -> dict[str, dict[str, ParamValue]]:
    """Read and check a params file; ParamsFileError (naming the file) if it cannot be used."""
    import yaml  # lazy: only when a file is used

    try:
        text = Path(path).read_text(encoding="utf-8")
    except OSError as exc:
        raise ParamsFileError(f"params file {path}: cannot read it: {exc.strerror or exc}") from None
    try:
        doc = yaml.safe_load(text)
    except yaml.YAMLError as exc:
        raise ParamsFileError(f"params file {path}: not valid YAML: {exc}") from None
    try:
        return check(doc, all_nodes)
    except ParamsFileError as exc:
        lines = str(exc).splitlines()
        raise ParamsFileError(f"params file {path}:\n" + "\n".join(f"  {line}" for line in lines)) from None


# --------------------------------------------------------------------------------------------- command line


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m mds_ach.tools.params",
                                     description="Print, write or check a ROS 2 params file for the MDS-Ach nodes.")
    parser.add_argument("--write", action="store_true", help=f"(re)write the shipped {default_path()}")
    parser.add_argument("--check", metavar="FILE", help="check FILE against the nodes' declarations")
    args = parser.parse_args(argv)
    if args.check:
        try:
            load(args.check)
        except ParamsFileError as exc:
            print(exc, file=sys.stderr)
            return 1
        print(f"{args.check}: ok")
        return 0
    text = render()
    if args.write:
        default_path().write_text(text, encoding="utf-8")
        print(f"wrote {default_path()}")
    else:
        sys.stdout.write(text)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
