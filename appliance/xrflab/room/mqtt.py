"""One way to connect to the room's broker, for benches, the room and the benchmark: paho-mqtt's
own client (MQTT 5, its network thread, its reconnect) with our credentials and TLS settings.

Keep-alive is short on purpose: mosquitto publishes a client's last will when it has heard
nothing for 1.5 keep-alives, so a bench that loses power or network is offline on the room page
within KEEPALIVE_S * 1.5 (3 s) plus one message.
"""

from __future__ import annotations

import ssl
from dataclasses import dataclass
from typing import Any

import paho.mqtt.client as paho
from paho.mqtt.enums import CallbackAPIVersion

KEEPALIVE_S = 2
RECONNECT_MIN_S, RECONNECT_MAX_S = 0.2, 2


@dataclass(frozen=True)
class Endpoint:
    """Where the broker is and who we are: what `xrf room join` stores on a bench."""

    host: str
    port: int
    username: str
    password: str
    ca_pem: str = ""  # the room's CA: TLS when set (the broker's certificate must name `host`)

    @property
    def tls(self) -> bool:
        return bool(self.ca_pem)


def client(endpoint: Endpoint, client_id: str, will: tuple[str, bytes] | None = None) -> paho.Client:
    """A configured, not yet connected client. The caller sets callbacks, then
    ``connect_async(endpoint)`` + ``loop_start()``."""
    c = paho.Client(CallbackAPIVersion.VERSION2, client_id=client_id, protocol=paho.MQTTv5)
    c.username_pw_set(endpoint.username, endpoint.password)
    if endpoint.tls:
        ctx = ssl.create_default_context(ssl.Purpose.SERVER_AUTH, cadata=endpoint.ca_pem)
        ctx.minimum_version = ssl.TLSVersion.TLSv1_2
        c.tls_set_context(ctx)
    if will is not None:
        c.will_set(will[0], will[1], qos=1, retain=True)
    # paho's hints say int seconds; it computes with floats, and 0.2 s keeps a bench's return quick.
    c.reconnect_delay_set(RECONNECT_MIN_S, RECONNECT_MAX_S)  # type: ignore[arg-type]
    # Our own queue bounds what waits for the broker (publisher.py); paho's is for in-flight QoS 1.
    c.max_queued_messages_set(0)
    return c


def connect_async(c: paho.Client, endpoint: Endpoint) -> None:
    c.connect_async(endpoint.host, endpoint.port, keepalive=KEEPALIVE_S, clean_start=True)


def reason_ok(reason_code: Any) -> bool:
    """paho 2 hands ReasonCode objects (or ints for MQTT 3)."""
    failure = getattr(reason_code, "is_failure", None)
    return not failure if failure is not None else int(reason_code) == 0
