"""Joint table: the project YAML agrees with the original XML, conversions, limits, variants, refusals."""

from __future__ import annotations

import ctypes
import logging
import math
import re
import xml.etree.ElementTree as ET
from dataclasses import fields
from pathlib import Path

import pytest
import yaml

from mds_ach.paths import config_path
from mds_ach.robot import anatomy, config, joints
from mds_ach.robot.config import ConfigError
from mds_ach.robot.msgs import MDS_JOINT_PARAM, MDS_STATE, get_name

ROBOT_FILES = {"default": "anatomy.xml", "isaac": "Isaac.anatomy.xml", "lucas": "Lucas.anatomy.xml",
               "octavia": "Octavia.anatomy.xml"}


@pytest.fixture
def xml_dir(shared_dir: Path) -> Path:
    return shared_dir / "mds-reference/configs"


def _same(a: config.JointConfig, b: config.JointConfig) -> None:
    for f in fields(a):
        if not f.compare:  # what a file left unstated (JointConfig.published): the YAML states everything
            continue
        va, vb = getattr(a, f.name), getattr(b, f.name)
        if isinstance(va, float):
            assert va == pytest.approx(vb, abs=1e-12), (a.short, f.name)
        else:
            assert va == vb, (a.short, f.name)


@pytest.mark.parametrize("robot", sorted(ROBOT_FILES))
def test_yaml_equals_the_original_xml(robot: str, xml_dir: Path) -> None:
    """Every number of joints.yaml (+ robots/<robot>.yaml) is the one of the robot's anatomy + mdsach.xml."""
    table = config.load(robot)
    assert table.robot == robot and len(table) == 43
    ref = config.from_xml(xml_dir / ROBOT_FILES[robot], xml_dir / "mdsach.xml", robot=robot, require_all=True)
    assert table.addresses == ref.addresses
    for a, b in zip(table, ref, strict=True):
        _same(a, b)
    assert table.accel_deg_s2 == 80.0 and table.trajectory_period == 0x0727


def test_every_reference_config_file_loads(xml_dir: Path, caplog: pytest.LogCaptureFixture) -> None:
    anatomies = sorted(xml_dir.glob("*anatomy.xml"))
    assert len(anatomies) == 7
    for path in anatomies:
        muscles = anatomy.load_anatomy(path)
        head_only = ".head." in path.name
        assert len(muscles) == (20 if head_only else 43), path.name
        with caplog.at_level(logging.INFO, logger="mds_ach.robot.anatomy"):
            table = config.from_xml(path, xml_dir / "mdsach.xml")
        assert [j.short for j in table] == [j.short for j in joints.JOINTS if j.address in muscles]
        if head_only:
            assert max(table.addresses) == 0x43
    for path, count in (("nrl001.xml", 48), ("nrl002.xml", 48), ("nrl003.xml", 46)):
        nodes = anatomy.load_node_configs(xml_dir / path)
        assert len(nodes) == count, path
        assert nodes[0x5F].maxpwm == 2300 and nodes[0x5F].mode == 0x0105
    # Nodes on the bus that the anatomy does not describe (spec §d.1).
    assert {0x44, 0x45, 0x46, 0x47, 0x58} <= set(anatomy.load_node_configs(xml_dir / "nrl001.xml"))


def test_duplicate_eye_short_names_are_mapped_with_a_note(xml_dir: Path, caplog: pytest.LogCaptureFixture) -> None:
    raw = {m.get("name"): m.find("parameter[@name='mdsachname']").get("value")
           for m in ET.parse(xml_dir / "mdsach.xml").getroot()}
    assert raw["LeftEyePan"] == raw["EyePitch"] == "LYP" and raw["RightEyePan"] == "RYP"
    with caplog.at_level(logging.INFO, logger="mds_ach.robot.anatomy"):
        overlay = anatomy.load_overlay(xml_dir / "mdsach.xml")
    assert (overlay["LeftEyePan"].short, overlay["EyePitch"].short, overlay["RightEyePan"].short) == (
        "LYY", "EYP", "RYY")
    notes = [r.getMessage() for r in caplog.records if "unique name" in r.getMessage()]
    assert len(notes) == 3 and any("'LYP'" in n and "EYP" in n for n in notes)


