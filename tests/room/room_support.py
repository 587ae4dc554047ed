"""Helpers of the room tests: a broker on free loopback ports and MQTT clients that keep what they
receive, so tests wait for conditions instead of sleeping."""

from __future__ import annotations

import json
import socket
import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

from xrflab.room import mqtt, topics
from xrflab.room.broker import ROOM_USER, BrokerFiles, BrokerProcess


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def broker_files(folder: Path, bind: str = "127.0.0.1", names: list[str] | None = None) -> BrokerFiles:
    files = BrokerFiles(folder, port=free_port(), tls_port=free_port(), bind=bind,
                        names=names or ["127.0.0.1", "localhost"])
    files.write()
    return files


def start_broker(files: BrokerFiles) -> BrokerProcess:
    proc = BrokerProcess(files)
    proc.start()
    return proc


def room_endpoint(files: BrokerFiles, tls: bool = False) -> mqtt.Endpoint:
    return mqtt.Endpoint("127.0.0.1", files.tls_port if tls else files.port, ROOM_USER, files.room_password(),
                         files.ca_cert.read_text() if tls else "")


class Recorder:
    """A connected MQTT client that records every message it receives and every PUBACK."""

    def __init__(self, endpoint: mqtt.Endpoint, client_id: str, subscribe: list[str] | None = None,
                 will: tuple[str, bytes] | None = None) -> None:
        self.messages: list[tuple[str, bytes, bool]] = []
        self.acks: dict[int, Any] = {}
        self.connected = threading.Event()
        self.refused: Any = None
        self._lock = threading.Lock()
        self.c = mqtt.client(endpoint, client_id, will)
        subs = subscribe or []

        def on_connect(c: Any, _u: Any, _f: Any, rc: Any, _p: Any = None) -> None:
            if not mqtt.reason_ok(rc):
                self.refused = rc
                return
            for s in subs:
                c.subscribe(s, qos=1)
            self.connected.set()

        def on_message(_c: Any, _u: Any, msg: Any) -> None:
            with self._lock:
                self.messages.append((msg.topic, msg.payload, bool(msg.retain)))

        def on_publish(_c: Any, _u: Any, mid: int, rc: Any, _p: Any = None) -> None:
            self.acks[mid] = rc

        self.c.on_connect, self.c.on_message, self.c.on_publish = on_connect, on_message, on_publish
        mqtt.connect_async(self.c, endpoint)
        self.c.loop_start()

    def wait_connected(self, timeout: float = 5.0) -> bool:
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            if self.connected.is_set():
                time.sleep(0.1)  # the SUBACK
                return True
            if self.refused is not None:
                return False
            time.sleep(0.02)
        return False

    def publish(self, topic: str, payload: Any, qos: int = 1, retain: bool = False) -> int:
        data = payload if isinstance(payload, bytes) else json.dumps(payload).encode()
        info = self.c.publish(topic, data, qos=qos, retain=retain)
        return info.mid

    def wait_ack(self, mid: int, timeout: float = 5.0) -> Any:
        deadline = time.monotonic() + timeout
        while mid not in self.acks:
            assert time.monotonic() < deadline, f"no PUBACK for {mid}"
            time.sleep(0.01)
        return self.acks[mid]

    def received(self, pred: Callable[[str, bytes], bool]) -> list[tuple[str, bytes, bool]]:
        with self._lock:
            return [m for m in self.messages if pred(m[0], m[1])]

    def wait_message(self, pred: Callable[[str, bytes], bool], timeout: float = 5.0) -> tuple[str, bytes, bool]:
        deadline = time.monotonic() + timeout
        while True:
            got = self.received(pred)
            if got:
                return got[0]
            assert time.monotonic() < deadline, "no matching MQTT message"
            time.sleep(0.01)

    def close(self) -> None:
        self.c.disconnect()
        self.c.loop_stop()


def bench_endpoint(files: BrokerFiles, name: str, password: str, tls: bool = False) -> mqtt.Endpoint:
    return mqtt.Endpoint("127.0.0.1", files.tls_port if tls else files.port, name, password,
                         files.ca_cert.read_text() if tls else "")


__all__ = ["Recorder", "broker_files", "start_broker", "room_endpoint", "bench_endpoint", "free_port", "topics"]
