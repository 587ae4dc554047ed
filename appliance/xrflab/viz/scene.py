"""The 3D view: a viser server run by the appliance, showing the bench's robot as its encoders say.

- Jiwy: ``urdf/jiwy.urdf`` drawn by ``urdf_view.UrdfView`` (viser's boxes and cylinders; not
  viser's ViserUrdf, whose trimesh stack costs 77 MB); pan/tilt follow the counts; a translucent green copy (the ghost) shows the
  setpoint (Ros2Xeno ``pan_setpoint``/``tilt_setpoint``, the jiwy example's fields).
- RELbot: a body with two wheels whose pose on the floor is the wheel odometry, with a trail
  that fades with age; "Reset odometry" puts it back at the origin.
- Linear stage: a rail between its end stops and a carriage at the encoder's position, with a
  translucent green carriage (the ghost) at the setpoint (Ros2Xeno ``position_setpoint``).

Data path (nothing touches the loop): the supervisor's telemetry reader hands every batch it
reads to ``VizService.on_telemetry`` (a run observer: server/runs/lifecycle.py). Samples are thinned to
200 Hz by the run's ``Recorder`` (the replay file), and the same kept samples drive the live
kinematics, so a replay shows exactly what the live view showed. The scene itself is pushed to
the browsers at 30 Hz by ``run()``, in a thread of its own (scene building never holds up the
event loop, where the supervisor's heartbeat runs).

Which profile: on the simulated bench the run's plant names it (``relbot``, ``jiwy``, ``stage``:
the plant and its default profile share the name); on a real
bench ``XRF_BENCH_PROFILE`` (environment) names it. No profile, or one without ``mechanics``:
the robot is hidden and the view says so (a wrong picture is worse than none).

Threads: ``on_telemetry`` runs in the appliance's event loop and only does arithmetic; the 30 Hz
updater and viser's GUI callbacks run in other threads. Shared state is under ``self._lock``.
"""

from __future__ import annotations

import asyncio
import bisect
import logging
import math
import threading
import time
import warnings
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from .. import profiles as profmod
from ..server.runs.lifecycle import RunObserver
from . import kinematics as kin
from .recorder import Recorder, has_recording, load_recording, recording_size

log = logging.getLogger("xrflab.viz")
URDF_JIWY = Path(__file__).resolve().parent / "urdf" / "jiwy.urdf"
URDF_CELL = Path(__file__).resolve().parent / "urdf" / "cell.urdf"
URDF_YOUBOT = Path(__file__).resolve().parent / "urdf" / "youbot.urdf"
UPDATE_HZ = 30.0
# The scene is updated only while someone watches it (issue 30 item 4: at idle the 30 Hz thread
# was a sizeable share of the appliance's CPU, for nobody): a browser connected through the
# /viser/ proxy (or a viser client on 127.0.0.1), or a GET
# /api/viz/state within this many seconds (the 3D page polls it; an API user polling the state
# expects it to move). Otherwise the thread sleeps until one of them wakes it.
STATE_WATCH_S = 5.0
TRAIL_SEND_HZ = 5.0
BULK_MIN = 8  # samples in a batch from which it is taken in numpy (VizService._bulk)
TRAIL_MAX = 400
BACKGROUND = (1.0, 1.0, 1.0)
TRAIL_COLOR = (0.85, 0.35, 0.05)


def wxyz_z(theta: float) -> tuple[float, float, float, float]:
    """Quaternion (w, x, y, z) of a rotation by theta about +z."""
    return (math.cos(theta / 2), 0.0, 0.0, math.sin(theta / 2))


def setpoint_angles(fields: dict[str, Any]) -> dict[str, float]:
    """{pan, tilt} from Ros2Xeno fields: <axis>_setpoint, else the first <axis>*set* field."""
    out: dict[str, float] = {}
    for axis in ("pan", "tilt"):
        key = (
            f"{axis}_setpoint"
            if f"{axis}_setpoint" in fields
            else next((k for k in fields if k.startswith(axis) and "set" in k), None)
        )
        v = fields.get(key) if key else None
        if isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v):
            out[axis] = float(v)
    return out


def stage_setpoint(fields: dict[str, Any]) -> float | None:
    """The linear stage's setpoint (m) from Ros2Xeno fields: position_setpoint, else the first
    position*set* field; None when there is none."""
    key = (
        "position_setpoint"
        if "position_setpoint" in fields
        else next((k for k in fields if k.startswith("position") and "set" in k), None)
    )
    v = fields.get(key) if key else None
    if isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v):
        return float(v)
    return None


def resolve_profile(plant: str, real_bench: bool, data_dir: Path | None) -> tuple[dict | None, str, str]:
    """(profile, name, message): profile None with a message when there is none to use."""
    name = profmod.bench_profile_name(plant, real_bench)
    if not name:
        return (
            None,
            "",
            (
                "This bench has no profile: the 3D view cannot know what is connected. "
                "Start the appliance with XRF_BENCH_PROFILE=<profile name> (e.g. relbot, jiwy)."
            ),
        )
    try:
        profile = profmod.load_profile(name, data_dir)
    except profmod.ProfileError as exc:
        return None, name, f"No usable bench profile {name!r}: {'; '.join(exc.errors)}"
    try:
        kin.from_profile(profile)
    except (kin.KinematicsError, KeyError, TypeError, ValueError) as exc:
        return None, name, f"Bench profile {name!r} cannot be drawn: {exc}"
    return profile, name, ""


