"""``python -m services.router``: a Zenoh router in a Python process (discovery hub of a stack).

Peers connect to it to find each other, then exchange data over direct links; it carries data itself only for
clients. No plugins (REST, storage) load in a Python router: use ``zenohd`` for those.
"""

from __future__ import annotations

import json
import logging
import sys
import threading

import msgspec

from protocol.bus import Bus, BusConfig

log = logging.getLogger("drivebench.router")


class RouterConfig(msgspec.Struct, frozen=True, kw_only=True, forbid_unknown_fields=True):
    """listen: endpoints the router accepts connections on (compose: ``tcp/[::]:7447``)."""

    bus: BusConfig = BusConfig(mode="router", listen=["tcp/[::]:7447"])


def main(argv: list[str] | None = None) -> int:
    from protocol.runtime import load_config, log_config, run_service, service_parser

    parser = service_parser("drivebench router: a Zenoh router for one stack")
    parser.add_argument("--listen", action="append", help="endpoint to listen on (repeatable)")
    args = parser.parse_args(argv)

    def run() -> int:
        overrides = list(args.set) + ["bus.mode=router"]
        if args.listen:
            overrides.append(f"bus.listen={json.dumps(args.listen)}")
        config = load_config(RouterConfig, path=args.config, overrides=overrides,
                             base={"bus": msgspec.to_builtins(RouterConfig().bus)})
        log_config(config)
        with Bus(config.bus, name="router"):
            log.info("router listening on %s", ", ".join(config.bus.listen))
            threading.Event().wait()
        return 0

    return run_service("router", run)


if __name__ == "__main__":
    sys.exit(main())