def test_spec_numbers(xml_dir: Path) -> None:
    """cpr, start pose and the derived ranges of spec §d.2 (ranges there are without the margin)."""
    t = config.load("default")
    assert t["LEP"].cpr == 51200 and t["RSR"].cpr == 491520 and t["RWR"].cpr == pytest.approx(125465.6)
    assert {s: t[s].home for s in ("RSP", "RSR", "REP", "LSP", "LSR", "LEP")} == pytest.approx(
        {"RSP": -0.445, "RSR": -1.18, "REP": -1.25, "LSP": -0.45, "LSR": 1.2, "LEP": -1.25})
    spec = {"REP": (-2.554, 0.054), "RSY": (-1.141, 1.441), "RSR": (-2.605, 0.245), "LEP": (-2.550, 0.050),
            "LSY": (-1.549, 1.049), "LSR": (-0.253, 2.653), "LWR": (-1.394, 0.834), "RSP": (-1.989, 1.099),
            "LSP": (-1.996, 1.096), "WST": (-0.406, 0.406), "NKR": (-0.439, 0.439)}
    for short, (lo, hi) in spec.items():
        j = t[short]
        no_margin = config.derived_limits(j.rom, j.cpr, 0.0, j.offset, j.direction)
        assert no_margin == pytest.approx((lo, hi), abs=1.5e-3), short
        # With the margin the range shrinks symmetrically about the ROM middle (motor zero).
        mid = -j.offset * j.direction
        assert j.lower > lo and j.upper < hi
        assert (j.upper - mid) == pytest.approx(mid - j.lower)
        assert (j.upper - j.lower) == pytest.approx(j.rom_rad * (1 - j.rom_margin))
    assert t.enabled == tuple(j for j in t if j.short in
                              {"NKR", "NKP1", "NKP2", "NKY", *joints.LEFT_ARM, *joints.RIGHT_ARM, "WST"})


@pytest.mark.parametrize("short", ["LEP", "RSR", "LWY", "NKY", "RWR"])
def test_rad_count_conversion(short: str) -> None:
    j = config.load()[short]
    assert j.to_counts(j.home) == pytest.approx(0.0, abs=1e-9)  # home pose = motor zero = ROM middle
    for q in (j.lower, j.home, j.upper, 0.3 * j.lower + 0.7 * j.upper):
        c = j.to_counts(q)
        assert c == pytest.approx((j.direction * q + j.offset) * j.cpr / (2 * math.pi))
        assert j.to_joint(c) == pytest.approx(q, abs=1e-12)
    # One motor degree is cpr/360 counts in the joint's direction.
    assert j.to_counts(j.home + j.direction * math.radians(1)) == pytest.approx(j.cpr / 360)
    # Half the usable ROM either side of the middle.
    assert abs(j.to_counts(j.lower)) == pytest.approx(j.rom / 2 * (1 - j.rom_margin))


def test_capture_values_convert() -> None:
    """The LEB log's 30 deg MOVETO (4266.67 counts) is 30 deg of motor travel on LEP's 51200 cpr."""
    lep = config.load()["LEP"]
    q = lep.to_joint(4266.6665)
    assert lep.motor_rad(q) == pytest.approx(math.radians(30), abs=1e-6)
    t = config.load()
    assert t.accel_counts(lep) == pytest.approx(80 * 51200 / 360)


