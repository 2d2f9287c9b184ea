"""The one module that talks to rerun: entity paths by role, the blueprint, the recording stream.

Entity paths (``<arm>`` an arm id, ``<joint>`` a joint name, both escaped for rerun)::

    /slave/<arm>/joints/measured           Scalars       rad (m: prismatic), slave/<arm>/measured_js: one
                                                         row per sample, instance i = joint i (a series
                                                         each, named and coloured by a static
                                                         SeriesLines on the entity)
    /slave/<arm>/joints/setpoint           Scalars       rad (m), slave/<arm>/servo_jp, likewise
    /slave/geometry/<robot>                Boxes3D + Ellipsoids3D + Capsules3D + Cylinders3D
                                                         every primitive geom of the robot's MuJoCo
                                                         model, one archetype per kind on one entity:
                                                         sizes and colours static, world poses (m)
                                                         per drawn frame, posed by mj_kinematics at
                                                         the measured joints
    /slave/geometry/<robot>/mesh/<body>/<i>  Mesh3D      a mesh geom (static, in its body's frame, the
                                                         implicit frame of .../mesh/<body>)
    /slave/body_poses                      Transform3D   the pose (world frame, m) of each body with
                                                         meshes: a row per moved body, child_frame its
                                                         frame (none for the built-in robots)
    /slave/<arm>/links                     LineStrips3D + Points3D  the arm's kinematic chain (from
                                                         measured_js: mh3f base→flange, vip R–E–W,
                                                         plas port→DH chain), m — only where the
                                                         robot's geometry is not drawn
    /slave/<arm>/forceps                   LineStrips3D  the instrument (mh3f flange→forceps tip,
                                                         plas pitch axis→tip), m — likewise
    /slave/<arm>/tip                       LineStrips3D + Points3D  measured_cp trail + current, m
    /slave/<arm>/target                    LineStrips3D + Points3D  setpoint_cp trail + current, m
    /slave/<arm>/trocar                    Points3D      operating_state.trocar (on change), m
    /slave/<arm>/rcm                       Points3D      remote centre of motion: vip R; mh3f the
                                                         point of the forceps axis nearest the trocar
                                                         (trocar mode only), m
    /slave/<arm>/vip                       Points3D      VIP from the mapping's "vip" events, m
    /slave/<arm>/tip_error_mm              Scalars       |tip(servo_jp) − tip(measured_js)|, mm
    /slave/<arm>/rcm_error_mm              Scalars       operating_state.rcm_error_mm (trocar mode)
    /slave/<arm>/state                     TextLog       operating_state changes (state, mode, follow)
    /safety/<arm>/state                    TextLog       watchdog state changes
    /safety/<arm>/latency_ms               Scalars       command-path latency (watchdog, 1 s window):
                                                         instances p50, p90, p99
    /safety/<arm>/scale                    Scalars       motion-scale factor from the watchdog
    /master/<arm>/tip                      LineStrips3D + Points3D  master measured_cp, master frame
    /master/<arm>/clutch                   Scalars       1 while the clutch pedal is pressed
    /mapping/<arm>/teleop                  TextLog       the mapping's teleop state of the pair driving
                                                         slave <arm>: every change (state, was, reason,
                                                         scales), mapping/<arm>/teleop_state
    /mapping/<arm>/engaged                 Scalars       1 while that state is ENABLED (the slave follows)
    /events                                TextLog       every SafetyEvent

The slave side is drawn in the slave's world frame (mh3f: the base frame; plas and vip: the port
frame, +z up) in the "slave" 3D view. The master pose is in the master device's own frame, which
has no fixed relation to the slave's (the mapping applies a clutch offset and a scale), so
``/master`` gets its own 3D view instead of being drawn at a made-up offset.

The layout (:func:`blueprint`) is sent once, when the slave arms are known; ``lean`` (the live
mirror's default) keeps the slave 3D view, the joint plots and the text log; ``full``::

    ┌───────────────────────────────┬─────────────────────────────────────────┐
    │ slave 3D (/slave/**)          │ <arm> joints: measured vs setpoint (one │
    │  robot bodies, trocar/RCM/    │ plot per arm, side by side)             │
    │  VIP, tip + target trails     ├─────────────────────────────────────────┤
    │                               │ tip / RCM error [mm]                    │
    │                               ├────────────────────┬────────────────────┤
    ├───────────────┬───────────────┤ latency [ms]       │ scale, clutch      │
    │ slave tip and │ master tip    ├────────────────────┴────────────────────┤
    │ target trails │ (/master/**)  │ modes & safety events (text log)        │
    └───────────────┴───────────────┴─────────────────────────────────────────┘

Every entity is one message per send to the viewer (a block of scalars, or the rows the batcher
gathered in ``flush_s``), and the web viewer takes in a bounded amount each frame: its pace is set
by the rows (and messages) a second and its frame rate (docs/performance.md). Hence one entity
per robot for all its primitives (posed in the world frame: a Transform3D row naming a frame
costs the viewer far more), one per arm for all its joints, one for the three latency
quantiles, no stick figure where the robot's bodies are drawn, and the mirror's lower rates
while it serves the viewer.

Time series show the last ``plot_window_s`` before the time cursor. Two timelines:
``source_time`` (the header stamp of the message, wall clock at the publisher) and
``receive_time`` (wall clock when the mirror received it). rerun is imported lazily, inside the
functions and classes that use it.
"""

