"""How a process joins the bus: config > environment > default, and one-line errors (pure, plus two real processes
that only fail at start-up)."""

from __future__ import annotations

import json
import subprocess
import sys

import msgspec
import pytest
from support.env import clean_env

from protocol.bus import (
    OBSERVER_BUS,
    BusConfig,
    BusError,
    resolve_bus,
    zenoh_config,
    zenoh_settings,
)
from protocol.deploy.config import ConfigError, load_config

ROUTER = "tcp/10.1.2.3:7447"


def resolved(config: BusConfig = BusConfig(), **env: str):
    return resolve_bus(config, env)


# -- endpoints and mode --


def test_defaults_without_environment_are_a_loopback_peer():
    bus = resolved()
    assert (bus.mode, bus.connect, bus.listen, bus.connect_timeout_ms) == ("peer", (), ("tcp/127.0.0.1:0",), -1)
    assert not bus.secure


def test_environment_fills_empty_fields():
    bus = resolved(DRIVEBENCH_ROUTER=f" {ROUTER} , tcp/10.1.2.4:7447", DRIVEBENCH_MODE="client")
    assert bus.mode == "client"
    assert bus.connect == (ROUTER, "tcp/10.1.2.4:7447")
    assert bus.listen == ()  # a client never listens


def test_a_peer_connecting_elsewhere_listens_on_every_interface_unless_told():
    assert resolved(DRIVEBENCH_ROUTER=ROUTER).listen == ("tcp/0.0.0.0:0",)
    assert resolved(DRIVEBENCH_ROUTER=ROUTER, DRIVEBENCH_LISTEN="tcp/10.1.2.9:7450").listen == ("tcp/10.1.2.9:7450",)


def test_config_wins_over_environment():
    config = BusConfig(mode="peer", connect=["tcp/127.0.0.1:7000"], listen=["tcp/127.0.0.1:7001"])
    bus = resolved(config, DRIVEBENCH_ROUTER=ROUTER, DRIVEBENCH_MODE="client", DRIVEBENCH_LISTEN="tcp/0.0.0.0:9")
    assert (bus.mode, bus.connect, bus.listen) == ("peer", ("tcp/127.0.0.1:7000",), ("tcp/127.0.0.1:7001",))


def test_observers_stay_clients_and_routers_stay_routers_whatever_the_environment():
    assert resolved(OBSERVER_BUS, DRIVEBENCH_MODE="peer", DRIVEBENCH_LISTEN="tcp/0.0.0.0:9").mode == "client"
    assert resolved(OBSERVER_BUS, DRIVEBENCH_LISTEN="tcp/0.0.0.0:9").listen == ()
    router = resolved(BusConfig(mode="router"), DRIVEBENCH_MODE="client", DRIVEBENCH_ROUTER=ROUTER)
    assert (router.mode, router.connect, router.listen) == ("router", (), ("tcp/[::]:7447",))
    assert resolved(BusConfig(mode="router"), DRIVEBENCH_LISTEN="tcp/0.0.0.0:7500").listen == ("tcp/0.0.0.0:7500",)


def test_overrides_and_files_are_explicit_config(tmp_path):
    path = tmp_path / "sim.yaml"
    path.write_text("bus:\n  connect: [tcp/127.0.0.1:7000]\n")

    class Config(msgspec.Struct, frozen=True, kw_only=True, forbid_unknown_fields=True):
        bus: BusConfig = BusConfig()

    config = load_config(Config, path=path, overrides=["bus.mode=client"])
    bus = resolved(config.bus, DRIVEBENCH_ROUTER=ROUTER, DRIVEBENCH_MODE="peer")
    assert (bus.mode, bus.connect) == ("client", ("tcp/127.0.0.1:7000",))


@pytest.mark.parametrize(
    ("env", "message"),
    [
        ({"DRIVEBENCH_MODE": "router"}, "DRIVEBENCH_MODE must be peer or client, got 'router'"),
        ({"DRIVEBENCH_MODE": "Peer"}, "DRIVEBENCH_MODE must be peer or client, got 'Peer'"),
        ({"DRIVEBENCH_ROUTER": "10.1.2.3:7447"}, "DRIVEBENCH_ROUTER: '10.1.2.3:7447' is not an endpoint"),
        ({"DRIVEBENCH_ROUTER": "htp/10.1.2.3:7447"}, "DRIVEBENCH_ROUTER: 'htp/10.1.2.3:7447' is not an endpoint"),
        ({"DRIVEBENCH_LISTEN": "tcp/0.0.0.0:1,0.0.0.0:2"}, "DRIVEBENCH_LISTEN: '0.0.0.0:2' is not an endpoint"),
    ],
)
def test_a_bad_variable_is_one_line_naming_it(env, message):
    with pytest.raises(BusError) as error:
        resolved(**env)
    assert message in str(error.value)
    assert "\n" not in str(error.value)


