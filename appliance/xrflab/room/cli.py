"""``xrf room`` (the room service) and ``xrf room join`` (enrol this bench in a room).
Registered in cli.py's EXTERNAL_SUBCOMMANDS; heavy imports stay inside ``run``."""

from __future__ import annotations

import argparse
from pathlib import Path

from .topics import MQTT_PORT, MQTT_TLS_PORT

HELP = "the lab room: every bench on one page, one class list (`xrf room join` enrols a bench)"


def default_room_dir() -> Path:
    from ..server.settings import default_data_dir

    return default_data_dir().parent / "xrf-lab-room"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "--data", type=Path, default=None, help="the room's data folder (default ~/.local/share/xrf-lab-room)"
    )
    parser.add_argument("--host", default="127.0.0.1", help="address of the room page (0.0.0.0 for the lab network)")
    parser.add_argument("--port", type=int, default=8100, help="port of the room page (default 8100)")
    parser.add_argument(
        "--broker-name",
        action="append",
        default=[],
        metavar="ADDR",
        help="the address benches use for the broker (repeatable; the first is given to benches; "
        "the broker's certificate names them all; default: 127.0.0.1)",
    )
    parser.add_argument(
        "--broker-port", type=int, default=MQTT_PORT, help=f"plain MQTT port (0: none; default {MQTT_PORT})"
    )
    parser.add_argument(
        "--broker-tls-port",
        type=int,
        default=MQTT_TLS_PORT,
        help=f"MQTT over TLS port (0: none; default {MQTT_TLS_PORT})",
    )
    parser.add_argument(
        "--no-tls", action="store_true", help="enrol benches on the plain port (a closed lab network only)"
    )
    parser.add_argument(
        "--external-broker",
        action="store_true",
        help="do not start mosquitto: one is run with <data>/broker/mosquitto.conf (e.g. by systemd)",
    )
    sub = parser.add_subparsers(dest="room_cmd")
    join = sub.add_parser("join", help="enrol this bench in a room with a join code from the room page")
    join.add_argument("room_url", help="the room's address, e.g. http://10.0.0.5:8100")
    join.add_argument("code", help="the one-time join code shown on the room page")
    join.add_argument("--name", required=True, help="this bench's name in the room (a-z, 0-9, '-'), e.g. bench07")
    join.add_argument(
        "--data", dest="bench_data", type=Path, default=None, help="the appliance's data folder (default: xrf serve's)"
    )
    join.add_argument(
        "--url",
        default="",
        help="this bench's dashboard address as the room's browsers reach it, recorded by the room "
        "(default: this bench's address towards the room, the appliance's default port)",
    )


def run(args: argparse.Namespace) -> int:
    if args.room_cmd == "join":
        from ..server.settings import default_data_dir
        from .enrol import join

        data = (args.bench_data or default_data_dir()).expanduser()
        try:
            e = join(args.room_url, args.code, args.name, data, args.url)
        except (RuntimeError, ValueError) as exc:
            print(f"xrf room join: {exc}")
            return 1
        b = e.broker
        print(
            f"xrf room join: bench {e.name} enrolled; broker {b.host}:{b.port} "
            f"({'TLS' if b.ca_pem else 'plain'}); dashboard {e.dashboard_url}; "
            "the running appliance joins within seconds"
        )
        return 0
    import os

    import uvicorn

    from .service import RoomConfig, create_room_app

    config = RoomConfig(
        data_dir=(args.data or default_room_dir()).expanduser(),
        host=args.host,
        port=args.port,
        broker_names=args.broker_name or ["127.0.0.1", "localhost"],
        broker_port=args.broker_port or None,
        broker_tls_port=args.broker_tls_port or None,
        tls=not args.no_tls,
        spawn_broker=not args.external_broker,
    )
    os.umask(0o077)  # the room's databases, keys and broker secrets are its own
    print(f"XRF Lab room: data in {config.data_dir}; open http://{args.host}:{args.port}/", flush=True)
    uvicorn.run(create_room_app(config), host=args.host, port=args.port, log_level="warning", proxy_headers=False)
    return 0
