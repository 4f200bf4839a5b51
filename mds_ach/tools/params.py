"""ROS 2 parameters files for the six nodes: ``config/params.yaml`` and the ones given to ``mds-ach start --params``.

The file is the standard ROS 2 format (``<node name>: ros__parameters: {name: value}``; ``/**/<node>``, ``/<ns>/<node>``
and ``/**`` sections for namespaced nodes, ``mds-ach start --namespace``), passed to each node as
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
import re
import sys
import textwrap
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from mds_ach.nodes.rosnode import Param, ParamValue
from mds_ach.paths import config_path

PARAMS_FILE = "params.yaml"  # in config/
ROS_TOKEN = re.compile(r"[A-Za-z_][A-Za-z0-9_]*")
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
# Sections are /**/NODE: NODE in any namespace, so the file also serves `mds-ach start --namespace NAME`; a section
# for one robot of several is /NAME/NODE:, one for every node /**: (each parameter checked for every node declaring it).
#
# GENERATED from the nodes' PARAMETERS (python -m mds_ach.tools.params --write); test_params.py keeps it in step.
# Values are the defaults. Commented lines: the default comes from the node's own config file (an active line would
# override that file), or `mds-ach start` sets the parameter itself. Reference: docs/parameters.md.
"""


def render(all_nodes: Sequence[NodeParams] | None = None) -> str:
    """The text of ``config/params.yaml`` for ``all_nodes`` (default: every node), with every declared parameter."""
    lines = [HEADER.rstrip("\n")]
    for node in all_nodes if all_nodes is not None else nodes():
        lines += ["", f"{WILDCARD}/{node.ros_name}:  # mds-ach start --only {node.name}", "  ros__parameters:"]
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


WILDCARD = "/**"
"""rcl's wildcard: ``/**`` (every node of every namespace) and ``/**/NODE`` (NODE in any namespace)."""


@dataclass(frozen=True)
class Section:
    """What a top-level key of a params file addresses, as rcl matches it against a node's fully qualified name:
    ``namespace`` ``/``, ``/robot1`` or None for any (``/**``), and ``node`` (None: every node)."""

    key: str
    namespace: str | None
    node: NodeParams | None

    def applies(self, node: NodeParams, namespace: str) -> bool:
        return (self.namespace is None or self.namespace == namespace) and self.node in (None, node)


def _section(key: str, by_ros: Mapping[str, NodeParams], by_name: Mapping[str, NodeParams]) -> Section | str:
    """The section a top-level key names, or the problem with it. Accepted: ``NODE``/``/NODE`` (no namespace),
    ``/NS/NODE`` (NS may have several tokens), ``/**`` and ``/**/NODE``."""
    if key == WILDCARD:
        return Section(key, None, None)
    any_namespace = key.startswith(WILDCARD + "/")
    tokens = key[len(WILDCARD):].strip("/").split("/") if any_namespace else key.strip("/").split("/")
    namespace = None if any_namespace else "/" + "/".join(tokens[:-1])
    bare = tokens[-1]
    if any("*" in token for token in tokens):
        return (f"{key!r}: this wildcard is not supported here; use /** (every node), /**/NODE (NODE in any namespace) "
                "or /NAMESPACE/NODE")
    if namespace is not None and not all(ROS_TOKEN.fullmatch(t) for t in namespace.strip("/").split("/") if t):
        return f"{key!r}: {namespace!r} is not a ROS namespace"
    if bare in by_ros:
        return Section(key, namespace, by_ros[bare])
    hint = f" (its ROS node name is {by_name[bare].ros_name!r})" if bare in by_name else ""
    return f"unknown node {key!r}{hint}; nodes: {', '.join(n.ros_name for n in by_ros.values())}"


def _check_section(section: Section, given: Mapping[str, Any], known: Sequence[NodeParams],
                   problems: list[str]) -> dict[str, ParamValue]:
    """The section's valid values; every problem appended (a wildcard section's parameter must be declared by a
    node it reaches, and fit every such node)."""
    flat: dict[str, Any] = {}
    _flatten("", given, flat)
    reached = [section.node] if section.node is not None else list(known)
    values: dict[str, ParamValue] = {}
    for name, value in flat.items():
        declaring = [(n, p) for n in reached for p in n.params if p.name == name]
        if not declaring:
            if section.node is not None:
                problems.append(f"{section.key}: unknown parameter {name!r}; {section.node.ros_name} declares: "
                                f"{', '.join(p.name for p in section.node.params)}")
            else:
                problems.append(f"{section.key}: unknown parameter {name!r}: no node declares it")
            continue
        whys = [f"{section.key}: {name}: {why}" + (f" (for {n.ros_name})" if section.node is None else "")
                for n, p in declaring if (why := check_value(p, value)) is not None]
        if whys:
            problems += whys
            continue
        values[name] = value
    return values


def check(doc: Any, all_nodes: Sequence[NodeParams] | None = None,
          namespace: str = "/") -> dict[str, dict[str, ParamValue]]:
    """``{ROS node name: {parameter: value}}`` that the nodes started in ``namespace`` get from a parsed params
    file (sections applied in file order, as rcl does: a later one wins); ParamsFileError listing every problem.
    Every section is checked, also those for another namespace (one file may serve several robots); a section for
    the nodes outside any namespace (``mds_daemon:``) when they start in one is refused: rcl would silently ignore
    it."""
    known = list(all_nodes) if all_nodes is not None else nodes()
    by_ros = {n.ros_name: n for n in known}
    by_name = {n.name: n for n in known}
    if doc is None:
        raise ParamsFileError("the file is empty (give at least one node section, or use --no-params)")
    if not isinstance(doc, Mapping):
        raise ParamsFileError("expected a mapping of node names (<node>: ros__parameters: {...})")
    problems: list[str] = []
    result: dict[str, dict[str, ParamValue]] = {}
    for key, body in doc.items():
        key = str(key)
        section = _section(key, by_ros, by_name)
        if isinstance(section, str):
            problems.append(section)
            continue
        if not isinstance(body, Mapping) or set(body) != {"ros__parameters"}:
            problems.append(f"{key}: expected exactly one key, ros__parameters")
            continue
        given = body["ros__parameters"]
        if not isinstance(given, Mapping) or not given:
            problems.append(f"{key}: ros__parameters must map parameter names to values (rcl refuses an empty one)")
            continue
        values = _check_section(section, given, known, problems)
        if section.namespace == "/" and namespace != "/":
            assert section.node is not None
            problems.append(f"{key}: this section is for {section.node.ros_name} outside any namespace, but the nodes "
                            f"start in {namespace}: write /**/{section.node.ros_name}: (any namespace) or "
                            f"{namespace}/{section.node.ros_name}:")
            continue
        for node in known:
            if section.applies(node, namespace):
                declared = {p.name for p in node.params}
                mine = {k: v for k, v in values.items() if k in declared}
                if mine or section.node is not None:
                    result.setdefault(node.ros_name, {}).update(mine)
    if problems:
        raise ParamsFileError("\n".join(problems))
    return result


def load(path: str | Path, all_nodes: Sequence[NodeParams] | None = None,
         namespace: str = "/") -> dict[str, dict[str, ParamValue]]:
    """Read and check a params file for nodes started in ``namespace`` (``check``); ParamsFileError (naming the
    file) if it cannot be used."""
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
        return check(doc, all_nodes, namespace)
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
