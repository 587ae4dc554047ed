"""The room's MQTT broker: Eclipse Mosquitto's configuration, credentials, ACL and TLS files.

Nothing of the transport is ours: this module only writes the files mosquitto reads and asks the
distribution's own tools to make the secrets (``mosquitto_passwd`` hashes the passwords, ``openssl``
makes the room's CA and the broker's certificate). Everything lives in one folder,
``<room data>/broker/``, private to the room's user (0700, files 0600):

    mosquitto.conf   listeners (plain and/or TLS), the files below, pid_file
    passwd           one line per user (``room`` and every enrolled bench), mosquitto_passwd's hashes
    acl              who may read and write which topic (topics.py)
    ca.crt ca.key    the room's own certificate authority (benches get ca.crt at enrolment)
    server.crt/.key  the broker's certificate, signed by that CA, naming the addresses benches use
    room.secret      the room's own broker password (the room service reads it)

Changing credentials or the ACL is followed by SIGHUP to the pid in ``mosquitto.pid``: mosquitto
re-reads its password and ACL files without dropping anyone (``reload``).
"""

from __future__ import annotations

import ipaddress
import os
import pwd
import secrets
import shutil
import signal
import subprocess
import tempfile
import time
from dataclasses import dataclass, field
from pathlib import Path

from . import payloads, topics

ROOM_USER = "room"


class BrokerError(Exception):
    pass


def private_write(path: Path, text: str) -> None:
    """Write atomically, 0600 from the first byte (a password or key is never world-readable)."""
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.")
    try:
        os.fchmod(fd, 0o600)
        with os.fdopen(fd, "w") as f:
            f.write(text)
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise


def tool(name: str) -> str:
    found = shutil.which(name) or next(
        (p for p in (f"/usr/sbin/{name}", f"/usr/bin/{name}") if os.access(p, os.X_OK)), None
    )
    if not found:
        raise BrokerError(f"{name} not found: install the Debian packages mosquitto and mosquitto-clients (./lab does)")
    return found


def acl_text() -> str:
    """The ACL: the room reads and writes everything of the room; a bench writes only under its own
    name (its username, ``%u``) and reads only the commands meant for it, for all, the class list,
    the published assignments and whether the room listens.
    Anything not granted is refused by the broker (a forged status is dropped; with MQTT 5 and QoS 1
    the publisher is told "not authorized")."""
    root = topics.ROOT
    return "\n".join(
        [
            "# Written by xrflab.room.broker; edits are overwritten.",
            f"user {ROOM_USER}",
            f"topic readwrite {root}/#",
            "",
            "# every other user is a bench named by its username",
            f"pattern write {root}/bench/%u/#",
            f"pattern read {root}/cmd/%u",
            f"pattern read {topics.CMD_ALL}",
            f"pattern read {topics.ACCOUNTS}",
            f"pattern read {topics.ASSIGNMENTS}",
            f"pattern read {topics.ROOM_ONLINE}",
            "",
        ]
    )