from __future__ import annotations

import contextlib
import functools
import logging
import signal
import socket
import subprocess
import time
from collections.abc import Callable, Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt
from telesurg.services.common import check_port_free
from telesurg.services.mirror.geometry import KINDS, Body, Primitive, quat_matrix
from telesurg.shared.session import die_with_parent
from telesurg.shared.viewer import viewer_url

log = logging.getLogger(__name__)

Color = tuple[int, int, int]

SLAVE_COLOR: Color = (80, 160, 255)
TARGET_COLOR: Color = (255, 170, 40)
LINK_COLOR: Color = (200, 200, 200)
FORCEPS_COLOR: Color = (250, 230, 90)
MASTER_COLOR: Color = (120, 220, 120)
TROCAR_COLOR: Color = (255, 60, 60)
RCM_COLOR: Color = (255, 80, 220)
VIP_COLOR: Color = (60, 230, 230)
#: Joint colours in plots (joint i takes entry i mod len); setpoints are drawn paler and thinner.
JOINT_COLORS: tuple[Color, ...] = (
    (228, 26, 28),
    (55, 126, 184),
    (77, 175, 74),
    (152, 78, 163),
    (255, 127, 0),
    (166, 86, 40),
    (247, 129, 191),
    (120, 120, 120),
)

#: Background of the lean layout's 3D view (a flat grey: the robot's blue and the trails stand out).
PLAIN_BACKGROUND: Color = (236, 236, 236)

_LEVELS = {"info": "INFO", "warning": "WARN", "error": "ERROR"}


# --------------------------------------------------------------------------- entity paths


def _part(name: str) -> str:
    import rerun as rr

    out: str = rr.escape_entity_path_part(name)
    return out


@functools.lru_cache(maxsize=4096)
def joints_path(arm: str, kind: str) -> str:
    """``/slave/<arm>/joints/<kind>``, kind ``measured`` or ``setpoint``: every joint of the arm,
    instance i = joint i."""
    return f"/slave/{_part(arm)}/joints/{kind}"


@functools.lru_cache(maxsize=4096)
def slave_path(arm: str, leaf: str) -> str:
    """``/slave/<arm>/<leaf>`` (``tip``, ``target``, ``links``, ``forceps``, ``state``, ...)."""
    return f"/slave/{_part(arm)}/{leaf}"


@functools.lru_cache(maxsize=4096)
def master_path(arm: str, leaf: str) -> str:
    """``/master/<arm>/<leaf>`` (``tip``, ``clutch``)."""
    return f"/master/{_part(arm)}/{leaf}"


@functools.lru_cache(maxsize=4096)
def safety_path(arm: str, leaf: str = "state") -> str:
    """``/safety/<arm>/<leaf>`` (``state``, ``scale``, ``latency_ms``, ...)."""
    return f"/safety/{_part(arm)}/{leaf}"


@functools.lru_cache(maxsize=4096)
def mapping_path(arm: str, leaf: str) -> str:
    """``/mapping/<arm>/<leaf>`` (``teleop``, ``engaged``) of the pair driving slave ``arm``."""
    return f"/mapping/{_part(arm)}/{leaf}"


EVENTS_PATH = "/events"
#: Leaf of ``/safety/<arm>/…``: the watchdog's latency quantiles, one entity (instances p50, p90, p99).
LATENCY = "latency_ms"
LATENCY_QUANTILES = ("p50", "p90", "p99")