# ---- replay ---------------------------------------------------------------------------------


@dataclass
class Replay:
    run_id: int
    kind: str  # pan_tilt | differential_drive | linear_stage | "" (no profile)
    profile_name: str
    message: str
    t: list[float]  # s since the first sample
    joints: list[tuple[float, float]] = field(default_factory=list)
    poses: list[tuple[float, float, float]] = field(default_factory=list)
    trail_lo: list[int] = field(default_factory=list)  # trail of sample i: trail[trail_lo[i]:trail_n[i]]
    trail_n: list[int] = field(default_factory=list)
    trail: list[tuple[float, float]] = field(default_factory=list)
    positions: list[float] = field(default_factory=list)  # linear_stage, m
    axes: list[list[float]] = field(default_factory=list)  # cell: each axis, rad or m
    arm: list[list[float]] = field(default_factory=list)  # youbot: the five joints, rad
    setpoint_t: list[float] = field(default_factory=list)
    setpoints: list[dict[str, Any]] = field(default_factory=list)

    @property
    def duration(self) -> float:
        return self.t[-1] if self.t else 0.0

    def index(self, t: float) -> int:
        return max(0, bisect.bisect_right(self.t, t) - 1)

    def setpoint_at(self, t: float) -> dict[str, Any]:
        i = bisect.bisect_right(self.setpoint_t, t) - 1
        return self.setpoints[i] if i >= 0 else {}


def _replay_model(r: Replay, model: Any, encs: list[tuple[int, ...]], times: list[float], resets: list[float]) -> None:
    """The recorded counts through the model, into the replay's series (IndexError: a sample
    has fewer channels than the model reads)."""
    if isinstance(model, kin.PanTilt):
        for enc in encs:
            a = model.update(enc)
            r.joints.append((a["pan"], a["tilt"]))
    elif isinstance(model, kin.DiffDrive):
        lo, ri = 0, 0
        for ti, enc in zip(times, encs):
            while ri < len(resets) and resets[ri] <= ti:
                model.reset_pose()
                lo = len(r.trail)  # the trail restarts at a reset, as it does live
                ri += 1
            p = model.update(enc)
            r.poses.append((p.x, p.y, p.theta))
            if len(r.trail) == lo or math.hypot(p.x - r.trail[-1][0], p.y - r.trail[-1][1]) >= model.trail_step_m:
                r.trail.append((p.x, p.y))
            r.trail_lo.append(lo)
            r.trail_n.append(len(r.trail))
    elif isinstance(model, kin.LinearStage):
        r.positions = [model.update(enc) for enc in encs]
    elif isinstance(model, kin.Cell):
        # The recording keeps no input pins: a replayed cell is drawn from where it started.
        r.axes = [list(model.update(enc)) for enc in encs]
    elif isinstance(model, kin.Youbot):
        for enc in encs:
            r.arm.append(list(model.update(enc)))
            p = model.pose
            r.poses.append((p.x, p.y, p.theta))


def build_replay(run_id: int, run_dir: Path, data_dir: Path | None = None) -> Replay:
    """Run a recording through the same kinematics as the live view (in a worker thread)."""
    rec = load_recording(run_dir)
    t0 = rec.t_ns[0] if rec.t_ns else 0
    times = [(t - t0) / 1e9 for t in rec.t_ns]
    profile = rec.meta.get("profile")
    message = ""
    model: Any = None
    if profile:
        try:
            model = kin.from_profile(profile)
        except (kin.KinematicsError, KeyError, TypeError, ValueError) as exc:
            message = f"the recorded profile cannot be drawn: {exc}"
    else:
        message = rec.meta.get("message") or "this run was recorded without a bench profile"
    r = Replay(run_id, model.kind if model else "", rec.meta.get("profile_name", ""), message, times)
    events = [(max(0.0, (e["t_ns"] - t0) / 1e9), e) for e in rec.events]
    current: dict[str, Any] = {}
    for te, e in events:
        if "setpoint" in e:
            current = {**current, **e["setpoint"]}
            r.setpoint_t.append(te)
            r.setpoints.append(dict(current))
    resets = [te for te, e in events if e.get("reset_odometry")]
    try:
        _replay_model(r, model, rec.enc, times, resets)
    except IndexError:
        # meta.json is the loop's to rewrite: a channel count below what the profile draws
        n = len(rec.enc[0]) if rec.enc else 0
        raise ValueError(f"run {run_id}: its recording has {n} channels, fewer than its profile draws") from None
    return r


# ---- the service ----------------------------------------------------------------------------


def _bench_channels(run: Any) -> int:
    """The run's channel count as its telemetry reader took it from the shared-memory header
    (bounded there: 1..XRF_MAX_CHANNELS); 4, one ico board, for a run without one."""
    ch = getattr(run, "channels", None)
    return int(ch.geom.channels) if ch is not None else 4


