"""The cell file's [line] tables: the OPC UA server's and the metrics endpoint's keys, each
refused in one line naming the key and what it takes; password hashes."""

import subprocess
import sys
import tomllib
from importlib import resources

import pytest

from vservo.core.cell.config import ConfigError, parse_cell
from vservo.core.cell.line import AnonymousAccess, PasswordError, PasswordHash

SHIPPED = tomllib.loads(resources.files("vservo.static").joinpath("cell.toml").read_text())
HASH = PasswordHash.of("line-4-secret").text()


def with_line(line: dict) -> dict:
    return {**SHIPPED, "line": line}


def test_the_shipped_cell_offers_nothing_to_the_line_until_enabled():
    line = parse_cell(SHIPPED).line
    assert not line.opcua.enabled and not line.metrics.enabled
    assert line.opcua.host == line.metrics.host == "127.0.0.1"
    assert line.opcua.anonymous is AnonymousAccess.READ_ONLY


def test_users_passwords_and_anonymous_access_are_read():
    line = parse_cell(
        with_line(
            {
                "opcua": {
                    "enabled": True,
                    "port": 4841,
                    "anonymous": "off",
                    "users": {"mes": {"password_hash": HASH}, "bench": {"password": "bench-password"}},
                },
                "metrics": {"enabled": True, "port": 9100},
            }
        )
    ).line
    users = {user.name: user for user in line.opcua.users}
    assert users["mes"].password.matches("line-4-secret") and not users["mes"].password.matches("line-4-secreT")
    assert users["bench"].password.matches("bench-password")
    assert line.opcua.endpoint == "opc.tcp://127.0.0.1:4841/vservo/"
    assert line.opcua.anonymous is AnonymousAccess.OFF and line.metrics.port == 9100


@pytest.mark.parametrize(
    ("line", "words"),
    [
        ({"opcua": {"port": 70000}}, "line.opcua.port = 70000: must be a TCP port from 0"),
        ({"metrics": {"port": -1}}, "line.metrics.port = -1: must be a TCP port from 0"),
        ({"opcua": {"host": "plant.local"}}, "line.opcua.host = 'plant.local': must be an IP address"),
        ({"opcua": {"anonymous": "write"}}, "line.opcua.anonymous = 'write': must be one of read-only, off"),
        ({"opcua": {"enabled": "yes"}}, "line.opcua.enabled = 'yes': must be true or false"),
        ({"opcua": {"endpoint": "x"}}, "unknown key line.opcua.endpoint"),
        ({"scada": {}}, "unknown key line.scada"),
        ({"opcua": {"users": {"mes": {}}}}, "line.opcua.users.mes.password_hash = None: give exactly one of"),
        ({"opcua": {"users": {"mes": {"password_hash": "md5$x"}}}}, "line.opcua.users.mes.password_hash = 'md5$x...': must be"),
        (
            {"opcua": {"users": {"mes": {"password": "short"}}}},
            "line.opcua.users.mes.password = '***': a password has at least 8",
        ),
        ({"opcua": {"users": {"bad name": {"password": "long enough"}}}}, "line.opcua.users.bad name"),
        ({"opcua": {"enabled": True, "anonymous": "off"}}, "line.opcua.anonymous = 'off': with no [line.opcua.users.NAME]"),
        (
            {"opcua": {"enabled": True, "host": "0.0.0.0", "users": {"mes": {"password_hash": HASH}}}},
            "line.opcua.host = '0.0.0.0': beyond loopback the users' passwords would cross the network in clear",
        ),
        ({"opcua": {"certificate": "/no/such/cert.pem"}}, "line.opcua.certificate = '/no/such/cert.pem': no such file"),
    ],
)
def test_a_bad_key_is_refused_in_one_line_naming_it(line, words):
    with pytest.raises(ConfigError) as refused:
        parse_cell(with_line(line), "cell.toml")
    message = str(refused.value)
    assert words in message and "\n" not in message, message
    assert "line-4-secret" not in message


def test_a_password_hash_round_trips_and_a_bad_one_is_refused():
    made = PasswordHash.of("correct horse battery")
    assert PasswordHash.parse(made.text()) == made
    with pytest.raises(PasswordError):
        PasswordHash.parse("pbkdf2-sha256$10$00$00")  # too few iterations, too short a salt and hash
    with pytest.raises(PasswordError):
        PasswordHash.of("short")


def test_password_hash_reads_the_password_from_standard_input_never_the_command_line():
    made = subprocess.run(
        [sys.executable, "-m", "vservo.app.cli", "password-hash"],
        input="line-4-secret\n",
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert made.returncode == 0, made.stderr
    assert PasswordHash.parse(made.stdout.strip()).matches("line-4-secret")
