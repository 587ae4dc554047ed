"""The bench self-check from Python: runs the native checker ``xrf-selfcheck`` (rt_core's tool of
its own, the same IcoIo code as the loop, not part of the runtime library) as a subprocess, hands
it the profile validated here (``xrflab.profiles``) in its flat form on stdin
(``xrflab.profile_flat``), streams its events, builds a ``Report``, keeps reports and exports
them. Also ``xrf selfcheck`` (registered in xrflab.cli's EXTERNAL_SUBCOMMANDS).

    check = SelfCheck("relbot", sim="relbot", faults="dead_encoder=2")
    for event in check.events():      # dicts as the checker prints them, see EVENT KINDS below
        ...                           # another thread may call check.abort()
    report = check.report             # or: report = check.run(on_event=print)
    path = save_report(report)        # <data>/selfcheck/<timestamp>-<bench>.json

Event kinds (one JSON object per line from the checker): ``start`` (profile, transport, sim,
faults, device, pid), ``progress`` (step, channel, fraction, text), ``step`` (id, channel,
status pass|warn|fail|skipped, title, message, action, data), ``end`` (verdict, counts,
aborted, outputs_zeroed), ``error`` (message: could not run).

The check refuses to start while a loop runs on the bench (``BenchBusy``): by default it looks at
the loop's shared memory (``shm``, default ``xrf``): a loop whose status says running and whose
pid is alive; a caller may pass its own ``bench_busy`` callable instead.

Heavy imports (the cffi channels binding, the build) stay inside functions: ``xrf`` imports this
module to build its parser.
"""

from __future__ import annotations

import argparse
import datetime as _dt
import json
import os
import signal
import socket
import subprocess
import sys
import threading
import time
from collections.abc import Callable, Iterator
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

from . import plants
from .channels import names as _names
from .errors import Invalid
from .profile_flat import flat_form
from .profiles import ProfileError, default_data_dir, find_profile, load_profile, validate_profile
from .server.settings import Settings

EXIT_PASS = 0
EXIT_FAIL = 1
EXIT_COULD_NOT_RUN = 2

MARKS = {"pass": "✓", "warn": "!", "fail": "✗", "skipped": "–"}
# "auto" (spidev when the device exists, else sim) and rt_core's transports (channels.h).
TRANSPORTS = ("auto", *_names.TRANSPORTS)
DEFAULT_SPI_DEVICE = Settings.spi_device

BenchBusyCheck = Callable[[], bool | str | None]


class SelfCheckError(Invalid, RuntimeError):
    """The check could not be started (checker missing, bad profile, bad arguments): an XrfError
    (422), answered by server/http/errors.py."""


class BenchBusy(SelfCheckError):
    """A loop is running on the bench: stop it first (409, not now)."""

    status = 409


@dataclass
class Step:
    id: str
    channel: int
    status: str
    title: str
    message: str
    action: str = ""
    data: dict[str, Any] = field(default_factory=dict)

    @property
    def mark(self) -> str:
        return MARKS.get(self.status, "?")