def test_param_and_state_fill() -> None:
    t = config.load("isaac")
    param = t.to_param()
    assert ctypes.sizeof(param) == 29000
    back = MDS_JOINT_PARAM.from_bytes(bytes(param))
    for j in t:
        p = back.joint[j.address]
        assert (p.address, p.enabled, get_name(p.name), get_name(p.nameshort)) == (
            j.address, int(j.enabled), j.name, joints.published_short(j.address, j.short))
        assert (p.rom, p.offset, p.direction, p.rom_margin) == (j.rom, j.offset, j.direction, j.rom_margin)
        assert p.encoderresolution * p.gearratio * p.encoderconfig_tickspercount == pytest.approx(j.cpr)
        assert get_name(p.HomeType) == j.homing.type and p.HomeError == j.homing.error
    assert back.joint[0x49].HomeError == 20 and get_name(back.joint[0x49].HomeType) == "manual"
    assert back.joint[0].address == 0 and get_name(back.joint[0].name) == ""
    state = MDS_STATE()
    t.fill_state(state)
    assert get_name(state.joint[0x5F].nameshort) == "LSP" and state.joint[0x5F].direction == -1
    assert state.joint[0x31].enabled == 0 and state.joint[0x30].enabled == 1


def test_mds_param_from_the_original_xml_is_what_the_original_parser_published(shared_dir: Path) -> None:
    """Issue #29 item 6: the original's parser padded each text it set with spaces to all 30 bytes (no NUL) and
    left unset fields zero; mdsach.xml names nodes 0x31, 0x32, 0x3f LYP, LYP, RYP; a missing rom.margin stayed
    0.0 in the frame (the limits still take 5 % for it)."""
    configs = shared_dir / "mds-reference" / "configs"
    table = config.from_xml(configs / "anatomy.xml", configs / "mdsach.xml")
    raw = bytes(table.to_param())
    param = MDS_JOINT_PARAM.from_bytes(raw)
    size = MDS_JOINT_PARAM.joint.size // 100  # one mds_jnt_param_t: 290 B
    for j in table:
        p = param.joint[j.address]
        for name in ("name", "nameshort", "coordsys", "HomeType", "HomeTarget"):
            at = j.address * size + getattr(type(p), name).offset
            field_bytes = raw[at:at + 30]
            text = field_bytes.rstrip(b" ")
            assert b"\0" not in field_bytes and text and field_bytes == text.ljust(30, b" "), (j.short, name)
    assert [get_name(param.joint[a].nameshort) for a in (0x31, 0x32, 0x3F)] == ["LYP", "LYP", "RYP"]
    assert get_name(param.joint[0x4C].nameshort) == "LEP" and get_name(param.joint[0x4C].name) == "LeftElbowFlex"
    assert raw[:size] == bytes(size), "an address without a muscle stays all zero"
    assert param.joint[0x3A].rom_margin == 0.0 and table["NKY"].rom_margin == 0.05  # HeadPan has no rom.margin
    assert param.joint[0x4C].rom_margin == table["LEP"].rom_margin > 0
    state = MDS_STATE()
    table.fill_state(state)
    assert [get_name(state.joint[a].nameshort) for a in (0x31, 0x32, 0x3F)] == ["LYP", "LYP", "RYP"]


def test_robot_selection(monkeypatch: pytest.MonkeyPatch, tmp_path: Path) -> None:
    monkeypatch.delenv(config.ROBOT_ENV, raising=False)
    monkeypatch.setenv("MDS_ACH_CONFIG_DIR", str(tmp_path))  # where `mds-ach changerobot` saves its choice
    assert config.load().robot == "default"
    (tmp_path / "robot").write_text("isaac\n")
    assert config.load().robot == "isaac"
    monkeypatch.setenv(config.ROBOT_ENV, "Octavia")
    t = config.load()
    assert t.robot == "octavia" and t["LEP"].rom == 21242 and t["WST"].rom == 53077
    assert config.load("lucas")["RSR"].rom == 223624  # the argument wins over the environment
    assert set(config.available_robots()) == set(ROBOT_FILES)
    monkeypatch.setenv(config.ROBOT_ENV, "hubo")
    with pytest.raises(ConfigError, match="unknown robot 'hubo'"):
        config.load()