def test_a_bad_config_value_names_the_field():
    class Config(msgspec.Struct, frozen=True, kw_only=True):
        bus: BusConfig = BusConfig()

    with pytest.raises(ConfigError, match=r"mode must be peer, client or router, got 'server' \(at bus\)$"):
        load_config(Config, overrides=["bus.mode=server"])
    with pytest.raises(ConfigError, match=r"connect: 'localhost:7447' is not an endpoint.* \(at bus\)$"):
        load_config(Config, overrides=["bus.connect=[localhost:7447]"])


def test_zenoh_accepts_every_resolved_config(tmp_path):
    ca, cert, key = (tmp_path / name for name in ("ca.pem", "me.pem", "me.key"))
    for path in (ca, cert, key):
        path.write_text("not checked here: Zenoh reads it when it connects\n")
    for config, env in [
        (BusConfig(), {}),
        (OBSERVER_BUS, {"DRIVEBENCH_ROUTER": ROUTER}),
        (BusConfig(mode="router", listen=["tcp/127.0.0.1:0"]), {}),
        (
            BusConfig(connect=["tls/router.lan:7447"]),
            {
                "DRIVEBENCH_TLS_ROOT_CA": str(ca),
                "DRIVEBENCH_TLS_CERT": str(cert),
                "DRIVEBENCH_TLS_KEY": str(key),
                "DRIVEBENCH_USER": "u",
                "DRIVEBENCH_PASSWORD": "p",
            },
        ),
    ]:
        zenoh_config(config, name="test", env=env)


# -- TLS and credentials --


@pytest.fixture
def pem(tmp_path):
    paths = {}
    for name in ("ca.pem", "me.pem", "me.key"):
        (tmp_path / name).write_text("PEM\n")
        paths[name] = str(tmp_path / name)
    return paths


def test_security_from_environment_makes_a_client_with_a_finite_connect_timeout(pem):
    bus = resolved(
        DRIVEBENCH_ROUTER="tls/router.lan:7447",
        DRIVEBENCH_TLS_ROOT_CA=pem["ca.pem"],
        DRIVEBENCH_TLS_CERT=pem["me.pem"],
        DRIVEBENCH_TLS_KEY=pem["me.key"],
        DRIVEBENCH_LISTEN="tcp/0.0.0.0:9",
    )
    assert bus.secure
    assert (bus.mode, bus.listen, bus.connect_timeout_ms) == ("client", (), 10_000)
    tls = zenoh_settings(bus, name="t")["transport"]["link"]["tls"]
    # Measured: a client shows its certificate to a mutual-TLS router only with enable_mtls.
    assert tls == {
        "root_ca_certificate": pem["ca.pem"],
        "connect_certificate": pem["me.pem"],
        "connect_private_key": pem["me.key"],
        "enable_mtls": True,
    }


def test_a_tls_endpoint_alone_is_secure():
    assert resolved(BusConfig(connect=["tls/router.lan:7447"])).mode == "client"


def test_config_files_win_over_environment_files(pem, tmp_path):
    other = tmp_path / "other.pem"
    other.write_text("PEM\n")
    bus = resolved(BusConfig(tls_root_ca=str(other)), DRIVEBENCH_TLS_ROOT_CA=pem["ca.pem"])
    assert bus.tls_root_ca == str(other)


@pytest.mark.parametrize(
    ("config", "env", "message"),
    [
        (
            BusConfig(tls_cert="/nonexistent/me.pem", tls_key="/nonexistent/me.key"),
            {},
            "bus.tls_cert: cannot read /nonexistent/me.pem: No such file or directory",
        ),
        (
            BusConfig(),
            {"DRIVEBENCH_TLS_ROOT_CA": "/nonexistent/ca.pem"},
            "DRIVEBENCH_TLS_ROOT_CA: cannot read /nonexistent/ca.pem: No such file or directory",
        ),
        (
            BusConfig(user="u", password_file="/nonexistent/pw"),
            {},
            "bus.password_file: cannot read /nonexistent/pw: No such file or directory",
        ),
    ],
)
def test_a_missing_file_is_one_line_naming_field_and_path(config, env, message):
    with pytest.raises(BusError) as error:
        resolved(config, **env)
    assert str(error.value) == message


