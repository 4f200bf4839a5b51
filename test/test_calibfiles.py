"""Issue #18 §1: the original installation's calibration XML at run time (/etc/mds-ach, $MDS_ACH_ANATOMY,
--anatomy), head-only anatomies, `changerobot` like the original, and bad XML refused with file and line.

Every test makes its own "/etc/mds-ach" in a temporary directory ($MDS_ACH_ETC); the real /etc is never read
(conftest points $MDS_ACH_ETC at a directory that does not exist)."""

from __future__ import annotations

import logging
import re
import shutil
import subprocess
from pathlib import Path

import pytest
from support import SHARED, VENV_BIN, in_netns
from support.system import START_TIMEOUT, mds_ach, running_system, system_env

import mds_ach as mds
from mds_ach import ach
from mds_ach.robot import calibfiles, config, joints
from mds_ach.robot.config import ConfigError

CONFIGS = SHARED / "mds-reference/configs"
HEAD = CONFIGS / "Isaac.head.anatomy.xml"


def _etc(tmp_path: Path, anatomy: str = "anatomy.xml", robots: bool = True) -> Path:
    """An original installation: <etc>/configs/{anatomy.xml (a copy of ``anatomy``), mdsach.xml, <Robot>...}."""
    etc = tmp_path / "etc-mds-ach"
    (etc / "configs").mkdir(parents=True)
    shutil.copyfile(CONFIGS / anatomy, etc / "configs/anatomy.xml")
    shutil.copyfile(CONFIGS / "mdsach.xml", etc / "configs/mdsach.xml")
    if robots:
        for f in ("Isaac.anatomy.xml", "Lucas.anatomy.xml", "Octavia.anatomy.xml"):
            shutil.copyfile(CONFIGS / f, etc / "configs" / f)
    return etc


def _line_of(path: Path, needle: str) -> int:
    return next(i for i, line in enumerate(path.read_text().splitlines(), 1) if needle in line)