#: The pose of each robot body with meshes, in one entity: Transform3D rows, each naming its body's
#: frame as ``child_frame`` (the implicit frame of :func:`mesh_path`, so its meshes follow). The
#: primitive geoms are not posed this way: they are sent posed in the world frame, a few entities a
#: frame (:meth:`RerunView.primitive_poses`) — the web viewer takes in a Transform3D row naming a
#: frame at a cost that kept it from live at 10 frames a second of 7 bodies, where the same scene as
#: posed primitives, 30 messages a second, kept up (docs/performance.md).
BODY_POSES = "/slave/body_poses"
#: The parent of every robot's geometry entities (:func:`geometry_path`).
GEOMETRY_ROOT = "/slave/geometry"
#: The frame body poses are given in: ``GEOMETRY_ROOT``'s implicit frame (the slave world frame).
GEOMETRY_FRAME = f"tf#{GEOMETRY_ROOT}"


@functools.lru_cache(maxsize=4096)
def geometry_path(robot: str) -> str:
    """``/slave/geometry/<robot>``: every primitive geom of a robot's MuJoCo model, one archetype
    per kind on this one entity (one message a drawn frame for the viewer to take in)."""
    return f"{GEOMETRY_ROOT}/{_part(robot)}"


@functools.lru_cache(maxsize=4096)
def mesh_path(robot: str, body: str) -> str:
    """``/slave/geometry/<robot>/mesh/<body>``: a robot body with meshes (children ``<i>``, static in
    its frame; its pose a row of :data:`BODY_POSES` naming this entity's implicit frame)."""
    return f"{GEOMETRY_ROOT}/{_part(robot)}/mesh/{_part(body)}"


def _window(seconds: float) -> list[Any]:
    """Visible time ranges: the last ``seconds`` before the cursor, on both timelines."""
    import rerun.blueprint as rrb

    start = rrb.TimeRangeBoundary.cursor_relative(seconds=-seconds)
    end = rrb.TimeRangeBoundary.cursor_relative(seconds=0.0)
    return [rrb.VisibleTimeRange(t, start=start, end=end) for t in ("source_time", "receive_time")]


def _time_panel() -> Any:
    """The time panel: the ``source_time`` timeline, **following** — the time cursor stays on the
    newest data the viewer has (not playing at 1× from where it started). rerun 0.41's viewer
    already follows a live stream by default; saying so in the blueprint keeps it so for every
    viewer the layout reaches (a late one included) whatever the viewer's own default."""
    import rerun.blueprint as rrb

    return rrb.TimePanel(timeline="source_time", play_state="following")


#: Blueprint overrides: entity path → SeriesLines (rerun types its keys as EntityPath | str).
_Overrides = dict[Any, Any]


def _lines(name: str, color: Color, width: float) -> Any:
    import rerun as rr

    return rr.SeriesLines.from_fields(names=[name], colors=[color], widths=[width])


#: Layouts of :func:`blueprint`: ``lean`` (the default) and ``full`` (module docstring).
LAYOUTS = ("lean", "full")


