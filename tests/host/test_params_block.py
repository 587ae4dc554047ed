"""The parameter block of a segment (rt_core's xrf/params.h) through the one cffi binding: the
loop's side and the host's side of a set, and a table a hostile guest wrote (issue 28).

The block lives in memory a guest writes: the host's reader must refuse a table whose count,
names or numbers break the rules, and a set must land whole or not at all.
"""

from __future__ import annotations

import errno
import math

import pytest

from xrflab.channels import ChannelsCorrupt, ffi, lib
from xrflab.channels import params as chparams


def _shm_with_table(n: int = 3) -> object:
    shm = ffi.new("struct xrf_shm *")
    p = shm.params
    p.count = n
    for i in range(n):
        p.desc[i].name = f"PID_Left\\K{i}".encode()
        p.desc[i].unit = b"-/rad"
        p.desc[i].initial = 1.0
        p.desc[i].min = 0.0
        p.desc[i].max = 10.0
        p.desc[i].source = lib.XRF_PARAM_SOURCE_20SIM
        p.value[i] = 1.0
    return shm


def test_round_trip_is_whole_and_answered_with_the_cycle() -> None:
    shm = _shm_with_table()
    table = chparams.read_table(shm, "t")
    assert [d.name for d in table.params] == ["PID_Left\\K0", "PID_Left\\K1", "PID_Left\\K2"]
    seq = chparams.send_set(shm, [(0, 2.5), (2, 7.0)])
    assert chparams.answered(shm, seq) is None  # the loop has not taken it yet
    seen = ffi.new("uint32_t *")
    got = ffi.new("struct xrf_param_set *")
    assert lib.xrf_params_take(ffi.addressof(shm, "params"), seen, got) == 1
    assert (got.count, got.index[0], got.value[0], got.index[1], got.value[1]) == (2, 0, 2.5, 2, 7.0)
    assert lib.xrf_params_set_check(got, 3) == 0
    assert lib.xrf_params_take(ffi.addressof(shm, "params"), seen, got) == 0  # taken once
    lib.xrf_params_answer(ffi.addressof(shm, "params"), got.seq, 0, 4242)
    a = chparams.answered(shm, seq)
    assert a is not None and a.applied and a.cycle == 4242


def test_the_loop_refuses_a_set_it_cannot_apply_whole() -> None:
    shm = _shm_with_table()
    seen = ffi.new("uint32_t *")
    got = ffi.new("struct xrf_param_set *")
    chparams.send_set(shm, [(0, 1.0), (3, 1.0)])  # index 3: the table has 3
    assert lib.xrf_params_take(ffi.addressof(shm, "params"), seen, got) == 1
    assert lib.xrf_params_set_check(got, 3) == -errno.EINVAL
    # A count the host never wrote (the guest scribbled it) is refused, not read beyond the set.
    shm.params.req_count = 1_000_000
    shm.params.req_seq += 2
    assert lib.xrf_params_take(ffi.addressof(shm, "params"), seen, got) == 1
    assert lib.xrf_params_set_check(got, 3) == -errno.EINVAL
    # A set the host is still writing (odd seq) is left for the next cycle.
    shm.params.req_seq += 1
    assert lib.xrf_params_take(ffi.addressof(shm, "params"), seen, got) == 0


def test_host_refuses_non_finite_values_and_a_held_block() -> None:
    shm = _shm_with_table()
    for bad in (math.nan, math.inf, -math.inf):
        with pytest.raises(ValueError):
            chparams.send_set(shm, [(0, bad)])
    with pytest.raises(ValueError):
        chparams.send_set(shm, [])
    shm.params.req_seq = 7  # a writer (or the guest) holds it and never finishes
    with pytest.raises(BlockingIOError):
        chparams.send_set(shm, [(0, 1.0)])


@pytest.mark.parametrize(
    "scribble",
    [
        lambda p: setattr(p, "count", lib.XRF_PARAMS_MAX + 1),
        lambda p: setattr(p, "origin", 99),
        lambda p: ffi.memmove(p.desc[1].name, b"x" * lib.XRF_PARAM_NAME_MAX, lib.XRF_PARAM_NAME_MAX),  # no NUL
        lambda p: ffi.memmove(p.desc[1].name, b'a"b\0', 4),  # a quote
        lambda p: ffi.memmove(p.desc[1].name, b"a\nb\0", 4),  # a control character
        lambda p: ffi.memmove(p.desc[1].name, b"\0", 1),  # empty
        lambda p: ffi.memmove(p.desc[1].name, b"PID_Left\\K0\0", 12),  # a duplicate
        lambda p: ffi.memmove(p.desc[1].unit, b"u" * lib.XRF_PARAM_UNIT_MAX, lib.XRF_PARAM_UNIT_MAX),
        lambda p: setattr(p.desc[1], "initial", math.nan),
        lambda p: setattr(p.desc[1], "max", math.inf),
        lambda p: setattr(p.desc[1], "initial", 11.0),  # above max
        lambda p: setattr(p.desc[1], "source", 0),
    ],
)
def test_a_hostile_table_is_refused(scribble) -> None:  # noqa: ANN001
    shm = _shm_with_table()
    scribble(shm.params)
    with pytest.raises(ChannelsCorrupt):
        chparams.read_table(shm, "t")


def test_values_read_back_are_bounded_by_our_table() -> None:
    shm = _shm_with_table()
    table = chparams.read_table(shm, "t")
    shm.params.value[1] = math.nan
    shm.params.count = 64  # changed after we took the table: our copy's count holds
    assert chparams.read_values(shm, table) == [1.0, 1.0, 1.0]
