"""The live recording's sender as the appliance had it before session 12, with the rerun SDK: the
reference that tests/logs/test_live_sender.py compares the appliance's own sender
(logs/rerun_sender.py LiveSender, no SDK) against. The same calls as LiveSender, made as
logs/rerun_live.py made them (RecordingStream + connect_grpc to the run's proxy, send_columns of
Scalars and TextLog, SeriesLines static, the live blueprint by bindings.send_blueprint)."""

from __future__ import annotations

from typing import Any

import numpy as np

APP_ID = "xrflab"


def live_blueprint(groups: list[str], telemetry: list[str], span_s: float, freq: int) -> Any:
    import rerun as rr
    import rerun.blueprint as rrb

    span = [
        rrb.VisibleTimeRange(
            "cycle",
            start=rrb.TimeRangeBoundary.cursor_relative(seq=-int(span_s * freq)),
            end=rrb.TimeRangeBoundary.cursor_relative(),
        ),
        rrb.VisibleTimeRange(
            "time",
            start=rrb.TimeRangeBoundary.cursor_relative(seconds=-span_s),
            end=rrb.TimeRangeBoundary.cursor_relative(),
        ),
    ]
    views = [
        rrb.TimeSeriesView(origin=f"/log/{rr.escape_entity_path_part(g)}", name=f"log: {g}", time_ranges=span)
        for g in groups
    ]
    views += [rrb.TimeSeriesView(origin=f"/telemetry/{t}", name=t, time_ranges=span) for t in telemetry]
    return rrb.Blueprint(rrb.Grid(*views), rrb.TimePanel(timeline="cycle"), collapse_panels=True)


class SdkSender:
    """LiveSender's calls through the rerun SDK, to the proxy at `grpc_url` (rerun+http://.../proxy)."""

    def __init__(self, grpc_url: str, recording_id: str) -> None:
        self._url = grpc_url
        self._recording_id = recording_id
        self.rec: Any = None

    def connect(self) -> None:
        import rerun as rr

        self.rec = rr.RecordingStream(APP_ID, recording_id=self._recording_id)
        self.rec.connect_grpc(self._url)

    def blueprint(self, groups: list[str], telemetry: list[str], span_s: float, freq: int) -> None:
        import rerun as rr
        from rerun.blueprint.api import create_in_memory_blueprint

        bp = live_blueprint(groups, telemetry, span_s, freq)
        storage = create_in_memory_blueprint(application_id=APP_ID, blueprint=bp).storage
        rr.bindings.send_blueprint(storage, True, True, recording=self.rec.to_native())

    def series_names(self, entity: str, names: list[str]) -> None:
        import rerun as rr

        self.rec.log(entity, rr.SeriesLines(names=names), static=True)

    def _indexes(self, cycle: np.ndarray, time_ns: np.ndarray) -> list[Any]:
        import rerun as rr

        return [
            rr.TimeColumn("cycle", sequence=cycle.astype(np.int64)),
            rr.TimeColumn("time", timestamp=time_ns.astype(np.int64).view("datetime64[ns]")),
        ]

    def scalars(self, entity: str, cycle: np.ndarray, time_ns: np.ndarray, values: np.ndarray) -> None:
        import rerun as rr

        self.rec.send_columns(entity, indexes=self._indexes(cycle, time_ns), columns=rr.Scalars.columns(scalars=values))

    def texts(self, entity: str, cycle: np.ndarray, t_s: np.ndarray, texts: list[str], level: str) -> None:
        import rerun as rr

        idx = [rr.TimeColumn("cycle", sequence=cycle.astype(np.int64)), rr.TimeColumn("time", timestamp=t_s)]
        cols = rr.TextLog.columns(text=texts, level=[level] * len(texts))
        self.rec.send_columns(entity, indexes=idx, columns=cols)

    def flush(self) -> bool:
        self.rec.flush()
        return True

    def close(self) -> None:
        self.rec.flush()
        self.rec.disconnect()