@dataclass
class BrokerFiles:
    """The broker folder and how mosquitto listens. `port`: plain MQTT (None: none); `tls_port`:
    MQTT over TLS (None: none); `bind`: the listeners' address; `names`: what benches call the
    broker (its certificate's subjectAltName: addresses and DNS names)."""

    folder: Path
    port: int | None = topics.MQTT_PORT
    tls_port: int | None = topics.MQTT_TLS_PORT
    bind: str = "0.0.0.0"
    names: list[str] = field(default_factory=lambda: ["127.0.0.1", "localhost"])

    # -- paths --------------------------------------------------------------------------------
    @property
    def conf(self) -> Path:
        return self.folder / "mosquitto.conf"

    @property
    def passwd(self) -> Path:
        return self.folder / "passwd"

    @property
    def acl(self) -> Path:
        return self.folder / "acl"

    @property
    def pid_file(self) -> Path:
        return self.folder / "mosquitto.pid"

    @property
    def ca_cert(self) -> Path:
        return self.folder / "ca.crt"

    @property
    def room_secret(self) -> Path:
        return self.folder / "room.secret"

    # -- writing ------------------------------------------------------------------------------
    def write(self) -> None:
        """Create what is missing (CA, certificate, the room's password) and (re)write the config
        and ACL. Idempotent: a second call keeps the CA, the certificate (unless `names` grew) and
        every password."""
        self.folder.mkdir(parents=True, exist_ok=True)
        os.chmod(self.folder, 0o700)
        if not self.passwd.exists():
            private_write(self.passwd, "")
        if not self.room_secret.exists():
            secret = secrets.token_urlsafe(24)
            self.set_password(ROOM_USER, secret)
            private_write(self.room_secret, secret + "\n")
        if self.tls_port is not None:
            self._make_tls()
        private_write(self.acl, acl_text())
        private_write(self.conf, self.config_text())

    def config_text(self) -> str:
        lines = [
            "# Written by xrflab.room.broker; edits are overwritten.",
            "per_listener_settings false",
            "allow_anonymous false",
            f"password_file {self.passwd}",
            f"acl_file {self.acl}",
            f"pid_file {self.pid_file}",
            # Started as root, mosquitto would switch to the `mosquitto` user and lose the private
            # files above: it stays the user who owns them.
            f"user {pwd.getpwuid(os.getuid()).pw_name}",
            # Retained states live in the benches, which publish them again on every connect; a
            # restarted broker needs no disk of its own.
            "persistence false",
            "log_dest stderr",
            "log_type error",
            "log_type warning",
            # A bench's queued events are resent after an outage; the broker need not hold more for
            # a client than this.
            "max_queued_messages 1000",
            # A client that sends a larger packet is disconnected (the room's class list is the
            # largest message; a bench's are far smaller and each receiver bounds them again:
            # payloads.py).
            f"max_packet_size {payloads.BROKER_MAX_PACKET}",
        ]
        if self.port is not None:
            lines += ["", f"listener {self.port} {self.bind}", "protocol mqtt"]
        if self.tls_port is not None:
            lines += [
                "",
                f"listener {self.tls_port} {self.bind}",
                "protocol mqtt",
                f"cafile {self.ca_cert}",
                f"certfile {self.folder / 'server.crt'}",
                f"keyfile {self.folder / 'server.key'}",
                "tls_version tlsv1.2",
            ]
        return "\n".join(lines) + "\n"

    def _make_tls(self) -> None:
        openssl = tool("openssl")
        key, crt = self.folder / "ca.key", self.ca_cert
        if not crt.exists():
            subprocess.run(
                [
                    openssl,
                    "req",
                    "-x509",
                    "-newkey",
                    "ec",
                    "-pkeyopt",
                    "ec_paramgen_curve:prime256v1",
                    "-nodes",
                    "-keyout",
                    str(key),
                    "-out",
                    str(crt),
                    "-days",
                    "3650",
                    "-subj",
                    "/CN=XRF Lab room CA",
                    "-addext",
                    "basicConstraints=critical,CA:TRUE",
                    "-addext",
                    "keyUsage=critical,keyCertSign,cRLSign",
                ],
                check=True,
                capture_output=True,
            )
            os.chmod(key, 0o600)
        names_file = self.folder / "server.names"
        wanted = "\n".join(sorted(set(self.names)))
        server_crt = self.folder / "server.crt"
        if server_crt.exists() and names_file.exists() and names_file.read_text() == wanted:
            return
        san = ",".join(("IP:" if _is_ip(n) else "DNS:") + n for n in sorted(set(self.names)))
        skey, csr = self.folder / "server.key", self.folder / "server.csr"
        subprocess.run(
            [
                openssl,
                "req",
                "-newkey",
                "ec",
                "-pkeyopt",
                "ec_paramgen_curve:prime256v1",
                "-nodes",
                "-keyout",
                str(skey),
                "-out",
                str(csr),
                "-subj",
                "/CN=xrf-room-broker",
            ],
            check=True,
            capture_output=True,
        )
        ext = self.folder / "server.ext"
        ext.write_text(
            f"subjectAltName={san}\nbasicConstraints=CA:FALSE\nkeyUsage=digitalSignature,keyEncipherment\n"
            "extendedKeyUsage=serverAuth\n"
        )
        subprocess.run(
            [
                openssl,
                "x509",
                "-req",
                "-in",
                str(csr),
                "-CA",
                str(crt),
                "-CAkey",
                str(key),
                "-CAcreateserial",
                "-out",
                str(server_crt),
                "-days",
                "825",
                "-extfile",
                str(ext),
            ],
            check=True,
            capture_output=True,
        )
        os.chmod(skey, 0o600)
        csr.unlink(missing_ok=True)
        names_file.write_text(wanted)

    # -- credentials --------------------------------------------------------------------------
    def set_password(self, username: str, password: str) -> None:
        """Add or change a user in the password file (mosquitto_passwd hashes it)."""
        topics.check_bench_name(username) if username != ROOM_USER else None
        subprocess.run(
            [tool("mosquitto_passwd"), "-b", str(self.passwd), username, password], check=True, capture_output=True
        )
        os.chmod(self.passwd, 0o600)

    def delete_user(self, username: str) -> None:
        subprocess.run([tool("mosquitto_passwd"), "-D", str(self.passwd), username], check=False, capture_output=True)

    def users(self) -> list[str]:
        return [line.split(":", 1)[0] for line in self.passwd.read_text().splitlines() if ":" in line]

    def room_password(self) -> str:
        return self.room_secret.read_text().strip()

    def reload(self) -> bool:
        """Make a running mosquitto re-read the password and ACL files (SIGHUP); False when none runs."""
        try:
            pid = int(self.pid_file.read_text().strip())
            os.kill(pid, signal.SIGHUP)
            return True
        except (OSError, ValueError):
            return False