def _columns(samples: Any) -> tuple[list[int], list[int], list[Any]]:
    """(t_ns, cycle, enc) of a batch of samples, as lists: the reader's TelemetryBatch has them
    (channels/rings.py, made by numpy); any other sequence is taken apart here."""
    if isinstance(getattr(samples, "t_ns", None), list):
        return samples.t_ns, samples.cycle, samples.enc
    return [s.t_ns for s in samples], [s.cycle for s in samples], [s.enc for s in samples]


def _dins(samples: Any) -> list[Any]:
    """Each sample's din (None where a sample has none): the home switches a Cell homes on."""
    if isinstance(getattr(samples, "t_ns", None), list):
        return samples.din
    return [getattr(s, "din", None) for s in samples]


class VizService(RunObserver):
    def __init__(self, settings: Any, supervisor: Any = None) -> None:
        self.settings = settings
        self.supervisor = supervisor
        self.server: Any = None
        self.error = ""  # viser could not start: the page shows this
        self.port: int | None = None
        self._lock = threading.Lock()
        self._start_lock = threading.Lock()  # viser starts once, at the first watcher (ensure_server)
        self._thread: threading.Thread | None = None
        self._stop = threading.Event()
        self._wake = threading.Event()  # a watcher came (viser client, state request) or stop
        self._state_asked = -1e9  # time.monotonic() of the last GET /api/viz/state
        self._viewers = 0  # browsers connected through the appliance's /viser/ proxy
        self.handovers = 0  # batches of samples taken (on_samples): tests, GET /api/viz
        # live
        self.mode = "idle"  # idle | live | replay
        self.run_id: int | None = None
        self.run_active = False
        self.plant = ""
        self.profile_name = ""
        self.message = ""
        self.model: Any = None
        self._backlog = kin.Backlog()  # the model's samples while nobody looks at it (_model_now)
        self.recorder: Recorder | None = None
        self.setpoint: dict[str, Any] = {}
        self._setpoint_seen: dict[str, Any] = {}
        self.samples = 0
        self.last_t_ns = 0
        self._trail_dirty = True
        # replay
        self.replay: Replay | None = None
        self.replay_t = 0.0
        # requests from viser's thread / the API
        self._want_reset = False
        # what the scene shows now (GET /api/viz/state)
        self.shown: dict[str, Any] = {}
        self.frames = 0
        self._scene_kind: str | None = None  # kind the scene's robot nodes were built for
        self._nodes: dict[str, Any] = {}
        self._gui: dict[str, Any] = {}
        self._last_trail_send = 0.0
        self._last_md = ""

    # -- lifecycle ------------------------------------------------------------------------------

    @property
    def data_dir(self) -> Path | None:
        return Path(self.settings.data_dir)

    def _real_bench(self) -> bool:
        try:
            return bool(self.settings.bench_is_real())
        except Exception:
            return False

    async def start(self) -> None:
        """The robot's model and the 30 Hz thread (asleep until someone watches). viser itself
        starts at the first watcher (ensure_server): importing it and running its server cost the
        appliance ~25 MB RSS and two threads from start-up on, for a view few sessions open
        (issue 30 item 4)."""
        import importlib.util

        if importlib.util.find_spec("viser") is None:  # without importing it
            self.error = "3D view unavailable: the viser package is not installed"
            log.warning("%s", self.error)
            return
        plant = self.settings.sim
        profile, name, message = resolve_profile(plant, self._real_bench(), self.data_dir)
        self._set_robot(profile, name, message, plant)
        # Its own thread, not a task: building a scene (loading the URDF) takes long enough to
        # delay the supervisor's heartbeat if it ran in the event loop.
        self._thread = threading.Thread(target=self.run, name="viz-30hz", daemon=True)
        self._thread.start()

    def ensure_server(self) -> int | None:
        """viser's port, starting it first if this is the first watcher (the /viser/ proxy, the
        scene's thread on a state request); None if it cannot start (the reason in .error).
        Blocking (the import and the server's start): not on the event loop."""
        with self._start_lock:
            if self.server is None and not self.error and not self._stop.is_set():
                try:
                    self._start_viser()
                except Exception as exc:  # no port, a broken install: the appliance runs without 3D
                    self.error = f"3D view unavailable: {exc}"
                    log.warning("%s", self.error)
            return self.port if self.server is not None else None

    def _start_viser(self) -> None:
        import viser

        port = int(self.settings.port) + 1
        # Loopback only, whatever --host is: browsers reach it through the appliance's /viser/
        # proxy (server/http/viser.py), behind the login.
        self.server = viser.ViserServer(host="127.0.0.1", port=port, label="XRF Lab 3D", verbose=False)
        self.port = int(self.server.get_port())

        self.server.scene.set_up_direction("+z")
        self._build_gui()
        self.server.on_client_connect(self._viser_client)

    def _viser_client(self, _client: Any) -> None:
        """A viser client connected (viser's thread): as viewer_joined, for one that came to
        viser's port directly."""
        self._wake.set()
        if self._viewers == 0 and time.monotonic() - self._state_asked >= STATE_WATCH_S:
            self._watch_started()

    async def stop(self) -> None:
        self._stop.set()
        self._wake.set()
        if self._thread is not None:
            await asyncio.to_thread(self._thread.join, 2.0)
        with self._lock:
            if self.recorder is not None:
                self.recorder.close()
        with self._start_lock:  # not while it starts (ensure_server): then it would outlive us
            server = self.server
        if server is not None:
            await asyncio.to_thread(server.stop)

    def info(self) -> dict[str, Any]:
        return {
            "available": not self.error,  # viser starts at the first watcher (ensure_server)
            "started": self.server is not None,
            "url": "/viser/",
            "port": self.port,
            "error": self.error,
            "update_hz": UPDATE_HZ,
            "watched": self.watched(),
            "frames": self.frames,
            "handovers": self.handovers,
        }

    # -- telemetry in (supervisor hook, event loop) ---------------------------------------------

    # A run observer (server/runs/lifecycle.py), after host logging: samples per reader batch, and
    # the end, which closes the run's recording.
    name = "3D view"

    def on_samples(self, run: Any, samples: Any) -> None:
        self.handovers += 1
        self.on_telemetry(run, samples)

    def live(self, run: Any) -> bool:
        # The recording and the model take every sample either way; only a 3D view that is
        # watched needs them as they come (else the reader hands them over once a second).
        return self.watched()

    async def on_ended(self, row: Any, run: Any) -> None:
        if run is not None:  # a run recovered at start-up was never shown here
            self.on_telemetry(run, None)

    def on_telemetry(self, run: Any, samples: Any) -> None:
        """(run, samples) per reader batch, (run, None) at the end. `samples`: the reader's
        TelemetryBatch (its columns are lists already: no sample is converted whole here) or
        any sequence of samples with t_ns, cycle, enc (and din)."""
        with self._lock:
            if samples is None:
                if run.row.id == self.run_id:
                    self.run_active = False
                    if self.recorder is not None:
                        self.recorder.close()
                return
            if run.row.id != self.run_id:
                self._new_run(run)
            rec = self.recorder
            model = self.model
            if not self._bulk(samples, rec, model):
                self._one_by_one(samples, rec, model)
            sp = getattr(run, "setpoint", None) or {}
            if sp != self._setpoint_seen:
                self._setpoint_seen = dict(sp)
                self.setpoint = dict(sp)
                if rec is not None:
                    rec.event(self.last_t_ns, setpoint=self.setpoint)

    def _bulk(self, samples: Any, rec: Recorder | None, model: Any) -> bool:
        """A batch handed over in bulk (the reader's, with nobody watching: up to IDLE_PERIOD_S of
        samples) recorded and run through the model in numpy, without a Python object per sample
        (issue 30 item 4: this was half the idle appliance's Python); True when done, False when
        the batch is for `_one_by_one` (a few samples, a Cell homing on its switches, samples
        denser than the recording keeps)."""
        if len(samples) < BULK_MIN or not hasattr(samples, "arrays") or isinstance(model, kin.Cell):
            return False
        t_ns, cycles, encs = samples.arrays()
        if rec is not None and not rec.add_many(t_ns, cycles, encs):
            return False
        self.samples += len(t_ns)
        self.last_t_ns = int(t_ns[-1])
        if model is not None and self._backlog.add(model, encs):  # run through it when looked at
            self._trail_dirty = True
        return True

    def _model_now(self) -> Any:
        """(Under the lock.) The model with every sample taken so far: its backlog (`_bulk`'s,
        while nobody watched) run through it first."""
        if self._backlog.apply(self.model):
            self._trail_dirty = True
        return self.model

    def _one_by_one(self, samples: Any, rec: Recorder | None, model: Any) -> None:
        """Each sample offered to the recording, the kept ones through the model."""
        self._model_now()  # the samples before these first
        t_ns, cycles, encs = _columns(samples)
        dins = _dins(samples) if isinstance(model, kin.Cell) else None
        for i, t in enumerate(t_ns):
            if rec is None or rec.add(t, cycles[i], encs[i]):
                self.samples += 1
                self.last_t_ns = t
                if dins is not None:
                    model.update(encs[i], dins[i])  # homes on its switches
                elif model is not None:
                    model.update(encs[i])
                    self._trail_dirty = True

    def _new_run(self, run: Any) -> None:
        if self.recorder is not None:
            self.recorder.close()
        row = run.row
        self.run_id = row.id
        self.run_active = True
        self.samples = 0
        self.setpoint, self._setpoint_seen = {}, {}
        plant = getattr(row, "sim", "") or self.settings.sim
        profile, name, message = resolve_profile(plant, self._real_bench(), self.data_dir)
        self._set_robot(profile, name, message, plant)
        meta = {
            "run_id": row.id,
            "build": row.build,
            "plant": plant,
            "profile_name": name,
            "profile": profile,
            "message": message,
            "real_bench": self._real_bench(),
        }
        try:
            self.recorder = Recorder(run.run_dir, meta, _bench_channels(run))
        except OSError as exc:
            log.warning("run %s: no 3D recording: %s", row.id, exc)
            self.recorder = None
        if self.mode != "replay":
            self.mode = "live"

    def _set_robot(self, profile: dict | None, name: str, message: str, plant: str) -> None:
        self.plant = plant
        self.profile_name = name
        self.message = message
        self._backlog.drop()  # the last run's samples, for the model replaced here
        self.model = kin.from_profile(profile) if profile else None
        self._trail_dirty = True

    # -- requests (API and viser GUI; any thread) -----------------------------------------------

    def reset_odometry(self) -> bool:
        with self._lock:
            if not isinstance(self._model_now(), kin.DiffDrive):  # reset after the samples before it
                return False
            self.model.reset_pose()
            self._trail_dirty = True
            if self.recorder is not None:
                self.recorder.event(self.last_t_ns, reset_odometry=True)
            return True

    def load_replay(self, run_id: int) -> Replay:
        """Switch to replaying a finished run (blocking: call from a worker thread)."""
        run_dir = self._run_dir(run_id)
        if run_dir is None or not has_recording(run_dir):
            raise LookupError(f"run {run_id} has no 3D recording")
        with self._lock:
            if run_id == self.run_id and self.run_active:
                raise ValueError(f"run {run_id} is still running: it is shown live")
        replay = build_replay(run_id, run_dir, self.data_dir)
        with self._lock:
            self.replay, self.replay_t, self.mode = replay, 0.0, "replay"
            self._trail_dirty = True
        self._sync_replay_gui()
        return replay

    def seek(self, t: float) -> float:
        with self._lock:
            if self.replay is None:
                raise LookupError("no replay loaded")
            self.replay_t = min(max(0.0, float(t)), self.replay.duration)
            self._trail_dirty = True
            t = self.replay_t
        slider = self._gui.get("slider")
        if slider is not None and abs(slider.value - t) > 1e-9:
            slider.value = t
        return t

    def go_live(self) -> None:
        with self._lock:
            self.mode = "live" if self.run_id is not None else "idle"
            self.replay = None
            self._trail_dirty = True
        self._sync_replay_gui()

    def _run_dir(self, run_id: int) -> Path | None:
        sup = self.supervisor
        if sup is not None:
            try:
                row = sup.store.get(run_id)
            except Exception:
                row = None
            if row is not None and row.run_dir:
                return Path(row.run_dir)
        return Path(self.settings.runs_dir) / str(run_id)

    def recordings(self) -> list[dict[str, Any]]:
        runs_dir = self.settings.runs_dir
        out = []
        if runs_dir and Path(runs_dir).is_dir():
            for d in Path(runs_dir).iterdir():  # <data>/runs/: the appliance's folder
                size = recording_size(d) if d.name.isdigit() else None  # inside a run: its helper
                if size is not None:
                    active = int(d.name) == self.run_id and self.run_active
                    out.append({"run_id": int(d.name), "active": active, "bytes": size})
        return sorted(out, key=lambda r: -r["run_id"])

    # -- the 30 Hz update -------------------------------------------------------------------------

    def state_asked(self) -> None:
        """GET /api/viz/state: someone watches the scene through the API (see STATE_WATCH_S)."""
        was = self.watched()
        self._state_asked = time.monotonic()
        self._wake.set()
        if not was:
            self._watch_started()

    def viewer_joined(self) -> None:
        """A browser's WebSocket through the /viser/ proxy opened (server/http/viser.py)."""
        was = self.watched()
        with self._lock:
            self._viewers += 1
        self._wake.set()
        if not was:
            self._watch_started()

    def _watch_started(self) -> None:
        """Nobody watched and now someone does: the run's reader hands the samples over now and
        then as they come (the model is current from then on), not at its next idle batch, up
        to IDLE_PERIOD_S later (server/runs/reader.py). From any thread."""
        sup = self.supervisor
        if sup is not None:
            sup.wake_reader()

    def viewer_left(self) -> None:
        with self._lock:
            self._viewers -= 1

    def watched(self) -> bool:
        if self._viewers > 0 or time.monotonic() - self._state_asked < STATE_WATCH_S:
            return True
        return self.server is not None and len(self.server.get_clients()) > 0

    def run(self) -> None:
        """The 30 Hz updater (own thread); asleep while nobody watches (watched())."""
        period = 1.0 / UPDATE_HZ
        next_t = time.monotonic()
        while not self._stop.is_set():
            if not self.watched():
                # Cleared before the re-check: a watcher arriving in between sets it again.
                self._wake.clear()
                if not self.watched():
                    self._wake.wait()  # a viewer, a viser client, a state request or stop() sets it
                    next_t = time.monotonic()
                    continue
            try:
                self.tick()
            except Exception:  # a scene problem must not end the updates
                log.exception("3D view update failed")
            next_t += period
            delay = next_t - time.monotonic()
            if delay < 0:
                next_t, delay = time.monotonic(), 0
            self._stop.wait(delay)

    def frame(self) -> dict[str, Any]:
        """What the scene should show now (under the lock)."""
        if self.mode == "replay" and self.replay is not None:
            r = self.replay
            i = r.index(self.replay_t)
            f: dict[str, Any] = {
                "mode": "replay",
                "kind": r.kind,
                "message": r.message,
                "run_id": r.run_id,
                "profile": r.profile_name,
                "t": self.replay_t,
                "duration": r.duration,
                "setpoint": r.setpoint_at(self.replay_t),
            }
            if r.kind == "pan_tilt" and r.joints:
                f["joints"] = dict(zip(("pan", "tilt"), r.joints[i]))
            elif r.kind == "differential_drive" and r.poses:
                f["pose"] = dict(zip(("x", "y", "theta"), r.poses[i]))
                n = r.trail_n[i]
                f["trail"] = r.trail[max(r.trail_lo[i], n - TRAIL_MAX) : n]
            elif r.kind == "linear_stage" and r.positions:
                f["position"] = r.positions[i]
            elif r.kind == "cell" and r.axes:
                f["axes"] = r.axes[i]
                f["homed"] = None
            elif r.kind == "youbot" and r.arm:
                f["arm"] = r.arm[i]
                f["pose"] = dict(zip(("x", "y", "theta"), r.poses[i]))
            return f
        m = self._model_now()
        f = {
            "mode": self.mode,
            "kind": m.kind if m else "",
            "message": self.message,
            "run_id": self.run_id,
            "profile": self.profile_name,
            "active": self.run_active,
            "samples": self.samples,
            "setpoint": dict(self.setpoint),
        }
        if isinstance(m, kin.PanTilt):
            f["joints"] = dict(m.angles)
        elif isinstance(m, kin.DiffDrive):
            p = m.pose
            f["pose"] = {"x": p.x, "y": p.y, "theta": p.theta}
            f["trail"] = m.trail[-TRAIL_MAX:]
        elif isinstance(m, kin.LinearStage):
            f["position"] = m.position
        elif isinstance(m, kin.Cell):
            f["axes"] = list(m.positions)
            f["homed"] = list(m.homed)
        elif isinstance(m, kin.Youbot):
            f["arm"] = list(m.angles)
            p = m.pose
            f["pose"] = {"x": p.x, "y": p.y, "theta": p.theta}
        return f

    def tick(self) -> None:
        with self._lock:
            f = self.frame()
            trail_dirty = self._trail_dirty
        if self.server is None and self.ensure_server() is None:
            return
        self._ensure_scene(f["kind"])
        n = self._nodes
        if f["kind"] == "pan_tilt":
            import numpy as np

            j = f.get("joints") or {"pan": 0.0, "tilt": 0.0}
            n["urdf"].update_cfg(np.array([j["pan"], j["tilt"]]))
            sp = setpoint_angles(f.get("setpoint") or {})
            ghost = n["ghost"]
            if sp:
                ghost.update_cfg(np.array([sp.get("pan", j["pan"]), sp.get("tilt", j["tilt"])]))
            ghost.show_visual = bool(sp)
            f["ghost"] = sp or None
        elif f["kind"] == "differential_drive":
            p = f.get("pose") or {"x": 0.0, "y": 0.0, "theta": 0.0}
            n["robot"].position = (p["x"], p["y"], 0.0)
            n["robot"].wxyz = wxyz_z(p["theta"])
            now = time.monotonic()
            if trail_dirty and now - self._last_trail_send >= 1.0 / TRAIL_SEND_HZ:
                self._send_trail(f.get("trail") or [])
                self._last_trail_send = now
                with self._lock:
                    self._trail_dirty = False
        elif f["kind"] == "cell":
            import numpy as np

            n["urdf"].update_cfg(np.array(f.get("axes") or [0.0, 0.0, 0.0]))
        elif f["kind"] == "youbot":
            import numpy as np

            # The base's frame moves on the floor (odometry); the arm's joints within it.
            p = f.get("pose") or {"x": 0.0, "y": 0.0, "theta": 0.0}
            n["robot"].position = (p["x"], p["y"], 0.0)
            n["robot"].wxyz = wxyz_z(p["theta"])
            n["urdf"].update_cfg(np.array(f.get("arm") or [0.0] * 5))
        elif f["kind"] == "linear_stage":
            carriage_x = f.get("position") or 0.0
            n["carriage"].position = (carriage_x, 0.0, 0.0)
            sp_x = stage_setpoint(f.get("setpoint") or {})
            if sp_x is not None:
                n["ghost"].position = (sp_x, 0.0, 0.0)
            n["ghost"].visible = sp_x is not None
            f["ghost"] = sp_x
        self.frames += 1
        f.pop("trail", None)
        f["frame"] = self.frames
        self.shown = f
        self._update_status(f)

    # -- scene building ---------------------------------------------------------------------------

    def _ensure_scene(self, kind: str) -> None:
        if kind == self._scene_kind:
            return
        # A URDF's remove() takes its links with it, and some of those links are kept here as
        # nodes of their own: viser warns once per node removed twice (20 lines per scene change).
        with warnings.catch_warnings():
            warnings.filterwarnings("ignore", message="Attempted to remove already removed node")
            for node in self._nodes.values():
                try:
                    node.remove()
                except Exception:
                    pass
        self._nodes = {}
        self._scene_kind = kind
        scene = self.server.scene
        if kind == "pan_tilt":
            from .urdf_view import UrdfView

            self._nodes["grid"] = scene.add_grid("/floor", width=1.0, height=1.0, cell_size=0.05, section_size=0.25)
            self._nodes["urdf"] = UrdfView(self.server, URDF_JIWY, root_node_name="/jiwy")
            self._nodes["ghost"] = UrdfView(
                self.server, URDF_JIWY, root_node_name="/jiwy_setpoint", mesh_color_override=(0.1, 0.8, 0.3, 0.3)
            )
            self.server.initial_camera.position = (0.55, -0.45, 0.45)
            self.server.initial_camera.look_at = (0.0, 0.0, 0.15)
        elif kind == "differential_drive":
            m = self.model
            r = getattr(m, "wheel_radius", 0.0505)
            track = getattr(m, "track", 0.20)
            self._nodes["grid"] = scene.add_grid("/floor", width=6.0, height=6.0, cell_size=0.1, section_size=1.0)
            robot = scene.add_frame("/relbot", show_axes=False)
            self._nodes["robot"] = robot
            scene.add_box(
                "/relbot/body",
                color=(60, 110, 190),
                dimensions=(0.22, track - 0.04, 0.08),
                position=(0.0, 0.0, r + 0.02),
            )
            wheel_q = (math.cos(math.pi / 4), math.sin(math.pi / 4), 0.0, 0.0)  # cylinder axis z -> y
            for side, y in (("left", track / 2), ("right", -track / 2)):
                scene.add_cylinder(
                    f"/relbot/wheel_{side}",
                    radius=r,
                    height=0.025,
                    color=(30, 30, 30),
                    wxyz=wheel_q,
                    position=(0.0, y, r),
                )
            scene.add_icosphere("/relbot/caster", radius=0.015, color=(120, 120, 120), position=(-0.09, 0.0, 0.015))
            scene.add_box(
                "/relbot/front", color=(230, 60, 40), dimensions=(0.06, 0.03, 0.01), position=(0.12, 0.0, r + 0.065)
            )
            self.server.initial_camera.position = (-0.9, -1.1, 1.0)
            self.server.initial_camera.look_at = (0.0, 0.0, 0.0)
            self._send_trail([])
        elif kind == "cell":
            from .urdf_view import UrdfView

            self._nodes["grid"] = scene.add_grid("/floor", width=1.0, height=1.0, cell_size=0.05, section_size=0.25)
            self._nodes["urdf"] = UrdfView(self.server, URDF_CELL, root_node_name="/cell")
            self.server.initial_camera.position = (0.2, -0.8, 0.6)
            self.server.initial_camera.look_at = (0.0, 0.0, 0.1)
        elif kind == "youbot":
            from .urdf_view import UrdfView

            self._nodes["grid"] = scene.add_grid("/floor", width=4.0, height=4.0, cell_size=0.1, section_size=1.0)
            # The URDF under a frame of its own, so the base's odometry moves the whole robot.
            self._nodes["robot"] = scene.add_frame("/youbot", show_axes=False)
            self._nodes["urdf"] = UrdfView(self.server, URDF_YOUBOT, root_node_name="/youbot/robot")
            self.server.initial_camera.position = (0.9, -1.2, 0.9)
            self.server.initial_camera.look_at = (0.1, 0.0, 0.25)
        elif kind == "linear_stage":
            lo, hi = getattr(self.model, "limits", (-0.1, 0.1))
            length = hi - lo + 0.06  # the rail reaches past the end stops to the end blocks
            self._nodes["grid"] = scene.add_grid("/floor", width=0.6, height=0.3, cell_size=0.01, section_size=0.05)
            self._nodes["rail"] = scene.add_box(
                "/stage_rail",
                color=(150, 150, 160),
                dimensions=(length, 0.04, 0.02),
                position=((lo + hi) / 2, 0.0, 0.01),
            )
            for side, x in (("low", lo - 0.02), ("high", hi + 0.02)):
                self._nodes[f"stop_{side}"] = scene.add_box(
                    f"/stage_stop_{side}", color=(60, 60, 60), dimensions=(0.01, 0.06, 0.05), position=(x, 0.0, 0.025)
                )
            self._nodes["motor"] = scene.add_cylinder(
                "/stage_motor",
                radius=0.02,
                height=0.05,
                color=(40, 40, 40),
                wxyz=(math.cos(math.pi / 4), 0.0, math.sin(math.pi / 4), 0.0),
                position=(lo - 0.05, 0.0, 0.025),
            )
            carriage = scene.add_frame("/stage_carriage", show_axes=False)
            self._nodes["carriage"] = carriage
            scene.add_box(
                "/stage_carriage/body", color=(60, 110, 190), dimensions=(0.04, 0.06, 0.03), position=(0.0, 0.0, 0.035)
            )
            ghost = scene.add_frame("/stage_setpoint", show_axes=False, visible=False)
            self._nodes["ghost"] = ghost
            scene.add_box(
                "/stage_setpoint/body",
                color=(25, 200, 75),
                opacity=0.3,
                dimensions=(0.04, 0.06, 0.03),
                position=(0.0, 0.0, 0.035),
            )
            self.server.initial_camera.position = (0.05, -0.35, 0.25)
            self.server.initial_camera.look_at = (0.0, 0.0, 0.02)
        else:
            self._nodes["grid"] = scene.add_grid("/floor", width=1.0, height=1.0, cell_size=0.1, section_size=0.5)

    def _send_trail(self, trail: list[tuple[float, float]]) -> None:
        import numpy as np

        scene = self.server.scene
        if len(trail) < 2:
            if "trail" in self._nodes:
                self._nodes["trail"].visible = False
            return
        pts = np.asarray(trail, dtype=np.float32)
        seg = np.zeros((len(pts) - 1, 2, 3), dtype=np.float32)
        seg[:, 0, :2], seg[:, 1, :2] = pts[:-1], pts[1:]
        seg[:, :, 2] = 0.002
        # Fading: the newest segment in the trail colour, the oldest nearly the background.
        age = np.linspace(0.9, 0.0, len(seg), dtype=np.float32)[:, None]
        col = np.asarray(TRAIL_COLOR, np.float32) * (1 - age) + np.asarray(BACKGROUND, np.float32) * age
        colors = np.repeat((col * 255).astype(np.uint8)[:, None, :], 2, axis=1)
        self._nodes["trail"] = scene.add_line_segments("/trail", points=seg, colors=colors, thickness=0.012)

    # -- GUI ----------------------------------------------------------------------------------------

    def _build_gui(self) -> None:
        # Display only: the scene is shared by everyone watching (observers too), so its panel must not change anything or
        # load another user's run. The controls (reset, replay, seek, live) are on the dashboard's
        # 3D page, through /api/viz with its permissions (issue 7, docs/developers/security.md).
        gui = self.server.gui
        self._gui["status"] = gui.add_markdown("Starting…")

    def _sync_replay_gui(self) -> None:
        g = self._gui
        if "slider" not in g:
            return
        r = self.replay
        if r is not None:
            g["slider"].max = max(r.duration, 0.01)
            g["slider"].value = 0.0
            g["slider"].disabled = False
            g["run"].value = r.run_id
        else:
            g["slider"].disabled = True

    def _update_status(self, f: dict[str, Any]) -> None:
        if "status" not in self._gui:
            return
        lines = []
        if f["mode"] == "replay":
            lines.append(f"**Replay** of run {f['run_id']}: {f['t']:.2f} / {f['duration']:.2f} s")
        elif f["mode"] == "live":
            lines.append(f"**Live**: run {f['run_id']}" + ("" if f.get("active") else " (ended)"))
        else:
            lines.append("**No run yet**: the robot is shown at rest")
        if f.get("message"):
            lines.append(f"⚠ {f['message']}")
        if "joints" in f:
            j = f["joints"]
            lines.append(f"pan {math.degrees(j['pan']):.1f}°, tilt {math.degrees(j['tilt']):.1f}°")
            if f.get("ghost"):
                g = f["ghost"]
                lines.append("setpoint (green): " + ", ".join(f"{k} {math.degrees(v):.1f}°" for k, v in g.items()))
        if "position" in f:
            lines.append(f"carriage at {1000 * f['position']:.1f} mm")
            if f.get("ghost") is not None:
                lines.append(f"setpoint (green): {1000 * f['ghost']:.1f} mm")
        if "axes" in f:
            a, h = f["axes"], f.get("homed")
            lines.append(f"table {math.degrees(a[0]):.1f}°, press {1000 * a[1]:.1f} mm, feeder {1000 * a[2]:.1f} mm")
            if h is None:
                lines.append("replay: drawn from where the axes started (no switches recorded)")
            else:
                lines.append(
                    "homed"
                    if all(h)
                    else "not homed: " + ", ".join(nm for nm, ok in zip(("table", "press", "feeder"), h) if not ok)
                )
        if "arm" in f:
            lines.append("arm " + ", ".join(f"J{k + 1} {math.degrees(a):.1f}°" for k, a in enumerate(f["arm"])))
        if "pose" in f:
            p = f["pose"]
            lines.append(f"x {p['x']:.3f} m, y {p['y']:.3f} m, θ {math.degrees(p['theta']):.1f}°")
        md = "  \n".join(lines)
        if md != self._last_md:  # markdown is re-sent only when the text changes (at most 30 Hz)
            self._gui["status"].content = md
            self._last_md = md
        if "reset" in self._gui:
            self._gui["reset"].disabled = f["kind"] != "differential_drive" or f["mode"] == "replay"
        if "no_profile" not in self._nodes and f.get("message") and not f["kind"]:
            self._nodes["no_profile"] = self.server.scene.add_label("/no_profile", f["message"], position=(0, 0, 0.1))
        elif "no_profile" in self._nodes and f["kind"]:
            self._nodes.pop("no_profile").remove()
