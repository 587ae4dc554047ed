"""Several ico boards over real spidev (issue 29): one SPI device per board, configured as a list
(Settings.spi_devices, $XRF_SPI_DEVICES), opened by rt_core's own spidev transport
(xrf_spi_probe: the code the loop and the safety watcher open them with). Without the hardware
here: what a bench whose profile needs more boards than devices are configured gets at run start
(refused, naming the missing board's device), and the error a device gets that is no SPI device
(a regular file, a folder, a missing path, a character device that is not SPI)."""

from __future__ import annotations

import asyncio
import errno
import json
from pathlib import Path

import pytest

from xrflab.channels import ffi, lib
from xrflab.server.runs import watch as run_watch
from xrflab.server.settings import Settings

REPO = Path(__file__).resolve().parents[2]


@pytest.fixture
def youbot_bench(monkeypatch: pytest.MonkeyPatch) -> None:
    """A real bench (forced: no /dev/evl here) whose profile is the youBot's: 9 channels, 3 boards."""
    monkeypatch.setenv("XRF_BENCH_PROFILE", "youbot")


def test_the_device_list_comes_from_the_environment(monkeypatch: pytest.MonkeyPatch, tmp_path: Path) -> None:
    monkeypatch.delenv("XRF_SPI_DEVICES", raising=False)
    assert Settings(data_dir=tmp_path).spi_bench() == ("/dev/spidev0.0",)
    monkeypatch.setenv("XRF_SPI_DEVICES", "/dev/spidev0.0, /dev/spidev0.1,/dev/spidev1.0")
    s = Settings(data_dir=tmp_path)
    assert s.spi_bench() == ("/dev/spidev0.0", "/dev/spidev0.1", "/dev/spidev1.0")
    # Board 1's device is the one every single-board path (self-check, doctor's probe) uses.
    assert Settings(data_dir=tmp_path, spi_devices=("/dev/spidev1.1", "/dev/spidev1.2")).spi_device == "/dev/spidev1.1"


def test_a_nine_channel_bench_with_one_device_is_refused_naming_the_missing_one(
    youbot_bench: None, tmp_path: Path
) -> None:
    s = Settings(data_dir=tmp_path, real_bench=True, spi_devices=("/dev/null",))
    why = run_watch.bench_refusal(s)
    assert "'youbot' has 9 channels on 3 ico boards" in why
    assert "board 2's device is missing" in why and "XRF_SPI_DEVICES" in why


def test_each_board_device_is_opened_as_an_spi_device(youbot_bench: None, tmp_path: Path) -> None:
    regular = tmp_path / "spidev0.1"
    regular.write_text("")
    folder = tmp_path / "spidev1.0"
    folder.mkdir()

    def refusal(*devices: str) -> str:
        return run_watch.bench_refusal(Settings(data_dir=tmp_path, real_bench=True, spi_devices=devices))

    # /dev/null is a character device, but its ioctl says it is no SPI device.
    why = refusal("/dev/null", str(regular), str(folder))
    assert (
        why
        == "board 1's SPI device /dev/null is not an SPI device (a regular file or another kind of device) (errno 25)"
    )
    assert refusal(str(tmp_path / "none"), "/dev/null", "/dev/null") == (
        f"board 1's SPI device {tmp_path / 'none'} does not exist (errno 2)"
    )
    # The same open as the transports: the failing board is named, not the first.
    failed = ffi.new("int32_t *")
    assert lib.xrf_spi_probe(f"{folder}".encode(), 1_000_000, failed) == -errno.EISDIR and failed[0] == 0
    assert lib.xrf_spi_probe(str(regular).encode(), 1_000_000, failed) == -errno.ENOTTY and failed[0] == 0
    assert run_watch.spi_problem((str(folder),)) == (
        f"board 1's SPI device {folder} is a folder, not an SPI device (errno {errno.EISDIR})"
    )


def test_a_simulated_bench_or_one_board_profile_needs_no_list(youbot_bench: None, tmp_path: Path, monkeypatch) -> None:
    assert run_watch.bench_refusal(Settings(data_dir=tmp_path, real_bench=False)) == ""
    monkeypatch.setenv("XRF_BENCH_PROFILE", "relbot")  # 2 channels: one board, /dev/null's error is the device's
    why = run_watch.bench_refusal(Settings(data_dir=tmp_path, real_bench=True, spi_devices=("/dev/null",)))
    assert why.startswith("board 1's SPI device /dev/null is not an SPI device")


def test_hold_or_several_boards_on_the_out_of_band_transport_are_refused(
    youbot_bench: None, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """EVL's out-of-band SPI gives the loop the bus (the watcher's in-band samples of the arm's
    counts would block behind it) and drives one board: a `hold` bench is refused with the
    transport that can hold it named, not run with `zero` (which drops the arm)."""
    devices = ("/dev/null", "/dev/null", "/dev/null")
    monkeypatch.setenv("XRF_TRANSPORT", "evl-spidev")
    why = run_watch.bench_refusal(Settings(data_dir=tmp_path, real_bench=True, spi_devices=devices))
    assert "needs the safe reaction 'hold'" in why and "Use XRF_TRANSPORT=spidev" in why
    monkeypatch.setenv("XRF_TRANSPORT", "spidev")  # in band: the devices' own check speaks
    why = run_watch.bench_refusal(Settings(data_dir=tmp_path, real_bench=True, spi_devices=devices))
    assert why.startswith("board 1's SPI device /dev/null is not an SPI device")
    # A bench of several boards without hold (a profile of 9 zero-reaction channels): one board only.
    profile = json.loads((REPO / "deploy/profiles/youbot.json").read_text())
    profile["name"] = "wide"
    del profile["safety"]
    (tmp_path / "profiles").mkdir()
    (tmp_path / "profiles/wide.json").write_text(json.dumps(profile))
    monkeypatch.setenv("XRF_BENCH_PROFILE", "wide")
    monkeypatch.setenv("XRF_TRANSPORT", "evl-spidev")
    why = run_watch.bench_refusal(Settings(data_dir=tmp_path, real_bench=True, spi_devices=devices))
    assert "9 channels on 3 ico boards, and XRF_TRANSPORT=evl-spidev drives one board" in why, why


def test_a_run_on_that_bench_is_refused_at_start(youbot_bench: None, tmp_path: Path) -> None:
    """The supervisor's start_run says why (409), before anything is built or recorded."""
    from xrflab.server.runs.errors import SupervisorError
    from xrflab.server.runs.store import RunStore
    from xrflab.server.runs.supervisor import Supervisor
    from xrflab.server.ws.hub import Hub

    settings = Settings(data_dir=tmp_path, real_bench=True, spi_devices=("/dev/null",))
    store = RunStore(settings.runs_db)

    async def start() -> None:
        supervisor = Supervisor(settings, Hub(), store)
        with pytest.raises(SupervisorError, match="board 2's device is missing") as refused:
            await supervisor.start_run("youbot")
        assert refused.value.status == 409

    try:
        asyncio.run(start())
        assert store.list() == []  # no run was recorded
    finally:
        store.close()