def _write(tmp_path: Path, mutate) -> Path:
    src = config_path("joints.yaml")
    doc = yaml.safe_load(src.read_text())
    mutate(doc)
    out = tmp_path / "joints.yaml"
    out.write_text(yaml.safe_dump(doc))
    return out


@pytest.mark.parametrize(
    ("mutate", "joint", "field"),
    [
        (lambda d: d["joints"]["LSY"].update(address=0x4C), "LSY", "address"),  # duplicate of LEP
        (lambda d: d["joints"].pop("WST"), "WST", "missing"),
        (lambda d: d["joints"]["LEP"].update(rom="lots"), "LEP", "rom"),
        (lambda d: d["joints"]["LEP"]["encoder"].update(gear_ratio="x"), "LEP", "encoder.gear_ratio"),
        (lambda d: d["joints"]["RSR"].update(direction=0.5), "RSR", "direction"),
        (lambda d: d["joints"]["RSR"].update(offset=float("nan")), "RSR", "offset"),
        (lambda d: d["joints"]["NKY"].update(enabled="yes"), "NKY", "enabled"),
        (lambda d: d["joints"]["NKY"].update(colour="red"), "NKY", "colour"),
        (lambda d: d["joints"]["LEP"].update(home=1.0), "LEP", "home"),
        (lambda d: d["joints"]["LEP"].update(upper=0.5), "LEP", "upper"),
        (lambda d: d["joints"]["LEP"].update(name="LeftKnee"), "LEP", "name"),
        (lambda d: d["joints"]["LEP"].update(rom=-5), "LEP", "rom"),
        (lambda d: d["joints"]["LEP"].pop("offset"), "LEP", "offset"),
    ],
)
def test_bad_yaml_is_refused_naming_file_joint_field(tmp_path: Path, mutate, joint: str, field: str) -> None:
    path = _write(tmp_path, mutate)
    with pytest.raises(ConfigError) as info:
        config.load(path=path, robot="default")
    msg = str(info.value)
    assert str(path) in msg and f"joint {joint}" in msg and field in msg, msg


@pytest.mark.parametrize(("key", "value", "field", "message"), [
    ("rom_margin", "1.0", "rom_margin", r"1 \(100 %\) is not a margin: it must be between 0 and 0\.5"),
    ("rom_margin", "1.5", "rom_margin", r"1\.5 \(150 %\) is not a margin"),
    ("safety_margin", "1.0e+9", "safety_margin", r"1e\+09 \(1e\+11 %\) is not a margin"),
    ("gear_ratio", "1.0e-300", "encoder.gear_ratio", r"1e-300 is not a reduction gear ratio"),
    ("resolution", "256.5", "encoder.resolution", r"256\.5 is not a whole number >= 1"),
    ("ticks_per_count", "2.5", "encoder.ticks_per_count", r"2\.5 is not a whole number >= 1"),
    ("rom", "90000", "rom", r"90000 counts is not a range of motion between 1 count and one revolution"),
    ("offset", "-71.6", "offset", r"-71\.6 rad is more than one turn"),
    ("acceleration", "-500", "homing.acceleration", r"-500 is negative"),
])
def test_yaml_numbers_are_checked_for_sense_with_the_line(tmp_path: Path, key: str, value: str, field: str,
                                                         message: str) -> None:
    """Issue #25 item 9: the bounds of the calibration XML hold for the YAML table too, refused at the field's line."""
    src = config_path("joints.yaml").read_text()
    text, n = re.subn(rf"(\n  LEP:.*?\b{key}: )[-0-9.e+]+", rf"\g<1>{value}", src, count=1, flags=re.S)
    assert n == 1
    path = tmp_path / "joints.yaml"
    path.write_text(text)
    line = next(i for i, (a, b) in enumerate(zip(src.splitlines(), text.splitlines(), strict=True), 1) if a != b)
    with pytest.raises(ConfigError) as info:
        config.load(path=path, robot="default")
    msg = str(info.value)
    assert msg.startswith(f"{path}:{line}: joint LEP: field '{field}': "), msg
    assert re.search(message, msg), msg