@dataclass
class Report:
    verdict: str  # pass | fail | aborted | error
    bench: str  # profile name
    steps: list[Step] = field(default_factory=list)
    profile: dict[str, Any] = field(default_factory=dict)  # the profile as used
    profile_file: str = ""
    transport: str = ""
    sim: str = ""
    faults: str = ""
    device: str = ""
    host: str = ""
    started: str = ""  # ISO 8601, local time with offset
    finished: str = ""
    duration_s: float = 0.0
    outputs_zeroed: bool = False
    error: str = ""  # why it could not run (verdict error)

    @property
    def exit_code(self) -> int:
        if self.verdict == "pass":
            return EXIT_PASS
        if self.verdict == "fail":
            return EXIT_FAIL
        return EXIT_COULD_NOT_RUN

    def step(self, step_id: str) -> Step | None:
        return next((s for s in self.steps if s.id == step_id), None)

    def failed(self) -> list[Step]:
        return [s for s in self.steps if s.status == "fail"]

    def counts(self) -> dict[str, int]:
        out = {k: 0 for k in MARKS}
        for s in self.steps:
            out[s.status] = out.get(s.status, 0) + 1
        return out

    def as_dict(self) -> dict[str, Any]:
        d = asdict(self)
        d["exit_code"] = self.exit_code
        d["counts"] = self.counts()
        return d

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> Report:
        d = dict(d)
        d.pop("exit_code", None)
        d.pop("counts", None)
        steps = [Step(**s) for s in d.pop("steps", [])]
        known = set(cls.__dataclass_fields__)
        return cls(steps=steps, **{k: v for k, v in d.items() if k in known})

    def to_json(self) -> str:
        return json.dumps(self.as_dict(), indent=2, ensure_ascii=False)

    def to_text(self) -> str:
        """Plain text for a terminal: one line per step with ✓/✗/–/!, the diagnosis and what to do."""
        lines = [
            f"Self-check of the {self.bench} bench: {self.verdict.upper()}",
            f"  {self.started}  host {self.host}  transport {self.transport}"
            + (f" ({self.sim}{', faults ' + self.faults if self.faults else ''})" if self.sim else ""),
        ]
        if self.error:
            lines.append(f"  could not run: {self.error}")
        for s in self.steps:
            lines.append(f"{s.mark} {s.id:<8} {s.title}")
            if s.status != "pass" or s.message:
                lines.append(f"    {s.message}")
            if s.action and s.status in ("fail", "warn"):
                lines.append(f"    → {s.action}")
        c = self.counts()
        lines.append(
            f"{c['pass']} passed, {c['warn']} warnings, {c['fail']} failed, {c['skipped']} skipped; "
            f"outputs {'zeroed' if self.outputs_zeroed else 'NOT confirmed zero'}"
        )
        return "\n".join(lines)

    def to_markdown(self) -> str:
        def cell(t: str) -> str:
            return t.replace("|", "\\|").replace("\n", " ")

        out = [
            f"# Self-check: {self.bench} bench — {self.verdict.upper()}",
            "",
            f"- date: {self.started}",
            f"- host: {self.host}",
            f"- transport: {self.transport}" + (f" (simulated {self.sim})" if self.sim else ""),
            f"- outputs zeroed at the end: {'yes' if self.outputs_zeroed else 'NOT CONFIRMED'}",
        ]
        if self.faults:
            out.append(f"- injected faults: `{self.faults}`")
        if self.error:
            out.append(f"- could not run: {self.error}")
        out += ["", "| | step | result | what to do |", "|---|---|---|---|"]
        for s in self.steps:
            out.append(f"| {s.mark} | {cell(s.title)} (`{s.id}`) | {cell(s.message)} | {cell(s.action)} |")
        return "\n".join(out) + "\n"


def export_report(report: Report, fmt: str = "json") -> str:
    """Report as text in 'json', 'text' or 'markdown'."""
    if fmt == "json":
        return report.to_json()
    if fmt in ("text", "txt"):
        return report.to_text() + "\n"
    if fmt in ("markdown", "md"):
        return report.to_markdown()
    raise ValueError(f"unknown export format {fmt!r} (json, text, markdown)")


# ---- reports folder -----------------------------------------------------------------------------


def reports_dir(data_dir: Path | None = None) -> Path:
    return Path(data_dir or default_data_dir()) / "selfcheck"


def save_report(report: Report, folder: Path | None = None, data_dir: Path | None = None) -> Path:
    """Write the report as <folder>/<timestamp>-<bench>.json (folder default <data>/selfcheck)."""
    folder = Path(folder) if folder else reports_dir(data_dir)
    folder.mkdir(parents=True, exist_ok=True)
    try:
        stamp = _dt.datetime.fromisoformat(report.started).strftime("%Y%m%d-%H%M%S")
    except ValueError:
        stamp = time.strftime("%Y%m%d-%H%M%S")
    base = f"{stamp}-{report.bench or 'bench'}"
    path = folder / f"{base}.json"
    n = 1
    while path.exists():
        n += 1
        path = folder / f"{base}-{n}.json"
    tmp = path.with_suffix(".json.tmp")
    tmp.write_text(report.to_json() + "\n", encoding="utf-8")
    os.replace(tmp, path)
    return path


def list_reports(folder: Path | None = None, data_dir: Path | None = None) -> list[Path]:
    """Saved reports, newest first."""
    folder = Path(folder) if folder else reports_dir(data_dir)
    if not folder.is_dir():
        return []
    return sorted(folder.glob("*.json"), reverse=True)


def load_report(path: Path | str) -> Report:
    return Report.from_dict(json.loads(Path(path).read_text(encoding="utf-8")))


# ---- is the bench busy? -------------------------------------------------------------------------


def loop_active(shm: str = "xrf") -> str | None:
    """A sentence naming the loop that runs on shared memory `shm`, or None when none does (no
    object, not ready, running == 0, or its pid is gone)."""
    from .channels import Channels, ChannelsError, shm_path

    try:
        if not shm_path(shm).exists():
            return None
        ch = Channels.open(shm, wait_s=0.0)
    except (ChannelsError, ValueError, OSError):
        return None
    try:
        status = ch.status()
        pid = int(ch.info.get("pid", 0))
        program = ch.info.get("program", "") or "a controller"
    except ChannelsError:
        return None
    finally:
        ch.close()
    if not status.running or pid <= 0:
        return None
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return None
    except PermissionError:
        pass  # alive, owned by someone else
    return f"a loop ({program}, pid {pid}, state {status.state_name}) is running on the bench: stop it first"


