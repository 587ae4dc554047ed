"""The table of edge values for all six log types, shared by the reader and converter tests
(tests/logs)."""

from __future__ import annotations

import numpy as np

F32_DENORMAL_MIN = np.float32(1e-45).item()
F32_DENORMAL_MAX = np.frombuffer(bytes.fromhex("ffff7f00"), "<f4")[0].item()
NAN_PAYLOAD = np.frombuffer(bytes.fromhex("0100000000fff87f"), "<f8")[0].item()  # quiet NaN, payload 1

VARIABLES = [
    ("flag", 1),
    ("letter", 2),
    ("count", 3),
    ("ratio", 4),
    ("value", 5),
    ("big", 6),
    ("pos_left", 5),
    ("pos_right", 5),
    ("cycle", 6),
    ("2 bad-name", 3),
]

_EDGE = [
    (True, b"\x00", -(2**31), float("nan"), float("nan"), -(2**63)),
    (False, b"\xff", 2**31 - 1, float("inf"), float("inf"), 2**63 - 1),
    (True, b"a", 0, float("-inf"), float("-inf"), 0),
    (False, b",", -1, F32_DENORMAL_MIN, 5e-324, -1),
    (True, b"\n", 1, F32_DENORMAL_MAX, -0.0, 2**53 + 1),
    (False, b'"', 7, -0.0, 1.7976931348623157e308, -(2**53) - 1),
    (True, b"\x7f", 123456, 3.4028234663852886e38, 0.1, 123),
    (False, b"\x80", -123456, 0.1, NAN_PAYLOAD, -123),
]


def edge_rows(n: int = 64) -> list[tuple]:
    rows = []
    for i in range(n):
        base = (
            _EDGE[i % len(_EDGE)]
            if i < 3 * len(_EDGE)
            else (bool(i & 1), bytes([i % 256]), i * 1000 - 7, i / 3.0, i / 7.0, i * 10**12)
        )
        rows.append(base + (i * 0.001, -i * 0.001, i + 10, -i))
    return rows


def columns_of(rows: list[tuple]) -> dict[str, np.ndarray]:
    """The expected column values, packed by NumPy from the Python values."""
    cols = list(zip(*rows))
    out = {
        "flag": np.array(cols[0], dtype="?"),
        "letter": np.frombuffer(b"".join(cols[1]), np.uint8),
        "count": np.array(cols[2], "<i4"),
        "ratio": np.array(cols[3], "<f4"),
        "value": np.array(cols[4], "<f8"),
        "big": np.array(cols[5], "<i8"),
        "pos_left": np.array(cols[6], "<f8"),
        "pos_right": np.array(cols[7], "<f8"),
        "cycle_2": np.array(cols[8], "<i8"),
        "2 bad-name": np.array(cols[9], "<i4"),
    }
    return out


def same_bits(a: np.ndarray, b: np.ndarray) -> bool:
    a, b = np.ascontiguousarray(a), np.ascontiguousarray(b)
    return a.shape == b.shape and a.dtype.itemsize == b.dtype.itemsize and a.tobytes() == b.tobytes()