def blueprint(
    slave_arms: Mapping[str, Sequence[str]] | None = None, plot_window_s: float = 20.0, layout: str = "full"
) -> Any:
    """The layout drawn in the module docstring: one joint plot per slave arm (``slave_arms``:
    arm → joint names; none: one plot of everything under ``/slave``). Series names, colours and
    widths are blueprint overrides, so the recording holds only the samples. ``lean``: the slave
    3D view, the joint plots and the text log only (fewer views for the viewer to draw each frame;
    the other entities are in the recording, a view away)."""
    import rerun.blueprint as rrb

    if layout not in LAYOUTS:
        raise ValueError(f"layout {layout!r}: valid: {', '.join(LAYOUTS)}")

    arms = dict(slave_arms or {})
    window = _window(plot_window_s)
    joints = [  # series names and colours: static on each entity (RerunView.joints)
        rrb.TimeSeriesView(
            name=f"{arm} joints: measured vs setpoint [rad | m]",
            origin=slave_path(arm, "joints"),
            time_ranges=window,
        )
        for arm in arms
    ]
    if not joints:
        joints.append(rrb.TimeSeriesView(name="slave joints [rad | m]", origin="/slave", time_ranges=window))
    events = rrb.TextLogView(
        name="modes & safety events", contents=["/slave/**", "/mapping/**", "/safety/**", EVENTS_PATH]
    )
    if layout == "lean":
        # a plain background and no ground grid: both are shaded per pixel every frame, which
        # under software WebGL is most of a frame's cost (docs/performance.md)
        slave_3d = rrb.Spatial3DView(
            name="slave (world frame, m)",
            origin="/",
            contents=["+ /slave/**"],
            background=rrb.Background(kind=rrb.BackgroundKind.SolidColor, color=PLAIN_BACKGROUND),
            line_grid=rrb.LineGrid3D(visible=False),
        )
        return rrb.Blueprint(
            rrb.Horizontal(
                slave_3d,
                rrb.Vertical(
                    rrb.Horizontal(*joints) if len(joints) > 1 else joints[0], events, row_shares=[3, 2]
                ),
                column_shares=[3, 2],
            ),
            _time_panel(),
            collapse_panels=True,
        )
    slave_3d = rrb.Spatial3DView(name="slave (world frame, m)", origin="/", contents=["+ /slave/**"])
    errors: _Overrides = {}
    scale: _Overrides = {}
    for i, arm in enumerate(arms):
        errors[slave_path(arm, "tip_error_mm")] = _lines(
            f"{arm} tip", JOINT_COLORS[2 * i % len(JOINT_COLORS)], 1.5
        )
        errors[slave_path(arm, "rcm_error_mm")] = _lines(
            f"{arm} RCM", JOINT_COLORS[(2 * i + 1) % len(JOINT_COLORS)], 1.5
        )
        scale[safety_path(arm, "scale")] = _lines(f"{arm} scale", JOINT_COLORS[i % len(JOINT_COLORS)], 1.5)
        scale[mapping_path(arm, "engaged")] = _lines(
            f"{arm} engaged", JOINT_COLORS[(i + 3) % len(JOINT_COLORS)], 1.5
        )
    # the trails alone: the camera fits them, not the whole arm (a 2 cm circle on a 1 m arm)
    tips = [slave_path(a, leaf) for a in arms for leaf in ("tip", "target", "vip")] or ["/slave/**"]
    right = rrb.Vertical(
        rrb.Horizontal(*joints) if len(joints) > 1 else joints[0],
        rrb.TimeSeriesView(
            name="tip / RCM error [mm]",
            contents=list(errors) or ["/slave/**"],
            time_ranges=window,
            overrides=errors,
        ),
        rrb.Horizontal(
            rrb.TimeSeriesView(  # p50 / p90 / p99: instances of one entity, named on it
                name="latency [ms]",
                contents=[safety_path(arm, LATENCY) for arm in arms] or ["/safety/**"],
                time_ranges=window,
            ),
            rrb.TimeSeriesView(
                name="motion scale, clutch",
                contents=[*scale, "/master/**", "/mapping/**"],
                time_ranges=window,
                overrides=scale,
            ),
        ),
        events,
        row_shares=[3, 2, 2, 2],
    )
    return rrb.Blueprint(
        rrb.Horizontal(
            rrb.Vertical(
                slave_3d,
                rrb.Horizontal(
                    rrb.Spatial3DView(name="slave tip (blue) and target (orange)", origin="/", contents=tips),
                    rrb.Spatial3DView(name="master tip (device frame)", origin="/master"),
                ),
                row_shares=[3, 2],
            ),
            right,
            column_shares=[1, 1],
        ),
        _time_panel(),
        collapse_panels=True,
    )


def _ts(ns: npt.ArrayLike) -> npt.NDArray[np.datetime64]:
    return np.asarray(ns, dtype=np.int64).astype("datetime64[ns]")


def _paler(c: Color) -> Color:
    r, g, b = (round(0.55 * v + 0.45 * 255) for v in c)
    return (r, g, b)


#: Radii in UI points (rerun: negative = points on screen), so arms of 5 cm (PLAS) and of 1 m
#: (MH3F) are drawn alike.
_THIN, _LINE, _THICK, _DOT, _BIG_DOT = -1.0, -1.5, -3.0, -3.0, -6.0