# ---- running ------------------------------------------------------------------------------------


def checker_path(log: Callable[[str], None] = lambda line: None) -> Path:
    """Build rt_core if needed and return <prefix>/bin/xrf-selfcheck."""
    from .build import BuildError, ensure_rt_core

    try:
        prefix = ensure_rt_core(log=log)
    except BuildError as exc:
        raise SelfCheckError(f"cannot build rt_core for the self-check: {exc}") from None
    exe = Path(prefix) / "bin" / "xrf-selfcheck"
    if not exe.exists():
        raise SelfCheckError(f"{exe}: not found after building rt_core")
    return exe


def _now_iso() -> str:
    return _dt.datetime.now().astimezone().isoformat(timespec="seconds")


class SelfCheck:
    """One run of the self-check. Not reusable: make a new one per run.

    profile: a name (edited copy in <data>/profiles first, then deploy/profiles), a path, or a
    profile dict; validated here, handed to the checker in its flat form on stdin.
    transport: sim | spidev | evl-spidev | auto (spidev when `device` exists, else sim).
    bench_busy: callable returning a reason (str or True) when the bench is in use; default:
    ``loop_active(shm)``. Pass ``shm=None`` and no callable to skip the test.
    sim_outputs_shm: a shared-memory object (made by the tests' xrf_testing.testloop.create_for_test) into which
    the simulated board mirrors its outputs (tests).
    """

    def __init__(
        self,
        profile: str | Path | dict[str, Any] = Settings.sim,
        *,
        transport: str = "sim",
        sim: str | None = None,
        faults: str | None = None,
        device: str | None = None,
        speed_hz: int | None = None,
        data_dir: Path | None = None,
        bench_busy: BenchBusyCheck | None = None,
        shm: str | None = "xrf",
        sim_outputs_shm: str | None = None,
        exe: Path | None = None,
        abort_timeout_s: float = 3.0,
    ) -> None:
        if transport not in TRANSPORTS:
            raise SelfCheckError(f"unknown transport {transport!r} (use {', '.join(TRANSPORTS)})")
        try:
            if isinstance(profile, dict):
                self.profile = validate_profile(profile)
                self.profile_path: Path | None = None  # no file: the dict is the profile
            else:
                self.profile_path = find_profile(profile, data_dir)
                self.profile = load_profile(self.profile_path)
        except ProfileError:
            raise
        except (OSError, json.JSONDecodeError) as exc:
            raise ProfileError([str(exc)], str(profile)) from None
        dev = device or DEFAULT_SPI_DEVICE
        if transport == "auto":
            transport = "spidev" if Path(dev).exists() else "sim"
        self.transport = transport
        robot = self.profile.get("robot", "")
        self.sim = (sim or (robot if robot in plants.names() else Settings.sim)) if transport == "sim" else ""
        self.faults = faults or ""
        self.device = dev if transport != "sim" else ""
        self.speed_hz = speed_hz or (self.profile.get("link", {}).get("spi_speed_hz") if transport != "sim" else None)
        self.bench_busy = bench_busy
        self.shm = shm
        self.sim_outputs_shm = sim_outputs_shm
        self.exe = Path(exe) if exe else None
        self.abort_timeout_s = abort_timeout_s
        self.report: Report | None = None
        self._proc: subprocess.Popen | None = None
        self._abort_requested = False
        self._lock = threading.Lock()

    # -- control --------------------------------------------------------------------------------

    def command(self) -> list[str]:
        exe = self.exe or checker_path()
        cmd = [str(exe), "--transport", self.transport, "--profile", "-"]
        if self.profile_path is not None:
            cmd += ["--profile-file", str(self.profile_path)]
        if self.transport == "sim":
            cmd += ["--sim", self.sim]
            if self.faults:
                cmd += ["--faults", self.faults]
            if self.sim_outputs_shm:
                cmd += ["--sim-outputs-shm", self.sim_outputs_shm]
        else:
            cmd += ["--device", self.device]
            if self.speed_hz:
                cmd += ["--speed", str(int(self.speed_hz))]
        return cmd

    def _check_busy(self) -> None:
        reason: bool | str | None
        if self.bench_busy is not None:
            reason = self.bench_busy()
        elif self.shm:
            reason = loop_active(self.shm)
        else:
            reason = None
        if reason:
            raise BenchBusy(reason if isinstance(reason, str) else "a loop is running on the bench: stop it first")

    def abort(self) -> None:
        """Ask the checker to stop (SIGINT: it zeroes the outputs between two frames and exits).
        If it has not exited after abort_timeout_s, SIGTERM, then SIGKILL. Returns at once."""
        with self._lock:
            self._abort_requested = True
            proc = self._proc
        if proc is None or proc.poll() is not None:
            return
        try:
            proc.send_signal(signal.SIGINT)
        except ProcessLookupError:
            return

        def escalate() -> None:
            for sig in (signal.SIGTERM, signal.SIGKILL):
                try:
                    proc.wait(timeout=self.abort_timeout_s)
                    return
                except subprocess.TimeoutExpired:
                    try:
                        proc.send_signal(sig)
                    except ProcessLookupError:
                        return

        threading.Thread(target=escalate, name="selfcheck-abort", daemon=True).start()

    # -- running ----------------------------------------------------------------------------------

    def events(self) -> Iterator[dict[str, Any]]:
        """Start the checker and yield its events as they come; sets self.report at the end.
        Raises BenchBusy before starting anything when a loop runs on the bench."""
        if self._proc is not None:
            raise SelfCheckError("this SelfCheck has already run: make a new one")
        self._check_busy()
        cmd = self.command()
        started = _now_iso()
        t0 = time.monotonic()
        report = Report(
            verdict="error",
            bench=self.profile.get("name", ""),
            profile=self.profile,
            profile_file=str(self.profile_path or ""),
            transport=self.transport,
            sim=self.sim,
            faults=self.faults,
            device=self.device,
            host=socket.gethostname(),
            started=started,
        )
        with self._lock:
            if self._abort_requested:
                report.error = "aborted before it started"
                report.verdict = "aborted"
                report.outputs_zeroed = True  # nothing was driven
                self.report = report
                return
            # close_fds (the default): the helper gets its pipes only; stdin carries the profile.
            # Tied: a self-check tool must not drive the board on after the appliance died.
            from .tied import popen_tied

            self._proc = popen_tied(
                cmd,
                death_signal=signal.SIGKILL,
                stdin=subprocess.PIPE,
                stdout=subprocess.PIPE,
                stderr=subprocess.PIPE,
                text=True,
                encoding="utf-8",
                errors="replace",
            )
        proc = self._proc
        assert proc.stdin is not None
        try:
            # A few kB, well inside a pipe's buffer: written whole before the checker reads it.
            proc.stdin.write(flat_form(self.profile))
        except BrokenPipeError:
            pass  # the checker is gone already; its exit code and stderr say why below
        finally:
            try:
                proc.stdin.close()
            except BrokenPipeError:
                pass
        ended = False
        try:
            assert proc.stdout is not None
            for line in proc.stdout:
                line = line.strip()
                if not line:
                    continue
                try:
                    ev = json.loads(line)
                except json.JSONDecodeError:
                    continue
                kind = ev.get("event")
                if kind == "step":
                    report.steps.append(
                        Step(
                            id=ev["id"],
                            channel=int(ev.get("channel", 0)),
                            status=ev["status"],
                            title=ev.get("title", ""),
                            message=ev.get("message", ""),
                            action=ev.get("action", ""),
                            data=ev.get("data") or {},
                        )
                    )
                elif kind == "end":
                    ended = True
                    report.verdict = ev.get("verdict", "error")
                    report.outputs_zeroed = bool(ev.get("outputs_zeroed"))
                elif kind == "error":
                    report.error = ev.get("message", "")
                yield ev
        finally:
            if proc.poll() is None and not ended:
                # The consumer stopped iterating early: stop the checker safely.
                self.abort()
            try:
                proc.wait(timeout=self.abort_timeout_s * 3 + 5)
            except subprocess.TimeoutExpired:
                proc.kill()
                proc.wait()
            stderr = proc.stderr.read() if proc.stderr else ""
            if proc.stdout:
                proc.stdout.close()
            if proc.stderr:
                proc.stderr.close()
            if not ended:
                report.verdict = "aborted" if self._abort_requested else "error"
                if not report.error:
                    report.error = f"the checker ended without a result (exit {proc.returncode})" + (
                        f": {stderr.strip()[-500:]}" if stderr.strip() else ""
                    )
            report.finished = _now_iso()
            report.duration_s = round(time.monotonic() - t0, 3)
            self.report = report

    def run(self, on_event: Callable[[dict[str, Any]], None] | None = None) -> Report:
        """Run to the end (or abort), calling on_event for each event; returns the Report."""
        for ev in self.events():
            if on_event:
                on_event(ev)
        assert self.report is not None
        return self.report


