"""The one module that talks to rerun: entity paths by role, the blueprint, and .rrd readers.

Entity paths (``<arm>`` an arm id, ``<joint>`` a joint name, both escaped for rerun)::

    /slave/<arm>/joints/<joint>/measured   Scalars      rad, from slave/<arm>/measured_js
    /slave/<arm>/joints/<joint>/setpoint   Scalars      rad, from slave/<arm>/servo_jp
    /slave/<arm>/tip                       LineStrips3D + Points3D  measured_cp trail + current, m
    /slave/<arm>/target                    LineStrips3D + Points3D  setpoint_cp trail + current, m
    /slave/<arm>/links                     LineStrips3D + Points3D  fk_frames of measured joints, m
    /slave/<arm>/state                     TextLog      operating_state changes
    /safety/<arm>/state                    TextLog      watchdog state changes
    /safety/<arm>/latency/p50_ms|p90_ms|p99_ms  Scalars  command-path latency (watchdog, 1 s window)
    /safety/<arm>/scale                    Scalars      motion-scale factor from the watchdog
    /master/<arm>/tip                      LineStrips3D + Points3D  master measured_cp, master frame
    /master/<arm>/clutch                   Scalars      1 while the clutch pedal is pressed
    /events                                TextLog      every SafetyEvent
    /world/trocar                          Points3D     static, (0.5, 0, 0.2) m

The slave side lives in the slave base frame (+z up) and is shown in the "slave" 3D view together
with ``/world``. The master pose is in the master device's own frame, which has no fixed relation
to the slave base (the mapping applies a clutch offset and a scale), so ``/master`` gets its own
3D view instead of being drawn at a made-up offset.

Two timelines: ``source_time`` (the header stamp of the message, wall clock at the publisher) and
``receive_time`` (wall clock when the mirror received it). rerun is imported lazily, inside the
functions and classes that use it.
"""

from __future__ import annotations

import functools
import logging
import socket
import urllib.parse
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt

log = logging.getLogger(__name__)

#: Trocar (remote centre of motion) in the slave base frame, m.
TROCAR_M = (0.5, 0.0, 0.2)

SLAVE_COLOR = (80, 160, 255)
TARGET_COLOR = (255, 170, 40)
LINK_COLOR = (200, 200, 200)
MASTER_COLOR = (120, 220, 120)
TROCAR_COLOR = (255, 60, 60)

_LEVELS = {"info": "INFO", "warning": "WARN", "error": "ERROR"}


# --------------------------------------------------------------------------- entity paths


def _part(name: str) -> str:
    import rerun as rr

    out: str = rr.escape_entity_path_part(name)
    return out


@functools.lru_cache(maxsize=4096)
def joint_path(arm: str, joint: str, kind: str) -> str:
    """``/slave/<arm>/joints/<joint>/<kind>``, kind ``measured`` or ``setpoint``."""
    return f"/slave/{_part(arm)}/joints/{_part(joint)}/{kind}"


@functools.lru_cache(maxsize=4096)
def slave_path(arm: str, leaf: str) -> str:
    """``/slave/<arm>/<leaf>`` (``tip``, ``target``, ``links``, ``state``)."""
    return f"/slave/{_part(arm)}/{leaf}"


@functools.lru_cache(maxsize=4096)
def master_path(arm: str, leaf: str) -> str:
    """``/master/<arm>/<leaf>`` (``tip``, ``clutch``)."""
    return f"/master/{_part(arm)}/{leaf}"


@functools.lru_cache(maxsize=4096)
def safety_path(arm: str) -> str:
    """``/safety/<arm>/state``."""
    return f"/safety/{_part(arm)}/state"


EVENTS_PATH = "/events"
TROCAR_PATH = "/world/trocar"


def viewer_url(grpc_uri: str, web_port: int) -> str:
    """Web viewer URL that opens ``grpc_uri``, the form rerun itself prints.

    >>> viewer_url("rerun+http://127.0.0.1:9876/proxy", 9090)
    'http://localhost:9090/?url=rerun%2Bhttp://127.0.0.1:9876/proxy'
    """
    return f"http://localhost:{web_port}/?url={urllib.parse.quote(grpc_uri, safe=':/')}"