def _rerun_binary() -> str:
    """rerun's own executable (``rerun_cli/rerun`` of the rerun-sdk wheel), started directly: the
    ``python -m rerun_cli`` wrapper runs it as a grandchild that outlives a killed mirror."""
    import importlib.util

    spec = importlib.util.find_spec("rerun_cli")
    exe = Path(spec.origin if spec is not None and spec.origin else ".").parent / "rerun"
    if not exe.is_file():
        raise ConnectionError(f"rerun's executable not found at {exe} (rerun-sdk installed without its CLI?)")
    return str(exe)


class RerunView:
    """A rerun recording with typed drawing calls; one instance per process, one thread uses it.

    Every call logs one entity once (``send_columns`` for blocks of scalars); colours and radii of
    3D entities and the names and colours of the joint and latency series are logged once per
    entity, static, so per-tick logs carry only positions and values (the other series' styles are
    in the blueprint).

    Args:
        application_id: rerun application id.
        recording_id: rerun recording id ("" → random); equal ids merge processes' data.
        save: path of an .rrd to write ("" → none).
        serve: host a gRPC server on 127.0.0.1:``grpc_port`` and the web viewer on
            ``web_host``:``web_port`` (a child ``rerun --serve-web --bind``: rerun's own
            ``serve_web_viewer`` listens on every interface).
        history_mb: MB of logged data the gRPC server keeps for a viewer that connects later (the
            oldest dropped first; static data — the robot geometry, styles — stays while the
            limit holds it: at 0.05 MB a late viewer got none of it, at 0.5 MB all of the MH3F's);
            0: rerun's default (1 GiB: a new viewer gets the whole session, from its start).
        flush_s: s between the batcher's sends to the sinks (0: rerun's default, 200 ms).
        rrd_footer: write rerun's footer (a manifest of every chunk, kept in memory until the
            file is closed: memory grows with the session) at the end of ``save``.
    """

    def __init__(
        self,
        application_id: str,
        recording_id: str = "",
        *,
        save: str = "",
        serve: bool = False,
        web_port: int = 9090,
        web_host: str = "127.0.0.1",
        grpc_port: int = 9876,
        history_mb: float = 0.0,
        flush_s: float = 0.0,
        rrd_footer: bool = False,
    ) -> None:
        import rerun as rr

        self._rr = rr
        self.url = ""
        self._web: subprocess.Popen[bytes] | None = None  # the web viewer's server
        self.blueprint_arms: tuple[str, ...] | None = None  # set once the layout is sent
        self._styled: set[str] = set()
        self._series_styles: dict[str, tuple[tuple[str, ...], tuple[Color, ...], float]] = {}
        self._capsule_lengths: dict[str, npt.NDArray[np.float64]] = {}  # robot → its capsules' (m)
        self._flushers: list[Callable[[], None]] = []
        batcher = rr.ChunkBatcherConfig(flush_tick=flush_s) if flush_s > 0 else None
        self._rec: Any = rr.RecordingStream(
            application_id, recording_id=recording_id or None, batcher_config=batcher
        )
        self._rec.set_log_tick_enabled(False)
        self._rec.set_log_time_enabled(False)
        sinks: list[Any] = []
        if save:
            Path(save).parent.mkdir(parents=True, exist_ok=True)
            sinks.append(rr.FileSink(save, write_footer=rrd_footer))
        if serve:
            check_port_free("127.0.0.1", grpc_port, "grpc_port")  # rerun only logs this failure
            limit = f"{history_mb:g}MB" if history_mb > 0 else "1GiB"  # rerun's default
            server = rr.GrpcServerSink(bind_ip="127.0.0.1", port=grpc_port, server_memory_limit=limit)
            sinks.append(server)
        self._rec.set_sinks(*sinks)
        if serve:
            try:
                web_port = self._serve_web_viewer(web_host, web_port, server.uri)
            except ConnectionError:
                self._rec.disconnect()
                raise
            self.url = viewer_url(server.uri, web_port)
        self._rec.log("/", rr.ViewCoordinates.RIGHT_HAND_Z_UP, static=True)
        self._rec.log("/master", rr.ViewCoordinates.RIGHT_HAND_Z_UP, static=True)

    def send_blueprint(
        self, slave_arms: Mapping[str, Sequence[str]], plot_window_s: float = 20.0, layout: str = "full"
    ) -> None:
        """Send the layout (:data:`LAYOUTS`) for these slave arms (arm → joint names), once (later
        calls do nothing)."""
        if self.blueprint_arms is not None:
            return
        self.blueprint_arms = tuple(slave_arms)
        self._rec.send_blueprint(
            blueprint(slave_arms, plot_window_s, layout), make_active=True, make_default=True
        )

    # -- styles, once per entity, static -------------------------------------------------
    def _once(self, path: str) -> bool:
        if path in self._styled:
            return False
        self._styled.add(path)
        return True

    def _style_3d(self, path: str, color: Color, line_radius: float, point_radius: float | None) -> None:
        """Static colour and radii of a LineStrips3D (+ Points3D unless ``point_radius`` is None:
        styling an archetype the entity never logs would make the viewer report it missing)."""
        if self._once(path):
            rr = self._rr
            parts = [rr.LineStrips3D.from_fields(colors=[color], radii=[line_radius])]
            if point_radius is not None:
                parts.append(rr.Points3D.from_fields(colors=[color], radii=[point_radius]))
            self._rec.log(path, *parts, static=True)

    # -- scalars in blocks: one send_columns per entity and call ---------------------------
    def series_style(self, path: str, names: Sequence[str], colors: Sequence[Color], width: float) -> None:
        """Names, colours and width of the series of a scalar entity (instance i: ``names[i]``),
        static on the entity (so a file opened without the layout shows them too); logged again
        only when they change."""
        key = (tuple(names), tuple(colors), width)
        if self._series_styles.get(path) == key:
            return
        self._series_styles[path] = key
        rr = self._rr
        self._rec.log(
            path,
            rr.SeriesLines.from_fields(names=list(names), colors=list(colors), widths=[width] * len(names)),
            static=True,
        )

    def series(
        self,
        path: str,
        source_ns: npt.ArrayLike,
        receive_ns: npt.ArrayLike,
        values: npt.ArrayLike,
    ) -> None:
        """Scalar samples at the given stamps, in one block: ``values`` (N,) one series, or
        (N, K) K series of one entity (instance k = column k)."""
        rr = self._rr
        self._rec.send_columns(
            path,
            indexes=[
                rr.TimeColumn("source_time", timestamp=_ts(source_ns)),
                rr.TimeColumn("receive_time", timestamp=_ts(receive_ns)),
            ],
            columns=rr.Scalars.columns(scalars=np.asarray(values, np.float64)),
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
        """Joint positions (N, J) [rad, m] → one block on the arm's ``kind`` entity (a series per
        joint: measured in the joint's colour, setpoints paler and thinner)."""
        colors = [JOINT_COLORS[j % len(JOINT_COLORS)] for j in range(len(names))]
        if kind == "setpoint":
            colors = [_paler(c) for c in colors]
        path = joints_path(arm, kind)
        self.series_style(path, [f"{n} {kind}" for n in names], colors, 2.0 if kind == "measured" else 1.0)
        self.series(path, source_ns, receive_ns, positions)

    # -- 3D, drawn at draw_hz (latest state only) -----------------------------------------
    def _at(self, source_ns: int, receive_ns: int) -> None:
        self._rec.set_time("source_time", timestamp=np.datetime64(source_ns, "ns"))
        self._rec.set_time("receive_time", timestamp=np.datetime64(receive_ns, "ns"))

    def trail(
        self,
        path: str,
        source_ns: int,
        receive_ns: int,
        points: npt.NDArray[np.float64],
        color: Color,
    ) -> None:
        """A polyline through ``points`` (N, 3) [m] plus a dot at the last one."""
        rr = self._rr
        self._style_3d(path, color, _THIN, _DOT)
        self._at(source_ns, receive_ns)
        self._rec.log(
            path,
            rr.LineStrips3D.from_fields(strips=points),  # an (N, 3) array: one strip (fast path)
            rr.Points3D.from_fields(positions=points[-1:]),
        )

    def arm(
        self,
        arm: str,
        source_ns: int,
        receive_ns: int,
        links: npt.NDArray[np.float64],
        forceps: npt.NDArray[np.float64] | None = None,
    ) -> None:
        """The arm as a polyline through its link points (N, 3) [m], joints as dots; the forceps
        (M, 3) [m] as a thicker polyline of its own."""
        rr = self._rr
        path = slave_path(arm, "links")
        self._style_3d(path, LINK_COLOR, _THICK, _DOT)
        self._at(source_ns, receive_ns)
        self._rec.log(
            path, rr.LineStrips3D.from_fields(strips=links), rr.Points3D.from_fields(positions=links)
        )
        if forceps is not None:
            fpath = slave_path(arm, "forceps")
            self._style_3d(fpath, FORCEPS_COLOR, _THICK, None)
            self._rec.log(fpath, rr.LineStrips3D.from_fields(strips=forceps))

    def robot(
        self, robot: str, primitives: Mapping[str, Sequence[Primitive]], mesh_bodies: Sequence[Body]
    ) -> None:
        """The static geometry of robot ``robot``: on one entity (:func:`geometry_path`), per
        primitive kind (:data:`KINDS`) its archetype with the sizes and colours of all its geoms
        of that kind (their poses come with :meth:`primitive_poses`, in the same order); each body
        with meshes at :func:`mesh_path` in its own frame (its pose with :meth:`body_pose`). Once
        per robot."""
        rr = self._rr
        if not self._once(geometry_path(robot)):
            return
        parts: list[Any] = []
        solid = rr.components.FillMode.Solid
        for kind, prims in primitives.items():
            size = np.asarray([p.size for p in prims])
            colors = [p.rgba for p in prims]
            part: Any
            if kind == "box":
                part = rr.Boxes3D(half_sizes=size, colors=colors, fill_mode=solid)
            elif kind == "ellipsoid":
                part = rr.Ellipsoids3D(half_sizes=size, colors=colors, fill_mode=solid)
            elif kind == "cylinder":
                part = rr.Cylinders3D(radii=size[:, 0], lengths=size[:, 1], colors=colors, fill_mode=solid)
            elif kind == "capsule":
                self._capsule_lengths[robot] = size[:, 1].copy()
                part = rr.Capsules3D(radii=size[:, 0], lengths=size[:, 1], colors=colors, fill_mode=solid)
            else:
                raise ValueError(f"primitive kind {kind!r}: valid: {', '.join(KINDS)}")
            parts.append(part)
        if parts:
            self._rec.log(geometry_path(robot), *parts, static=True)
        for body in mesh_bodies:
            for i, mesh in enumerate(body.meshes):
                self._rec.log(
                    f"{mesh_path(robot, body.name)}/{i}",
                    rr.Mesh3D(
                        vertex_positions=mesh.vertices, triangle_indices=mesh.faces, albedo_factor=mesh.rgba
                    ),
                    static=True,
                )

    def primitive_poses(
        self,
        robot: str,
        source_ns: int,
        receive_ns: int,
        poses: Mapping[str, tuple[npt.NDArray[np.float64], npt.NDArray[np.float64]]],
    ) -> None:
        """Where every primitive geom of ``robot`` is from this time on: kind → (centres (N, 3) [m],
        quaternions w x y z (N, 4)) in the world frame, in the order :meth:`robot` was given them
        (one row of the robot's entity)."""
        rr = self._rr
        self._at(source_ns, receive_ns)
        parts: list[Any] = []
        for kind, (centers, quats_wxyz) in poses.items():
            xyzw = np.roll(np.asarray(quats_wxyz, np.float64), -1, axis=-1)
            part: Any
            if kind == "box":
                part = rr.Boxes3D.from_fields(centers=centers, quaternions=xyzw)
            elif kind == "ellipsoid":
                part = rr.Ellipsoids3D.from_fields(centers=centers, quaternions=xyzw)
            elif kind == "cylinder":
                part = rr.Cylinders3D.from_fields(centers=centers, quaternions=xyzw)
            elif kind == "capsule":  # rerun's starts at its translation and runs along its +z
                axis = np.stack([quat_matrix(q)[:, 2] for q in np.asarray(quats_wxyz, np.float64)])
                start = centers - 0.5 * self._capsule_lengths[robot][:, None] * axis
                part = rr.Capsules3D.from_fields(translations=start, quaternions=xyzw)
            else:
                raise ValueError(f"primitive kind {kind!r}: valid: {', '.join(KINDS)}")
            parts.append(part)
        if parts:
            self._rec.log(geometry_path(robot), *parts)

    def body_pose(
        self,
        robot: str,
        body: str,
        source_ns: int,
        receive_ns: int,
        position: npt.NDArray[np.float64],
        quat_wxyz: npt.NDArray[np.float64],
    ) -> None:
        """The pose of robot body ``body`` with meshes (world frame, m; quaternion w x y z) from this
        time on: a row of :data:`BODY_POSES` naming the body's frame."""
        rr = self._rr
        self._at(source_ns, receive_ns)
        self._rec.log(
            BODY_POSES,
            rr.Transform3D(
                translation=position,
                quaternion=rr.Quaternion(xyzw=np.roll(quat_wxyz, -1)),
                child_frame=f"tf#{mesh_path(robot, body)}",
                parent_frame=GEOMETRY_FRAME,
            ),
        )

    def point(
        self,
        path: str,
        source_ns: int,
        receive_ns: int,
        position: Sequence[float] | npt.NDArray[np.float64],
        color: Color,
        label: str,
    ) -> None:
        """One labelled point [m] (trocar, RCM, VIP)."""
        rr = self._rr
        if self._once(path):
            self._rec.log(
                path,
                rr.Points3D.from_fields(colors=[color], radii=[_BIG_DOT], labels=[label]),
                static=True,
            )
        self._at(source_ns, receive_ns)
        self._rec.log(path, rr.Points3D.from_fields(positions=np.asarray(position, np.float64).reshape(1, 3)))

    def hide_point(self, path: str, source_ns: int, receive_ns: int) -> None:
        """No point at ``path`` from this time on (e.g. the RCM when leaving trocar mode); its
        static style stays for the next :meth:`point`."""
        self._at(source_ns, receive_ns)
        self._rec.log(path, self._rr.Points3D.from_fields(positions=np.empty((0, 3))))

    def text(self, path: str, source_ns: int, receive_ns: int, text: str, severity: str) -> None:
        """One TextLog line; ``severity`` info / warning / error."""
        self._at(source_ns, receive_ns)
        self._rec.log(path, self._rr.TextLog(text, level=_LEVELS.get(severity, "ERROR")))

    def image(self, camera: str, source_ns: int, receive_ns: int, jpeg: bytes) -> None:
        """One camera frame at ``/camera/<cam>/image``, as the encoded JPEG (rerun decodes it)."""
        self._at(source_ns, receive_ns)
        self._rec.log(
            f"/camera/{_part(camera)}/image", self._rr.EncodedImage(contents=jpeg, media_type="image/jpeg")
        )

    def send_now(self) -> None:
        """Hand what was logged since the batcher's last send to the sinks now, without waiting
        for it (the same messages as at the batcher's next tick, up to ``flush_s`` sooner)."""
        self._rec.flush(timeout_sec=0.0)

    def add_flusher(self, flush: Callable[[], None]) -> None:
        """Have :meth:`close` call ``flush()`` first (a drawer's buffered samples reach the sinks)."""
        self._flushers.append(flush)

    def _serve_web_viewer(self, host: str, port: int, uri: str) -> int:
        """Serve rerun's web viewer (static files; its data comes from ``uri``) on ``host:port``
        from a child ``rerun --serve-web --bind HOST`` (ended with this process: SIGKILL when its
        parent dies); the port it serves on (``port`` 0: a free one)."""
        if port == 0:
            with socket.socket() as s:
                s.bind((host, 0))
                port = int(s.getsockname()[1])
        check_port_free(host, port, "web_port")
        argv = [_rerun_binary(), "--serve-web", "--bind", host]
        argv += ["--web-viewer-port", str(port), uri]
        self._web = subprocess.Popen(
            argv,
            stdout=subprocess.DEVNULL,
            stderr=subprocess.DEVNULL,
            preexec_fn=functools.partial(die_with_parent, signal.SIGKILL),
        )
        deadline = time.monotonic() + 30.0
        while time.monotonic() < deadline and self._web.poll() is None:
            with contextlib.suppress(OSError), socket.create_connection((host, port), timeout=0.2):
                return port
            time.sleep(0.1)
        self._stop_web()
        raise ConnectionError(f"rerun web viewer on {host}:{port} did not start")

    def _stop_web(self) -> None:
        web, self._web = self._web, None
        if web is None:
            return
        web.kill()  # (it serves static files: nothing to save; it outlives a SIGTERM while serving)
        web.wait()

    def close(self) -> None:
        """Send what the drawers still buffer, flush everything to the sinks and close them (the
        .rrd is complete after this); stop the web viewer's server."""
        try:
            for flush in self._flushers:
                flush()
        finally:
            self._rec.flush(timeout_sec=10.0)
        self._rec.disconnect()
        self._stop_web()