def test_a_robot_overlay_is_checked_at_its_own_line(tmp_path: Path) -> None:
    (tmp_path / "robots").mkdir()
    (tmp_path / "joints.yaml").write_text(config_path("joints.yaml").read_text())
    overlay = config_path("robots/isaac.yaml").read_text()
    assert "  NKR: {rom: 28544, rom_margin: 0.09," in overlay
    (tmp_path / "robots/isaac.yaml").write_text(overlay.replace("rom_margin: 0.09,", "rom_margin: 1.5,", 1))
    line = next(i for i, t in enumerate(overlay.splitlines(), 1) if t.startswith("  NKR:"))
    with pytest.raises(ConfigError, match=rf"^{re.escape(str(tmp_path / 'robots/isaac.yaml'))}:{line}: joint NKR: "
                                          r"field 'rom_margin': 1\.5 \(150 %\) is not a margin"):
        config.load("isaac", path=tmp_path / "joints.yaml")


def test_yaml_aliases_cannot_blow_up_the_line_map(tmp_path: Path) -> None:
    """The line map walks each node once: 10^12 paths through nested aliases, or a recursive alias, are refused at
    once like any other wrong table (walking every path would never end)."""
    bomb = "l0: &l0 {a: 1, b: 2, c: 3, d: 4, e: 5, f: 6, g: 7, h: 8, i: 9, j: 10}\n" + "".join(
        f"l{i}: &l{i} {{" + ", ".join(f"k{k}: *l{i - 1}" for k in range(10)) + "}\n" for i in range(1, 12))
    path = tmp_path / "joints.yaml"
    path.write_text("format: 1\njoints: {LEP: {rom: &r {x: *r}}}\n" + "description:\n  " + bomb.replace("\n", "\n  "))
    with pytest.raises(ConfigError, match=rf"{re.escape(str(path))}:\d+: "):
        config.load(path=path, robot="default")


def test_narrower_limits_are_accepted(tmp_path: Path) -> None:
    path = _write(tmp_path, lambda d: d["joints"]["LEP"].update(lower=-2.0, upper=-0.2))
    t = config.load(path=path, robot="default")
    assert (t["LEP"].lower, t["LEP"].upper) == (-2.0, -0.2)
    assert t["LEP"].clamp(0.3) == -0.2 and t["LEP"].clamp(-3) == -2.0 and not t["LEP"].within_limits(0.0)


def test_bad_xml_is_refused(tmp_path: Path, xml_dir: Path) -> None:
    text = (xml_dir / "anatomy.xml").read_text()
    bad = tmp_path / "anatomy.xml"
    bad.write_text(re.sub(r'(name="LeftElbowFlex">\s*<parameter name="rom" value=")\d+', r"\1abc", text))
    with pytest.raises(anatomy.XmlConfigError, match=r"anatomy.xml:\d+: muscle LeftElbowFlex: parameter rom"):
        anatomy.load_anatomy(bad)
    bad.write_text(text.replace('address="0x004c"', 'address="0x004b"').replace('address="0x004C"',
                                                                                  'address="0x004B"'))
    with pytest.raises(anatomy.XmlConfigError, match="duplicate address 0x4B"):
        anatomy.load_anatomy(bad)
    bad.write_text(text[: len(text) // 2])
    with pytest.raises(anatomy.XmlConfigError, match="malformed XML"):
        anatomy.load_anatomy(bad)


def test_cli_prints_table(capsys: pytest.CaptureFixture[str]) -> None:
    assert config.main(["--robot", "lucas"]) == 0
    out = capsys.readouterr().out
    assert "robot lucas" in out and re.search(r"0x4C LEP\s+LeftElbowFlex", out)