def run_selfcheck(
    profile: str | Path | dict[str, Any] = Settings.sim,
    *,
    on_event: Callable[[dict[str, Any]], None] | None = None,
    **kwargs: Any,
) -> Report:
    """SelfCheck(profile, **kwargs).run(on_event)."""
    return SelfCheck(profile, **kwargs).run(on_event)


# ---- xrf selfcheck ------------------------------------------------------------------------------

HELP = "check the bench (ico board, SPI link, motors, encoders, I/O) against its bench profile"


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument(
        "--profile",
        help="bench profile: relbot, jiwy, an edited profile's name or a FILE.json "
        f"(default: the --sim robot, else {Settings.sim})",
    )
    p.add_argument(
        "--sim",
        type=plants.arg_type,
        metavar="PLANT",
        help="simulated board to check (implies --transport sim): relbot, jiwy, ... (rt_core's plant table)",
    )
    p.add_argument("--faults", help="faults to inject into the simulated board, e.g. dead_encoder=2")
    p.add_argument(
        "--transport",
        choices=list(TRANSPORTS),
        default=None,
        help="how to reach the board (default: sim with --sim, else auto)",
    )
    p.add_argument("--device", default=None, help=f"spidev device (default {DEFAULT_SPI_DEVICE})")
    p.add_argument("--speed", type=int, default=None, help="SPI clock in Hz (default: the profile's)")
    p.add_argument("--json", action="store_true", help="print the report as JSON")
    p.add_argument("--markdown", action="store_true", help="print the report as Markdown")
    p.add_argument(
        "--save", metavar="DIR", type=Path, default=None, help="folder for the report (default <data>/selfcheck)"
    )
    p.add_argument("--no-save", action="store_true", help="do not keep the report")
    p.add_argument("--data", type=Path, default=None, help=f"data folder (default {default_data_dir()})")
    p.add_argument(
        "--shm",
        default=os.environ.get("XRF_SHM", "xrf"),
        help="shared memory of the bench's loop, checked before starting (default $XRF_SHM or xrf)",
    )
    p.add_argument("--quiet", "-q", action="store_true", help="no progress on stderr")