def test_the_installation_xml_is_the_table(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    etc = _etc(tmp_path, "Lucas.anatomy.xml")
    monkeypatch.setenv(calibfiles.ETC_ENV, str(etc))
    table = config.load()
    assert table.robot == config.XML_ROBOT
    assert table.sources == (str(etc / "configs/anatomy.xml"), str(etc / "configs/mdsach.xml"))
    lucas = config.load("lucas")  # an explicit variant is the packaged YAML
    assert lucas.sources[0].endswith("joints.yaml") and [j.rom for j in table] == [j.rom for j in lucas]
    assert config.load("xml").sources == table.sources  # what the daemon publishes as its robot: same files
    assert "calibration XML" in config.describe(table) and str(etc / "configs/anatomy.xml") in config.describe(table)
    # $MDS_ACH_ANATOMY wins over /etc; the overlay is found in /etc/mds-ach/configs; 'none' switches the XML off
    monkeypatch.setenv(calibfiles.ANATOMY_ENV, str(CONFIGS / "Octavia.anatomy.xml"))
    octavia = config.load()
    assert octavia.sources == (str(CONFIGS / "Octavia.anatomy.xml"), str(etc / "configs/mdsach.xml"))
    assert octavia["LEP"].rom == 21242
    monkeypatch.setenv(calibfiles.ANATOMY_ENV, "none")
    assert config.load().robot == "default"
    with pytest.raises(ConfigError, match="there is none here"):
        config.load("xml")
    # the brief's /etc/mds-ach/anatomy.xml and the original's configs/anatomy.xml: both, differing, is refused
    monkeypatch.delenv(calibfiles.ANATOMY_ENV)
    shutil.copyfile(CONFIGS / "Isaac.anatomy.xml", etc / "anatomy.xml")
    with pytest.raises(ConfigError, match="both exist and differ"):
        config.load()
    (etc / "configs/anatomy.xml").unlink()
    assert config.load().sources[0] == str(etc / "anatomy.xml")
    monkeypatch.setenv(calibfiles.OVERLAY_ENV, str(tmp_path / "nope.xml"))
    with pytest.raises(ConfigError, match="nope.xml: no such overlay file"):
        config.load()


def test_head_only_anatomy_loads_with_the_other_nodes_disabled(monkeypatch: pytest.MonkeyPatch,
                                                                caplog: pytest.LogCaptureFixture) -> None:
    monkeypatch.setenv(calibfiles.ANATOMY_ENV, str(HEAD))
    with caplog.at_level(logging.INFO, logger="mds_ach.robot.config"):
        table = config.load()
    notes = [r.getMessage() for r in caplog.records if r.name == "mds_ach.robot.config"]
    assert len(notes) == 1 and "head only (20 of 43 nodes): arms and torso absent, disabled" in notes[0]
    assert len(table) == 43
    head = {j.address for j in joints.JOINTS if j.address <= 0x43}
    assert not any(j.enabled for j in table if j.address not in head)
    xml = config.from_xml(HEAD, CONFIGS / "mdsach.xml")
    assert [table[j.address] for j in xml] == list(xml)  # the head as the file says


def test_converter_takes_a_head_only_anatomy(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    assert config.main(["--from-xml", str(HEAD), str(CONFIGS / "mdsach.xml")]) == 0
    path = tmp_path / "joints.yaml"
    path.write_text(capsys.readouterr().out)
    table = config.load(path=path, robot="default")
    assert len(table) == 43 and table["NKY"].rom == config.from_xml(HEAD, CONFIGS / "mdsach.xml")["NKY"].rom
    assert not table["LEP"].enabled


@pytest.mark.parametrize("damage, needle, message", [
    (lambda t: re.sub(r'(name="LeftElbowFlex">\s*<parameter name="rom" value=")\d+', r"\1abc", t),
     'value="abc"', r"muscle LeftElbowFlex: parameter rom: not a number: 'abc'"),
    (lambda t: t.replace('address="0x004c"', 'address="0x004b"').replace('address="0x004C"', 'address="0x004B"'),
     'name="LeftElbowFlex"', r"muscle LeftElbowFlex: duplicate address 0x4B \(also \w+, line \d+\)"),
    (lambda t: re.sub(r'<muscle address="0x004[cC]".*?</muscle>', "", t, flags=re.S),
     "<anatomy", r"missing muscle LeftElbowFlex \(0x4C\): the anatomy has 22 of the 23 arms and torso nodes"),
    (lambda t: t[: len(t) // 2], None, r"malformed XML"),
])
def test_bad_xml_names_file_and_line_and_starts_nothing(tmp_path: Path, monkeypatch: pytest.MonkeyPatch, damage,
                                                        needle: str | None, message: str) -> None:
    bad = tmp_path / "anatomy.xml"
    bad.write_text(damage((CONFIGS / "anatomy.xml").read_text()))
    shutil.copyfile(CONFIGS / "mdsach.xml", tmp_path / "mdsach.xml")
    monkeypatch.setenv(calibfiles.ANATOMY_ENV, str(bad))
    with pytest.raises(ConfigError) as err:
        config.load()
    text = str(err.value)
    line = _line_of(bad, needle) if needle else None
    where = str(line) if line else r"\d+"
    assert re.match(re.escape(str(bad)) + ":" + where + ": ", text), text
    assert re.search(message, text), text
    assert "\n" not in text


def _lep(param: str, value: str):
    """A damage: LeftElbowFlex's ``param`` set to ``value`` (its needle is the new line's text)."""
    return lambda t: re.sub(rf'(name="LeftElbowFlex">.*?<parameter name="{re.escape(param)}" value=")[^"]*',
                            rf"\g<1>{value}", t, count=1, flags=re.S)


@pytest.mark.parametrize("param, value, message", [
    ("rom.margin", "100%", r"parameter rom\.margin: 1 \(100 %\) is not a margin: it must be between 0 and 0\.5"),
    ("rom.margin", "150%", r"parameter rom\.margin: 1\.5 \(150 %\) is not a margin"),
    ("rom.margin", "-5%", r"parameter rom\.margin: -0\.05 \(-5 %\) is not a margin"),
    ("safetymargin", "1e9", r"parameter safetymargin: 1e\+09 \(1e\+11 %\) is not a margin"),
    ("gearratio", "1e-300", r"parameter gearratio: 1e-300 is not a reduction gear ratio \(>= 1\)"),
    ("gearratio", "1e300", r"parameter gearratio: 5\.12e\+302 counts per revolution .* more than a float32"),
    ("encoderresolution", "256.5", r"parameter encoderresolution: 256\.5 is not a whole number >= 1"),
    ("encoderconfig.tickspercount", "0.5", r"parameter encoderconfig\.tickspercount: 0\.5 is not a whole number"),
    ("rom", "60000", r"parameter rom: 60000 counts is not a range of motion between 1 count and one revolution "
                     r"\(51200 counts: resolution 256 x gear_ratio 100 x ticks_per_count 2\)"),
    ("rom", "0.001", r"parameter rom: 0\.001 counts is not a range of motion"),
    ("HomeTimeout", "-75", r"parameter HomeTimeout: -75 is negative"),
])
def test_calibration_numbers_are_checked_for_sense(tmp_path: Path, monkeypatch: pytest.MonkeyPatch, param: str,
                                                   value: str, message: str) -> None:
    """Issue #25 item 9: a margin of 100 % (the range a point) or 150 % (inverted), a gear ratio of 1e-300, a safety
    margin of 1e9... loaded silently; each is refused naming the file, the parameter's line and the parameter."""
    bad = tmp_path / "anatomy.xml"
    bad.write_text(_lep(param, value)((CONFIGS / "anatomy.xml").read_text()))
    line = _line_of(bad, f'name="{param}" value="{value}"')
    assert 648 < line < 664  # inside LeftElbowFlex
    shutil.copyfile(CONFIGS / "mdsach.xml", tmp_path / "mdsach.xml")
    monkeypatch.setenv(calibfiles.ANATOMY_ENV, str(bad))
    with pytest.raises(ConfigError) as err:
        config.load()
    text = str(err.value)
    assert text.startswith(f"{bad}:{line}: muscle LeftElbowFlex: "), text
    assert re.search(message, text), text


def test_overlay_offsets_are_checked_for_sense(tmp_path: Path) -> None:
    """An mdsach.xml offset beyond one turn (degrees for radians) is refused at its line."""
    overlay = tmp_path / "mdsach.xml"
    overlay.write_text((CONFIGS / "mdsach.xml").read_text().replace('value="-1.25"', 'value="-71.6"', 1))
    line = _line_of(overlay, 'value="-71.6"')
    with pytest.raises(ConfigError, match=rf"^{re.escape(str(overlay))}:{line}: muscle \w+: parameter offset: "
                                          r"-71\.6 rad is more than one turn"):
        config.load(anatomy_path=CONFIGS / "anatomy.xml", overlay_path=overlay)


def test_every_reference_file_passes_the_sense_checks_unchanged() -> None:
    """The original's files are the positive set: each loads, with the numbers the files give (the margins of 50 %
    on the fingers, the safetymargin "50" the later "5%" overrides)."""
    for path in sorted(CONFIGS.glob("*anatomy.xml")):
        table = config.from_xml(path, CONFIGS / "mdsach.xml")
        assert {j.safety_margin for j in table} == {0.05}, path.name
        assert all(0.0 <= j.rom_margin <= 0.5 and j.lower < j.upper for j in table), path.name
    assert {j.rom_margin for j in config.from_xml(CONFIGS / "anatomy.xml")} == {0.05, 0.1, 0.5}


EXTERNAL = '<!DOCTYPE anatomy [\n  <!ENTITY rom SYSTEM "file:///etc/hostname">\n]>\n'
LAUGHS = ('<!DOCTYPE anatomy [\n  <!ENTITY lol "lol">\n  <!ENTITY lol1 "&lol;&lol;&lol;&lol;&lol;&lol;&lol;&lol;">\n'
          + "".join(f'  <!ENTITY lol{i} "{f"&lol{i - 1};" * 10}">\n' for i in range(2, 10)) + "]>\n")


@pytest.mark.parametrize("name", ["anatomy.xml", "mdsach.xml"])
@pytest.mark.parametrize("doctype, entity", [
    (EXTERNAL, "rom"),  # external: expat dropped the reference silently (an empty value, or a missing one)
    (LAUGHS, "lol"),  # internal: the billion laughs, expanded before
    ('<!DOCTYPE anatomy SYSTEM "http://example.invalid/anatomy.dtd">\n', None),  # external DTD: undeclared refs
], ids=["external-entity", "billion-laughs", "external-dtd"])
def test_entities_are_refused_naming_the_file(tmp_path: Path, name: str, doctype: str, entity: str | None) -> None:
    files = {n: tmp_path / n for n in ("anatomy.xml", "mdsach.xml")}
    for n, path in files.items():
        shutil.copyfile(CONFIGS / n, path)
    text = (CONFIGS / name).read_text()
    ref = "&rom;" if entity == "rom" else "&lol9;" if entity else "&undeclared;"
    files[name].write_text(doctype + text.replace('value="-1.25"' if name == "mdsach.xml" else 'value="21182"',
                                                  f'value="{ref}"', 1))
    with pytest.raises(ConfigError) as err:
        config.load(anatomy_path=files["anatomy.xml"], overlay_path=files["mdsach.xml"])
    text = str(err.value)
    if entity:
        line = _line_of(files[name], f"<!ENTITY {entity} ")
        assert text.startswith(f"{files[name]}:{line}: <!DOCTYPE> declares the entity {entity!r}: "), text
    else:
        assert text.startswith(f"{files[name]}:1: <!DOCTYPE anatomy> names an external document type "), text
    assert "may declare no entities and no external DTD" in text and "\n" not in text


def test_start_with_bad_xml_starts_nothing(tmp_path: Path, clean_shm: None) -> None:
    bad = tmp_path / "anatomy.xml"
    bad.write_text((CONFIGS / "anatomy.xml").read_text().replace('value="28592"', 'value="2x8592"', 1))
    line = _line_of(bad, 'value="2x8592"')
    env = system_env(tmp_path / "rt")
    proc = mds_ach("start", "nocan", "--anatomy", str(bad), "--overlay", str(CONFIGS / "mdsach.xml"), env=env)
    assert proc.returncode == 1, proc.stdout + proc.stderr
    assert f"{bad}:{line}: muscle" in proc.stderr and "not a number: '2x8592'" in proc.stderr
    assert "started" not in proc.stdout
    assert not list((tmp_path / "rt").glob("*.pid")) and not any(ach.exists(n) for n in mds.ALL_CHANNELS)


def test_changerobot_copies_the_anatomy_like_the_original(tmp_path: Path) -> None:
    etc = _etc(tmp_path)
    env = system_env(tmp_path / "rt") | {calibfiles.ETC_ENV: str(etc)}
    active = etc / "configs/anatomy.xml"
    proc = mds_ach("changerobot", "isaac", env=env)
    assert proc.returncode == 0, proc.stderr
    assert proc.stdout.startswith("-- Robot Changed to Isaac --")
    assert active.read_bytes() == (CONFIGS / "Isaac.anatomy.xml").read_bytes()
    status = mds_ach("status", "--window", "0.1", env=env)
    assert re.search(rf"table\s+robot xml from {re.escape(str(active))} \+ {re.escape(str(etc / 'configs'))}"
                     r"/mdsach.xml \(calibration XML", status.stdout), status.stdout
    # unknown name: the original's words, exit 2, nothing changed
    bad = mds_ach("changerobot", "marvin", env=env)
    assert bad.returncode == 2 and bad.stdout.strip() == "-- No Change to Robot --" and "marvin" in bad.stderr
    assert active.read_bytes() == (CONFIGS / "Isaac.anatomy.xml").read_bytes()
    # a path to an anatomy file (here a head-only one)
    proc = mds_ach("changerobot", str(HEAD), env=env)
    assert proc.returncode == 0 and active.read_bytes() == HEAD.read_bytes(), proc.stderr
    # a file that does not load is refused, with its line, before anything is copied
    broken = tmp_path / "broken.anatomy.xml"
    broken.write_text((CONFIGS / "Lucas.anatomy.xml").read_text().replace('value="1024"', 'value="x"', 1))
    proc = mds_ach("changerobot", str(broken), env=env)
    assert proc.returncode == 1 and f"{broken}:{_line_of(broken, 'value=' + chr(34) + 'x')}:" in proc.stderr
    assert proc.stdout.strip() == "-- No Change to Robot --" and active.read_bytes() == HEAD.read_bytes()


def test_head_only_robot_runs_and_every_tool_names_the_files(tmp_path: Path,
                                                              monkeypatch: pytest.MonkeyPatch) -> None:
    """A whole system on a head-only calibration in /etc/mds-ach: it starts, the arms are disabled, and status,
    read param and the daemon log say which files the table came from."""
    assert in_netns()
    etc = _etc(tmp_path, "Octavia.head.anatomy.xml", robots=False)
    monkeypatch.setenv(calibfiles.ETC_ENV, str(etc))
    runtime = tmp_path / "rt"
    with running_system(runtime) as env:
        files = f"{etc}/configs/anatomy.xml + {etc}/configs/mdsach.xml"
        status = mds_ach("status", "--window", "0.5", env=env, timeout=START_TIMEOUT)
        assert (f"table      robot xml from {files} (calibration XML, 4 of 43 nodes enabled) (the running daemon's"
                in status.stdout), status.stdout
        param = mds_ach("read", "param", "NKY", env=env)
        assert param.returncode == 0 and f"joint table: robot xml from {files}" in param.stdout, param.stdout
        lep = mds_ach("read", "param", "LEP", env=env)
        assert re.search(r"\benabled\s+0\b", lep.stdout), lep.stdout
        log = (runtime / "daemon.log").read_text()
        assert f"joint table: robot xml from {files} (calibration XML, " in log
        assert "head only (20 of 43 nodes): arms and torso absent, disabled (never driven)" in log


def test_daemon_reads_anatomy_and_overlay_options(tmp_path: Path, clean_shm: None) -> None:
    """`daemon --anatomy/--overlay` (what `ros2 run mds_ach daemon` users give): a bad file is refused with file and
    line before the daemon touches a channel."""
    bad = tmp_path / "Lucas.anatomy.xml"
    bad.write_text(re.sub(r'address="0x004[cC]"', 'address="0x004B"', (CONFIGS / "Lucas.anatomy.xml").read_text()))
    proc = subprocess.run([str(VENV_BIN / "mds-ach-daemon"), "--no-ros", "--nocan", "--anatomy", str(bad),
                           "--overlay", str(CONFIGS / "mdsach.xml")], capture_output=True, text=True, timeout=60)
    assert proc.returncode == 2, proc.stderr
    line = _line_of(bad, 'name="LeftElbowFlex"')
    assert f"{bad}:{line}: muscle LeftElbowFlex: duplicate address 0x4B" in proc.stderr, proc.stderr
    assert not any(ach.exists(n) for n in mds.ALL_CHANNELS)
