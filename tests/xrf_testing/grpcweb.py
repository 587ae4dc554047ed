"""A minimal gRPC-web reader for tests of the live rerun stream: the framing of the gRPC-web
protocol (github.com/grpc/grpc/blob/master/doc/PROTOCOL-WEB.md): each message is one flag byte
(0x00 data, 0x80 trailers), a 4-byte big-endian length and the payload. Payloads stay opaque
protobuf bytes; tests look for what they must contain (a recording id, an entity path)."""

from __future__ import annotations

import struct
import time
from collections.abc import Callable
from dataclasses import dataclass, field

import httpx

READ_MESSAGES = "/rerun.sdk_comms.v1alpha1.MessageProxyService/ReadMessages"
EMPTY_REQUEST = b"\x00\x00\x00\x00\x00"  # one data frame holding an empty ReadMessagesRequest
GRPC_WEB = {"content-type": "application/grpc-web+proto", "x-grpc-web": "1"}


@dataclass
class Stream:
    status: int
    headers: dict[str, str]
    messages: list[bytes] = field(default_factory=list)
    trailers: bytes = b""
    ended_by: str = ""  # "server" (it closed the stream), "until", "timeout" or "quiet"

    @property
    def data(self) -> bytes:
        return b"".join(self.messages)


def split_frames(buf: bytes) -> tuple[list[tuple[int, bytes]], bytes]:
    """Complete frames in `buf` and the incomplete rest."""
    frames, pos = [], 0
    while len(buf) - pos >= 5:
        flag, length = buf[pos], struct.unpack(">I", buf[pos + 1 : pos + 5])[0]
        if flag not in (0x00, 0x80):
            raise ValueError(f"not a gRPC-web frame: flag {flag:#x} at byte {pos}")
        if len(buf) - pos - 5 < length:
            break
        frames.append((flag, buf[pos + 5 : pos + 5 + length]))
        pos += 5 + length
    return frames, buf[pos:]


def read_messages(
    client: httpx.Client,
    url: str,
    until: Callable[[bytes], bool] = lambda data: False,
    timeout: float = 20.0,
    headers: dict[str, str] | None = None,
    body: bytes = EMPTY_REQUEST,
    quiet: float = 5.0,
    on_message: Callable[[bytes], None] | None = None,
) -> Stream:
    """POST a ReadMessages call and read the stream until `until(all payload bytes so far)` is
    true, the server ends it, `timeout` passes or the stream is quiet for `quiet` s (then
    whatever arrived is returned; `ended_by` says which). `on_message(payload)`: each data
    message as it arrives."""
    deadline = time.monotonic() + timeout
    with client.stream(
        "POST",
        url,
        content=body,
        headers={**GRPC_WEB, **(headers or {})},
        timeout=httpx.Timeout(10.0, read=min(timeout, quiet)),
    ) as r:
        out = Stream(r.status_code, {k.lower(): v for k, v in r.headers.items()})
        if r.status_code != 200:
            r.read()
            return out
        rest = b""
        chunks = r.iter_raw()
        out.ended_by = "timeout"
        while time.monotonic() < deadline:
            try:
                chunk = next(chunks)
            except (StopIteration, httpx.RemoteProtocolError):
                out.ended_by = "server"
                break
            except httpx.ReadTimeout:
                out.ended_by = "quiet"
                break
            frames, rest = split_frames(rest + chunk)
            for flag, payload in frames:
                if flag == 0x80:
                    out.trailers = payload
                else:
                    out.messages.append(payload)
                    if on_message is not None:
                        on_message(payload)
            if out.trailers:
                out.ended_by = "server"
                break
            if until(out.data):
                out.ended_by = "until"
                break
        return out


def watch_live(client: httpx.Client) -> Stream:
    """A viewer reading the current run's live stream for a moment (its first message, or a few
    quiet seconds): the run's proxy process starts at its first viewer (LiveProxy.ensure_running)
    and, while the run goes on, stays after the viewer left. For tests that need the run's
    helpers running as a watched run has them."""
    # quiet 12 s: the read route answers once the recording has sent again (up to 10 s,
    # server/http/rerun.py _live_edge), and rerun's import in the appliance comes first.
    return read_messages(client, READ_MESSAGES, until=lambda data: len(data) > 0, timeout=20, quiet=12)
