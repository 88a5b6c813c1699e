"""``python -m services.router``: a Zenoh router in a Python process (discovery hub of a stack).

Peers connect to it to find each other, then exchange data over direct links; it carries data itself only for
clients. No plugins (REST, storage) load in a Python router: use ``zenohd`` for those.

A secure router (``docs/security.md``) listens on ``tls/...``, may demand clients' certificates (``mtls``) and/or
user names and passwords (``users_file``), and enforces access control: drivebench's roles (``roles``) or a
hand-written Zenoh policy (``access_control_file``). Every process of a secure stack is then a client of it.
"""

from __future__ import annotations

import json
import logging
import sys
import time

import msgspec

from protocol.bus import Bus, BusConfig, resolve_bus
from protocol.deploy.security import Identity, router_settings

log = logging.getLogger("drivebench.router")


class RouterConfig(msgspec.Struct, frozen=True, kw_only=True, forbid_unknown_fields=True):
    """Config of the router process.

    bus: its bus; ``mode`` is always router. ``bus.listen``: endpoints it accepts connections on (empty =
        ``DRIVEBENCH_LISTEN``, else ``tcp/[::]:7447``); ``tls/HOST:PORT`` for TLS. ``bus.tls_cert`` / ``bus.tls_key``:
        the certificate it shows clients (its names must include the host they connect to) and its key;
        ``bus.tls_root_ca``: the CA that signed the clients' certificates (mutual TLS). Each falls back to
        ``DRIVEBENCH_TLS_CERT`` / ``_KEY`` / ``_ROOT_CA``.
    mtls: demand a certificate signed by ``bus.tls_root_ca`` from every client; its common name is the client's
        identity for ``roles``.
    users_file: ``user:password`` lines; every client must then authenticate with one (``bus.user``,
        ``DRIVEBENCH_USER`` / ``DRIVEBENCH_PASSWORD``); the user name is an identity for ``roles``.
    roles: access control from drivebench's roles (``protocol.deploy.security.ROLES``: brain, orchestrator, service,
        simulator, noise, scorer, recorder, viz, replay, observer), each a list of identities: a name (certificate
        common name or user name) or ``{cert_common_name: ..., username: ...}``. Default deny: an identity in no
        role gets nothing.
    access_control_file: instead of ``roles``, a hand-written Zenoh ``access_control`` section (YAML, JSON or
        JSON5).
    """

    bus: BusConfig = BusConfig(mode="router")
    mtls: bool = False
    users_file: str = ""
    roles: dict[str, list[str | Identity]] = {}
    access_control_file: str = ""


def main(argv: list[str] | None = None) -> int:
    from protocol.deploy.runtime import load_config, log_config, run_service, service_parser, stop_requested

    parser = service_parser("drivebench router: a Zenoh router for one stack")
    parser.add_argument("--listen", action="append", help="endpoint to listen on (repeatable)")
    args = parser.parse_args(argv)

    def run() -> int:
        overrides = list(args.set) + ["bus.mode=router"]
        if args.listen:
            overrides.append(f"bus.listen={json.dumps(args.listen)}")
        config = load_config(RouterConfig, path=args.config, overrides=overrides)
        log_config(config)
        bus_config = config.bus
        resolved = resolve_bus(bus_config)
        extra = router_settings(
            mtls=config.mtls,
            tls_root_ca=resolved.tls_root_ca,
            tls_cert=resolved.tls_cert,
            listen=resolved.listen,
            users_file=config.users_file,
            roles=config.roles,
            access_control_file=config.access_control_file,
        )
        if "access_control" in extra and any(e.split("/", 1)[0] not in ("tls", "quic") for e in resolved.listen):
            log.warning("access control with a plain (non-TLS) listener: links on it carry no certificate")
        with Bus(bus_config, name="router", extra=extra) as bus:
            features = (
                ("mTLS", config.mtls),
                ("user/password", bool(config.users_file)),
                ("access control", "access_control" in extra),
            )
            security = ", ".join(name for name, on in features if on)
            log.info("router listening on %s%s", ", ".join(bus.resolved.listen), f" ({security})" if security else "")
            while not stop_requested():
                time.sleep(0.2)
        return 0

    return run_service("router", run)


if __name__ == "__main__":
    sys.exit(main())