def blueprint() -> Any:
    """Layout: slave + world 3D, master 3D, joint plots, state and event logs."""
    import rerun.blueprint as rrb

    return rrb.Blueprint(
        rrb.Horizontal(
            rrb.Vertical(
                rrb.Spatial3DView(name="slave", origin="/", contents=["/slave/**", "/world/**"]),
                rrb.Spatial3DView(name="master", origin="/master"),
                row_shares=[3, 1],
            ),
            rrb.Vertical(
                rrb.TimeSeriesView(name="joints [rad]", origin="/slave"),
                rrb.TimeSeriesView(name="clutch", origin="/master"),
                rrb.TimeSeriesView(name="latency [ms] / scale", origin="/safety"),
                rrb.TextLogView(name="state", contents=["/slave/**", "/safety/**"]),
                rrb.TextLogView(name="events", origin=EVENTS_PATH),
                row_shares=[4, 1, 1, 2, 2],
            ),
            column_shares=[3, 2],
        ),
        rrb.TimePanel(timeline="source_time"),
        collapse_panels=True,
    )


def _check_port_free(host: str, port: int, name: str) -> None:
    with socket.socket() as s:
        s.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)  # like the server; TIME_WAIT ok
        try:
            s.bind((host, port))
        except OSError as exc:
            raise ConnectionError(f"{name} {host}:{port} is not available: {exc}") from exc


def _ts(ns: npt.ArrayLike) -> npt.NDArray[np.datetime64]:
    return np.asarray(ns, dtype=np.int64).astype("datetime64[ns]")


class RerunView:
    """A rerun recording with typed drawing calls; one instance per process, one thread uses it.

    Args:
        application_id: rerun application id.
        recording_id: rerun recording id ("" → random); equal ids merge processes' data.
        save: path of an .rrd to write ("" → none).
        serve: host a gRPC server on 127.0.0.1:``grpc_port`` and the web viewer on ``web_port``.
    """

    def __init__(
        self,
        application_id: str,
        recording_id: str = "",
        *,
        save: str = "",
        serve: bool = False,
        web_port: int = 9090,
        grpc_port: int = 9876,
    ) -> None:
        import rerun as rr

        self._rr = rr
        self.url = ""
        self._styled: set[str] = set()
        self._rec: Any = rr.RecordingStream(application_id, recording_id=recording_id or None)
        self._rec.set_log_tick_enabled(False)
        self._rec.set_log_time_enabled(False)
        sinks: list[Any] = []
        if save:
            Path(save).parent.mkdir(parents=True, exist_ok=True)
            sinks.append(rr.FileSink(save))
        if serve:
            _check_port_free("127.0.0.1", grpc_port, "grpc_port")  # rerun only logs this failure
            server = rr.GrpcServerSink(bind_ip="127.0.0.1", port=grpc_port)
            sinks.append(server)
        self._rec.set_sinks(*sinks)
        if serve:
            try:
                rr.serve_web_viewer(web_port=web_port, open_browser=False, connect_to=server.uri)
            except RuntimeError as exc:
                self._rec.disconnect()
                raise ConnectionError(f"rerun web viewer on port {web_port}: {exc}") from exc
            self.url = viewer_url(server.uri, web_port)
        self._rec.send_blueprint(blueprint(), make_active=True, make_default=True)
        self._rec.log("/", rr.ViewCoordinates.RIGHT_HAND_Z_UP, static=True)
        self._rec.log(
            TROCAR_PATH,
            rr.Points3D([TROCAR_M], colors=[TROCAR_COLOR], radii=[0.008], labels=["trocar"]),
            static=True,
        )
        self._rec.log("/master", rr.ViewCoordinates.RIGHT_HAND_Z_UP, static=True)

    # -- high-rate series: one send_columns per entity and call --------------------------
    def series(
        self,
        path: str,
        source_ns: npt.ArrayLike,
        receive_ns: npt.ArrayLike,
        values: npt.NDArray[np.float64],
    ) -> None:
        """Scalar samples ``values`` (N,) at the given stamps, in one block."""
        rr = self._rr
        self._rec.send_columns(
            path,
            indexes=[
                rr.TimeColumn("source_time", timestamp=_ts(source_ns)),
                rr.TimeColumn("receive_time", timestamp=_ts(receive_ns)),
            ],
            columns=rr.Scalars.columns(scalars=values),
        )

    def joints(
        self,
        arm: str,
        kind: str,
        names: Sequence[str],
        source_ns: npt.ArrayLike,
        receive_ns: npt.ArrayLike,
        positions: npt.NDArray[np.float64],
    ) -> None:
        """Joint positions (N, J) [rad] → one block per joint entity."""
        rr = self._rr
        indexes = [
            rr.TimeColumn("source_time", timestamp=_ts(source_ns)),
            rr.TimeColumn("receive_time", timestamp=_ts(receive_ns)),
        ]
        for j, name in enumerate(names):
            self._rec.send_columns(
                joint_path(arm, name, kind),
                indexes=indexes,
                columns=rr.Scalars.columns(scalars=positions[:, j]),
            )

    # -- drawn at draw_hz -----------------------------------------------------------------
    def _at(self, source_ns: int, receive_ns: int) -> None:
        self._rec.set_time("source_time", timestamp=np.datetime64(source_ns, "ns"))
        self._rec.set_time("receive_time", timestamp=np.datetime64(receive_ns, "ns"))

    def _style(self, path: str, color: tuple[int, int, int], line_radius: float, point_radius: float) -> None:
        """Colours and radii once, static: per-tick logs then carry only positions."""
        if path in self._styled:
            return
        self._styled.add(path)
        rr = self._rr
        self._rec.log(
            path,
            rr.LineStrips3D.from_fields(colors=[color], radii=[line_radius]),
            rr.Points3D.from_fields(colors=[color], radii=[point_radius]),
            static=True,
        )

    def trail(
        self,
        path: str,
        source_ns: int,
        receive_ns: int,
        points: npt.NDArray[np.float64],
        color: tuple[int, int, int],
    ) -> None:
        """A polyline through ``points`` (N, 3) [m] plus a dot at the last one."""
        rr = self._rr
        self._style(path, color, 0.0015, 0.005)
        self._at(source_ns, receive_ns)
        self._rec.log(
            path,
            rr.LineStrips3D.from_fields(strips=[points]),
            rr.Points3D.from_fields(positions=points[-1:]),
        )

    def links(self, arm: str, source_ns: int, receive_ns: int, points: npt.NDArray[np.float64]) -> None:
        """The arm as a polyline through its link points (7, 3) [m], joints as dots."""
        rr = self._rr
        path = slave_path(arm, "links")
        self._style(path, LINK_COLOR, 0.006, 0.012)
        self._at(source_ns, receive_ns)
        self._rec.log(
            path,
            rr.LineStrips3D.from_fields(strips=[points]),
            rr.Points3D.from_fields(positions=points),
        )

    def text(self, path: str, source_ns: int, receive_ns: int, text: str, severity: str) -> None:
        """One TextLog line; ``severity`` info / warning / error."""
        self._at(source_ns, receive_ns)
        self._rec.log(path, self._rr.TextLog(text, level=_LEVELS.get(severity, "ERROR")))

    def close(self) -> None:
        """Flush everything to the sinks and close them (the .rrd is complete after this)."""
        self._rec.flush(timeout_sec=10.0)
        self._rec.disconnect()