def _is_ip(name: str) -> bool:
    try:
        ipaddress.ip_address(name)
        return True
    except ValueError:
        return False


class BrokerProcess:
    """A mosquitto started with the folder's configuration (by `xrf room`, the tests and the
    benchmark). It dies with its starter (tied.popen_tied): no broker outlives the room."""

    def __init__(self, files: BrokerFiles, log: Path | None = None) -> None:
        self.files = files
        self.log = log or files.folder / "mosquitto.log"
        self.proc: subprocess.Popen[bytes] | None = None

    def start(self, timeout: float = 10.0) -> None:
        from ..tied import popen_tied

        self.files.pid_file.unlink(missing_ok=True)
        with open(self.log, "ab") as out:
            self.proc = popen_tied(
                [tool("mosquitto"), "-c", str(self.files.conf)],
                stdin=subprocess.DEVNULL,
                stdout=out,
                stderr=out,
                close_fds=True,
            )
        port = self.files.port if self.files.port is not None else self.files.tls_port
        assert port is not None, "BrokerFiles listens on a plain or a TLS port"
        host = "127.0.0.1" if self.files.bind in ("0.0.0.0", "") else self.files.bind
        deadline = time.monotonic() + timeout
        import socket

        while True:
            if self.proc.poll() is not None:
                raise BrokerError(f"mosquitto exited with {self.proc.returncode}; see {self.log}")
            try:
                with socket.create_connection((host, port), timeout=0.5):
                    return
            except OSError:
                if time.monotonic() > deadline:
                    self.stop()
                    raise BrokerError(f"mosquitto did not listen on {host}:{port} within {timeout} s") from None
                time.sleep(0.02)

    @property
    def pid(self) -> int | None:
        return self.proc.pid if self.proc and self.proc.poll() is None else None

    def kill(self) -> None:
        """A broker crash (SIGKILL): what the failure tests need."""
        if self.proc and self.proc.poll() is None:
            self.proc.kill()
            self.proc.wait()

    def stop(self) -> None:
        if self.proc and self.proc.poll() is None:
            self.proc.terminate()
            try:
                self.proc.wait(timeout=5)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait()