def run(args: argparse.Namespace) -> int:
    transport = args.transport or ("sim" if args.sim or args.faults else "auto")
    profile = args.profile or args.sim or Settings.sim
    try:
        check = SelfCheck(
            profile,
            transport=transport,
            sim=args.sim,
            faults=args.faults,
            device=args.device,
            speed_hz=args.speed,
            data_dir=args.data,
            shm=args.shm,
        )
    except (ProfileError, SelfCheckError) as exc:
        print(f"xrf selfcheck: {exc}", file=sys.stderr)
        return EXIT_COULD_NOT_RUN

    tty = sys.stderr.isatty()

    def show(ev: dict[str, Any]) -> None:
        if args.quiet:
            return
        if ev.get("event") == "progress" and tty:
            print(f"\r\033[K  … {ev.get('text', '')}", end="", file=sys.stderr, flush=True)
        elif ev.get("event") == "step":
            mark = MARKS.get(ev.get("status", ""), "?")
            clear = "\r\033[K" if tty else ""
            print(f"{clear}{mark} {ev['id']:<8} {ev.get('title', '')}", file=sys.stderr, flush=True)

    previous = signal.getsignal(signal.SIGINT)

    def on_sigint(signum: int, frame: Any) -> None:
        print("\nxrf selfcheck: aborting (outputs are being zeroed)…", file=sys.stderr, flush=True)
        check.abort()

    signal.signal(signal.SIGINT, on_sigint)
    try:
        report = check.run(show)
    except BenchBusy as exc:
        print(f"xrf selfcheck: {exc}", file=sys.stderr)
        return EXIT_COULD_NOT_RUN
    except SelfCheckError as exc:
        print(f"xrf selfcheck: {exc}", file=sys.stderr)
        return EXIT_COULD_NOT_RUN
    finally:
        signal.signal(signal.SIGINT, previous)
    if args.json:
        print(report.to_json())
    elif args.markdown:
        print(report.to_markdown(), end="")
    else:
        print(report.to_text())
    if not args.no_save:
        try:
            path = save_report(report, folder=args.save, data_dir=args.data)
            print(f"xrf selfcheck: report saved to {path}", file=sys.stderr)
        except OSError as exc:
            print(f"xrf selfcheck: could not save the report: {exc}", file=sys.stderr)
    return report.exit_code
