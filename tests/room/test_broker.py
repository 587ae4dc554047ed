"""The broker as the room configures it: per-bench credentials, the ACL (a bench writes only under
its own name, only the room commands) and TLS with the room's own CA. Real mosquitto, real paho."""

from __future__ import annotations

import json
import ssl
import subprocess
import time

import pytest

from xrf_testing.harness import wait_for
from xrf_testing.room_support import Recorder, bench_endpoint, room_endpoint
from xrflab.room import mqtt, topics
from xrflab.room.broker import acl_text

NOT_AUTHORIZED = 135  # MQTT 5 reason code
# How long a test listens for a message that must not arrive.
SILENCE_S = 0.3


def _enrol(files, *names):
    pws = {}
    for n in names:
        pws[n] = f"pw-{n}-0123456789"
        files.set_password(n, pws[n])
    return pws


def test_bench_publishes_only_under_its_own_name(broker) -> None:
    files = broker.files
    pws = _enrol(files, "b1", "b2")
    assert broker.files.reload()
    room = Recorder(room_endpoint(files), "room", [topics.BENCH_ALL])
    b1 = Recorder(bench_endpoint(files, "b1", pws["b1"]), "b1", [topics.cmd("b1"), topics.CMD_ALL, topics.cmd("b2")])
    try:
        assert room.wait_connected() and b1.wait_connected()
        own = b1.publish(topics.bench("b1", "status"), {"seq": 1, "who": "b1"})
        assert mqtt.reason_ok(b1.wait_ack(own))
        room.wait_message(lambda t, p: t == topics.bench("b1", "status"))
        # b1 forges b2's status: the broker refuses it (MQTT 5 PUBACK "not authorized") and the
        # room never sees it
        forged = b1.publish(topics.bench("b2", "status"), {"seq": 99, "who": "forged"})
        assert int(b1.wait_ack(forged).value) == NOT_AUTHORIZED
        # a bench cannot command
        cmd = b1.publish(topics.CMD_ALL, {"cmd": "stop"})
        assert int(b1.wait_ack(cmd).value) == NOT_AUTHORIZED
        # nor rewrite the class list
        acc = b1.publish(topics.ACCOUNTS, {"users": []})
        assert int(b1.wait_ack(acc).value) == NOT_AUTHORIZED
        # nor say that the room listens (its peers would send their events to nobody)
        fake = b1.publish(topics.ROOM_ONLINE, {"online": True, "conn": "b1"}, retain=True)
        assert int(b1.wait_ack(fake).value) == NOT_AUTHORIZED
        # the room commands b1 and all; b1 never receives b2's commands
        room.publish(topics.cmd("b2"), {"id": "x2", "cmd": "stop"})
        room.publish(topics.cmd("b1"), {"id": "x1", "cmd": "stop"})
        room.publish(topics.CMD_ALL, {"id": "xa", "cmd": "stop"})
        b1.wait_message(lambda t, p: t == topics.CMD_ALL)
        b1.wait_message(lambda t, p: t == topics.cmd("b1"))
        # b2's command went out before b1's, so it would have arrived by now; still listen a while
        time.sleep(SILENCE_S)  # the point: listen a while for what must NOT arrive
        assert not b1.received(lambda t, p: t == topics.cmd("b2"))
        assert not room.received(lambda t, p: b"forged" in p)
        assert not b1.received(lambda t, p: t == topics.CMD_ALL and b"users" in p)
    finally:
        room.close()
        b1.close()


def test_wrong_password_and_anonymous_refused(broker) -> None:
    files = broker.files
    _enrol(files, "b1")
    broker.files.reload()
    wrong = Recorder(bench_endpoint(files, "b1", "not-the-password"), "w")
    anon = Recorder(mqtt.Endpoint("127.0.0.1", files.port, "", ""), "anon")
    try:
        assert not wrong.wait_connected(3)
        assert not anon.wait_connected(3)
    finally:
        wrong.close()
        anon.close()
    # the CLI client too (mosquitto-clients), against the same broker
    r = subprocess.run(
        [
            "mosquitto_pub",
            "-h",
            "127.0.0.1",
            "-p",
            str(files.port),
            "-t",
            "xrf/cmd/all",
            "-m",
            "x",
            "-u",
            "b1",
            "-P",
            "nope",
        ],
        capture_output=True,
        text=True,
        timeout=10,
    )
    assert r.returncode != 0


def test_deleted_bench_is_refused_after_reload(broker) -> None:
    files = broker.files
    pws = _enrol(files, "b3")
    files.reload()
    ok = Recorder(bench_endpoint(files, "b3", pws["b3"]), "b3")
    assert ok.wait_connected()
    ok.close()
    files.delete_user("b3")
    assert files.reload()

    def refused() -> bool:  # once mosquitto has applied the reload (SIGHUP, asynchronous)
        again = Recorder(bench_endpoint(files, "b3", pws["b3"]), "b3b")
        try:
            return not again.wait_connected(3)
        finally:
            again.close()

    wait_for(refused, 15, "the deleted bench to be refused")


def test_tls_with_the_rooms_own_ca(broker) -> None:
    files = broker.files
    pws = _enrol(files, "b1")
    files.reload()
    # with the room's CA: connected, and the broker's certificate names 127.0.0.1
    good = Recorder(bench_endpoint(files, "b1", pws["b1"], tls=True), "tls-good", [topics.cmd("b1")])
    try:
        assert good.wait_connected()
        room = Recorder(room_endpoint(files, tls=True), "room-tls")
        assert room.wait_connected()
        room.publish(topics.cmd("b1"), {"cmd": "stop", "id": "t"})
        good.wait_message(lambda t, p: json.loads(p).get("id") == "t")
        room.close()
    finally:
        good.close()
    # the system's CAs do not know the room's: the handshake fails
    ctx = ssl.create_default_context()
    import socket

    with socket.create_connection(("127.0.0.1", files.tls_port), timeout=5) as raw:
        with pytest.raises(ssl.SSLCertVerificationError):
            ctx.wrap_socket(raw, server_hostname="127.0.0.1")
    # a name the certificate does not carry is refused as well (hostname check)
    ctx2 = ssl.create_default_context(cadata=files.ca_cert.read_text())
    with socket.create_connection(("127.0.0.1", files.tls_port), timeout=5) as raw:
        with pytest.raises(ssl.SSLCertVerificationError):
            ctx2.wrap_socket(raw, server_hostname="broker.elsewhere.example")
    # and mosquitto's own client with the CA file gets through (openssl-made CA, mosquitto's TLS)
    r = subprocess.run(
        [
            "mosquitto_pub",
            "-h",
            "127.0.0.1",
            "-p",
            str(files.tls_port),
            "--cafile",
            str(files.ca_cert),
            "-t",
            topics.bench("b1", "event"),
            "-m",
            "{}",
            "-u",
            "b1",
            "-P",
            pws["b1"],
            "-q",
            "1",
        ],
        capture_output=True,
        text=True,
        timeout=10,
    )
    assert r.returncode == 0, r.stderr


def test_acl_names_every_rule() -> None:
    text = acl_text()
    assert "pattern write xrf/bench/%u/#" in text and "user room" in text
    assert "pattern write xrf/cmd" not in text
