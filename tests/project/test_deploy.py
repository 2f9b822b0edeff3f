"""The service files in deploy/: the systemd unit passes `systemd-analyze verify` with no
finding, keeps the stop that holds the robot, and starts a command line vservo's own parser
takes; the udev rule names the adapter's stable link."""

import configparser
import re
import shlex
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from vservo.app.cli import build_parser

ROOT = Path(__file__).resolve().parents[2]
UNIT = ROOT / "deploy" / "vservo.service"
RULE = ROOT / "deploy" / "99-vservo-robot.rules"
INSTALLED_AT = "/opt/vservo/venv/bin/vservo"  # where docs/deployment.md installs vservo


def systemd_analyze() -> str:
    found = shutil.which("systemd-analyze")
    assert found, "systemd-analyze is missing: tests/install.sh installs Debian's systemd package (apt-get install systemd)"
    return found


def verify(unit_text: str, folder: Path) -> subprocess.CompletedProcess:
    """`systemd-analyze verify` on the unit, its vservo the one of this test's environment: verify
    requires ExecStart's program to exist, and on this machine vservo is not under /opt."""
    here = Path(sys.executable).parent / "vservo"
    assert here.is_file(), f"vservo's console script is not installed beside {sys.executable}"
    assert INSTALLED_AT in unit_text
    unit = folder / "vservo.service"
    unit.write_text(unit_text.replace(INSTALLED_AT, str(here)))
    return subprocess.run([systemd_analyze(), "verify", str(unit)], capture_output=True, text=True, timeout=120)


def service_environment() -> list[str]:
    """The unit's Environment= lines (configparser keeps only the last of a repeated key)."""
    return [line.split("=", 1)[1] for line in UNIT.read_text().splitlines() if line.startswith("Environment=")]


def service_section() -> configparser.SectionProxy:
    parser = configparser.ConfigParser(strict=False, interpolation=None)
    parser.optionxform = str  # systemd's keys are case-sensitive
    parser.read(UNIT)
    return parser["Service"]


def test_the_unit_passes_systemd_analyze_verify_without_a_finding(tmp_path):
    checked = verify(UNIT.read_text(), tmp_path)
    assert checked.returncode == 0 and checked.stderr.strip() == "", checked.stderr


def test_verify_finds_a_broken_unit(tmp_path):
    """The check can fail: verify reports a bad value on standard error (its exit code stays 0)."""
    broken = UNIT.read_text().replace("KillSignal=SIGINT", "KillSignal=SIGFOO")
    checked = verify(broken, tmp_path)
    assert "SIGFOO" in checked.stderr


def test_the_unit_restarts_on_failure_and_its_stop_holds_the_robot():
    service = service_section()
    assert service["Restart"] == "on-failure"
    # SIGINT to the app and the controller alike (control-group): the controller holds the arm
    # and lets the run end on record, within the controller's own waits (10 s for the run, 30 s
    # for the app's stop of the controller) before systemd would kill it.
    assert service["KillSignal"] == "SIGINT" and service["KillMode"] == "control-group"
    assert int(service["TimeoutStopSec"]) > 30
    assert service["User"] != "root"


def test_the_unit_starts_a_command_line_vservo_takes():
    service = service_section()
    environment = dict(line.split("=", 1) for line in service_environment())
    command = shlex.split(re.sub(r"\$\{(\w+)\}", lambda name: environment[name.group(1)], service["ExecStart"]))
    assert command[0] == INSTALLED_AT
    args = build_parser().parse_args(command[1:])
    assert args.command == "serve" and args.host == "127.0.0.1"  # the page only through the reverse proxy
    assert (args.log_format, args.log_level) == ("json", "info")
    assert args.cell == "/var/lib/vservo/cell.toml"  # in the service's own folder: commissioning writes beside it


RULE_KEY = re.compile(r'^[A-Z_]+(\{[A-Za-z_]+\})?(==|!=|=|\+=|-=|:=)"[^"]*"$')


def test_the_udev_rule_gives_the_adapter_its_stable_name():
    rules = [line for line in RULE.read_text().splitlines() if line.strip() and not line.startswith("#")]
    assert len(rules) == 1
    keys = [key.strip() for key in rules[0].split(",")]
    assert all(RULE_KEY.match(key) for key in keys), keys
    assert 'SUBSYSTEM=="tty"' in keys and 'SYMLINK+="vservo-robot"' in keys and 'GROUP="dialout"' in keys


@pytest.mark.parametrize("name", ["vservo.service", "99-vservo-robot.rules", "vservo.env.example"])
def test_deployment_guide_names_each_file(name):
    assert f"deploy/{name}" in (ROOT / "docs" / "deployment.md").read_text()
