"""The OPC UA server with its certificate ([line.opcua] certificate and private_key): it offers
Basic256Sha256 with signing and encryption only, so a client without security is refused
and a user's password never crosses the wire in clear; anonymous "off" refuses a session
without a user. A real asyncua server in a controller of the simulated cell, a real client."""

from __future__ import annotations

import asyncio
import socket
import tomllib
from importlib import resources
from pathlib import Path

import pytest
from asyncua import Client, ua
from asyncua.crypto.cert_gen import setup_self_signed_certificate
from asyncua.crypto.security_policies import SecurityPolicyBasic256Sha256
from asyncua.ua.uaerrors import BadIdentityTokenRejected, UaError
from cryptography.x509.oid import ExtendedKeyUsageOID

from tests.controller_fixtures import simulated_controller
from vservo.app.browser import free_port
from vservo.core.cell.config import parse_cell
from vservo.core.production.opcua_server import (
    LOCKOUT_S,
    MAX_WRONG_PASSWORDS,
    NAMESPACE,
    CellOpcUaServer,
    OpcUaError,
    OpcUaUsers,
)

USER, PASSWORD = "mes", "line-4-secret"


def certificate(folder: Path, name: str, uri: str, use: ExtendedKeyUsageOID) -> tuple[Path, Path]:
    cert, key = folder / f"{name}-cert.der", folder / f"{name}-key.pem"
    asyncio.run(setup_self_signed_certificate(key, cert, uri, "localhost", [use], {"commonName": name}))
    return cert, key


async def sessions(endpoint: str, client_cert: Path, client_key: Path) -> None:
    plain = Client(endpoint)  # no security: the server offers none
    plain.set_user(USER)
    plain.set_password(PASSWORD)
    with pytest.raises(UaError, match="No matching endpoints.*SecurityPolicy#None"):
        await plain.connect()

    anonymous = Client(endpoint)  # anonymous = "off": an encrypted channel without a user is refused too
    await anonymous.set_security(SecurityPolicyBasic256Sha256, str(client_cert), str(client_key))
    with pytest.raises(BadIdentityTokenRejected):  # the server offers no anonymous token at all
        await anonymous.connect()
    await anonymous.disconnect()

    client = Client(endpoint)
    await client.set_security(SecurityPolicyBasic256Sha256, str(client_cert), str(client_key))
    client.set_user(USER)
    client.set_password(PASSWORD)
    async with client:
        namespace = await client.get_namespace_index(NAMESPACE)
        assert await client.get_node(ua.NodeId("Cell.Phase", namespace)).read_value() == "idle"
        assert "demo" in await client.get_node(ua.NodeId("Cell.Jobs", namespace)).read_value()


@pytest.mark.usefixtures("no_leaked_threads")
def test_with_its_certificate_the_server_offers_only_encrypted_sessions(tmp_path):
    server_cert, server_key = certificate(tmp_path, "server", "urn:vservo:controller", ExtendedKeyUsageOID.SERVER_AUTH)
    client_cert, client_key = certificate(tmp_path, "client", "urn:vservo:test-client", ExtendedKeyUsageOID.CLIENT_AUTH)
    tables = tomllib.loads(resources.files("vservo.static").joinpath("cell.toml").read_text())
    tables["line"] = {
        "opcua": {
            "enabled": True,
            "port": free_port(),
            "anonymous": "off",
            "certificate": str(server_cert),
            "private_key": str(server_key),
            "users": {USER: {"password": PASSWORD}},
        }
    }
    config = parse_cell(tables, "cell.toml", tmp_path)
    with simulated_controller(config, tmp_path / "data") as controller:
        server = CellOpcUaServer(controller, config.line.opcua)
        try:
            endpoint = server.start()
            asyncio.run(sessions(endpoint, client_cert, client_key))
        finally:
            server.close()


@pytest.mark.usefixtures("no_leaked_threads")
def test_a_port_in_use_is_refused_in_one_line(tmp_path):
    tables = tomllib.loads(resources.files("vservo.static").joinpath("cell.toml").read_text())
    with socket.socket() as taken:
        taken.bind(("127.0.0.1", 0))
        taken.listen()
        tables["line"] = {"opcua": {"enabled": True, "port": taken.getsockname()[1]}}
        config = parse_cell(tables, "cell.toml", tmp_path)
        with simulated_controller(config, tmp_path / "data") as controller:
            server = CellOpcUaServer(controller, config.line.opcua)
            try:
                with pytest.raises(
                    OpcUaError, match=r"could not start on opc.tcp://127.0.0.1:\d+/vservo/: .*address already in use"
                ):
                    server.start()
            finally:
                server.close()
            assert not controller.state_subscribers  # the server's subscriber went with it


def test_five_wrong_passwords_lock_the_user_out_for_a_minute_and_other_names_are_not_counted(tmp_path):
    tables = tomllib.loads(resources.files("vservo.static").joinpath("cell.toml").read_text())
    tables["line"] = {"opcua": {"enabled": True, "port": 0, "users": {USER: {"password": PASSWORD}}}}
    clock = [100.0]
    users = OpcUaUsers(parse_cell(tables, "cell.toml", tmp_path).line.opcua, clock=lambda: clock[0])
    assert users.get_user(None, USER, PASSWORD).name == USER
    for _ in range(MAX_WRONG_PASSWORDS - 1):
        assert users.get_user(None, USER, "guess") is None
    assert users.get_user(None, USER, PASSWORD) is not None  # a right one clears the count
    for _ in range(MAX_WRONG_PASSWORDS):
        assert users.get_user(None, USER, "guess") is None
        assert users.get_user(None, "nobody", "guess") is None
    clock[0] += LOCKOUT_S - 1.0
    assert users.get_user(None, USER, PASSWORD) is None  # locked out, the right password or not
    clock[0] += 1.0
    assert users.get_user(None, USER, PASSWORD).name == USER
    assert "nobody" not in users._wrong and set(users._locked_until_s) == {USER}  # unknown names are not kept