def test_incomplete_security_settings_are_refused(pem, tmp_path):
    empty = tmp_path / "empty.pw"
    empty.write_text("\n")
    with pytest.raises(BusError, match=f"bus.password_file: {empty} has no password on its first line"):
        resolved(BusConfig(user="alice", password_file=str(empty)))
    with pytest.raises(BusError, match="DRIVEBENCH_TLS_CERT is set but not its pair"):
        resolved(DRIVEBENCH_TLS_CERT=pem["me.pem"])
    with pytest.raises(BusError, match="DRIVEBENCH_USER is set but no password"):
        resolved(DRIVEBENCH_USER="alice")
    with pytest.raises(BusError, match="DRIVEBENCH_PASSWORD is set but no user"):
        resolved(DRIVEBENCH_PASSWORD="secret")


def test_a_secure_process_must_be_a_listenerless_client(pem):
    with pytest.raises(
        BusError, match="bus.mode is peer, but TLS or credentials are set: a secure process must be a client"
    ):
        resolved(BusConfig(mode="peer", connect=["tls/router.lan:7447"]), DRIVEBENCH_TLS_ROOT_CA=pem["ca.pem"])
    with pytest.raises(BusError, match="DRIVEBENCH_MODE is peer"):
        resolved(DRIVEBENCH_MODE="peer", DRIVEBENCH_USER="alice", DRIVEBENCH_PASSWORD="secret")
    with pytest.raises(BusError, match="a secure client must not listen"):
        resolved(BusConfig(mode="client", listen=["tcp/0.0.0.0:0"]), DRIVEBENCH_TLS_ROOT_CA=pem["ca.pem"])


def test_a_tls_listener_needs_the_routers_certificate(pem):
    with pytest.raises(BusError, match=r"listening on \['tls/0.0.0.0:7447'\] needs the router's certificate"):
        resolved(BusConfig(mode="router", listen=["tls/0.0.0.0:7447"]))
    router = resolved(
        BusConfig(mode="router", listen=["tls/0.0.0.0:7447"]),
        DRIVEBENCH_TLS_CERT=pem["me.pem"],
        DRIVEBENCH_TLS_KEY=pem["me.key"],
    )
    assert router.connect_timeout_ms == -1  # a router is never a client
    tls = zenoh_settings(router, name="r")["transport"]["link"]["tls"]
    assert (tls["listen_certificate"], tls["listen_private_key"]) == (pem["me.pem"], pem["me.key"])


def test_the_password_comes_from_a_file_or_the_environment_and_is_never_shown(tmp_path):
    secret = tmp_path / "pw"
    secret.write_text("s3cret:with colon\nignored\n")
    from_file = resolved(BusConfig(user="alice", password_file=str(secret)), DRIVEBENCH_PASSWORD="other")
    assert from_file.password == "s3cret:with colon"
    from_env = resolved(DRIVEBENCH_USER="alice", DRIVEBENCH_PASSWORD="other")
    assert from_env.password == "other"
    for bus in (from_file, from_env):
        assert "s3cret" not in repr(bus) + bus.describe() and "other" not in repr(bus) + bus.describe()
    assert zenoh_settings(from_env, name="t")["transport"]["auth"] == {"usrpwd": {"user": "alice", "password": "other"}}
    assert "password" not in msgspec.structs.asdict(BusConfig())  # configs are logged and recorded: no secret in them


# -- real processes: the error is one line on stderr and exit code 2 --


def test_a_service_with_a_bad_variable_exits_2_with_one_line():
    result = subprocess.run(
        [sys.executable, "-m", "brains", "--brain", "constant"],
        capture_output=True,
        text=True,
        timeout=60,
        env=clean_env(DRIVEBENCH_MODE="server", DRIVEBENCH_ROUTER="tcp/127.0.0.1:9"),
    )
    assert result.returncode == 2, result.stderr
    last = result.stderr.strip().splitlines()[-1]
    assert last == "brain: error: DRIVEBENCH_MODE must be peer or client, got 'server'"


def test_a_router_with_a_missing_certificate_exits_2_with_one_line(tmp_path):
    config = tmp_path / "router.yaml"
    config.write_text(
        json.dumps(
            {
                "bus": {
                    "listen": ["tls/127.0.0.1:0"],
                    "tls_cert": str(tmp_path / "router.pem"),
                    "tls_key": str(tmp_path / "router.key"),
                }
            }
        )
    )
    result = subprocess.run(
        [sys.executable, "-m", "services.router", "--config", str(config)],
        capture_output=True,
        text=True,
        timeout=60,
        env=clean_env(),
    )
    assert result.returncode == 2, result.stderr
    assert result.stderr.strip().splitlines()[-1] == (
        f"router: error: bus.tls_cert: cannot read {tmp_path / 'router.pem'}: No such file or directory"
    )