# --------------------------------------------------------------------------- reading an .rrd


def _chunks(path: str | Path) -> Any:
    from rerun.chunk import RrdReader

    return RrdReader(str(path)).stream()


def entity_paths(path: str | Path) -> set[str]:
    """Every entity path with data in the first recording of an .rrd (properties excluded)."""
    return {c.entity_path for c in _chunks(path) if not c.entity_path.startswith("/__")}


def scalar_counts(path: str | Path) -> dict[str, int]:
    """Number of Scalars rows per entity path in an .rrd."""
    counts: dict[str, int] = {}
    for c in _chunks(path):
        names = c.to_record_batch().schema.names
        if any(n.startswith("Scalars:") for n in names):
            counts[c.entity_path] = counts.get(c.entity_path, 0) + c.num_rows
    return counts


def text_logs(path: str | Path) -> list[tuple[str, str, str]]:
    """``(entity_path, level, text)`` of every TextLog row in an .rrd, in file order."""
    out: list[tuple[str, str, str]] = []
    for c in _chunks(path):
        batch = c.to_record_batch()
        names = batch.schema.names
        if "TextLog:text" not in names:
            continue
        texts = batch.column("TextLog:text").to_pylist()
        levels = (
            batch.column("TextLog:level").to_pylist() if "TextLog:level" in names else [None] * len(texts)
        )
        for t, lv in zip(texts, levels, strict=True):
            for i, line in enumerate(t or []):
                level = lv[i] if lv and i < len(lv) else ""
                out.append((c.entity_path, str(level or ""), str(line)))
    return out
