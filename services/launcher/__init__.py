"""``telesurg up``: start a site router and every service on this machine, stop them cleanly.

Each service runs as its own OS process, a zenoh client of the site router on an explicit
loopback endpoint, with its table of the site file ``--config-dir``/site.toml (default: the
packaged ``deploy/local``; docs/deploy.md#site-files). The launcher builds every service's config
first: a missing site file, an unknown key or a wrong type stops it before anything starts.
Once up, it waits for the master's first sample (:data:`MASTER_WAIT_S`) and otherwise stops, naming
the cause (exit 1). Ctrl-C (SIGINT) or SIGTERM stops the services in a safe order — the watchdog
first (it revokes every lease), slave and router last — waits for them, and exits 0 if every
process stopped cleanly. Children also stop by themselves if the launcher dies (they watch their
parent PID).

A secured site (``deploy/slave-site.sh``) gives the router more listeners and its TLS / access
control flags (``--listen``, ``--tls-*``, ``--mtls``, ``--acl``), which go to the router only.
With ``--acl`` the site is locked down (services/launcher/lockdown.py): the loopback endpoint
``--host``:``--port`` is mutual TLS with a local CA made at every start, and each service
connects with its own certificate (``--credentials-dir``); without it, plain TCP.

Examples::

    telesurg up --port 7447 --log-dir out/logs --set mapping.scale=0.3
    telesurg up --config-dir deploy/plas
    telesurg up --seconds 30 --record run.mcap          # a session, recorded from its start
    telesurg up --replay run.mcap --replay-json diff.json   # its master replayed into a fresh site
    telesurg up --site lab --port 7448 --services watchdog,slave_control,mapping \
        --listen tls/0.0.0.0:7447 --tls-ca certs/ca.pem --tls-cert certs/slave-site.pem \
        --tls-key certs/slave-site.key --mtls --acl deploy/slave-site/acl.json5
"""

from __future__ import annotations

import argparse
import contextlib
import functools
import importlib
import importlib.resources
import itertools
import json
import logging
import os
import secrets
import signal
import socket
import subprocess
import sys
import threading
import time
import urllib.parse
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from types import TracebackType
from typing import IO, Any

from telesurg.services.common import (
    STACKS_SIGNAL,
    check_port_free,
    duration_s,
    install_stop_handlers,
    setup_logging,
    tcp_port,
)
from telesurg.shared.auth import default_keys_dir, ensure_keyring
from telesurg.shared.bus import BusConfig, add_bus_args, bus_from_args
from telesurg.shared.config import SITE_FILE, load_config, read_site, site_plugins
from telesurg.shared.errors import ConfigError, SiteStartError, TelesurgError
from telesurg.shared.service_table import ROUTER
from telesurg.shared.service_table import SERVICES as SERVICE_ROWS
from telesurg.shared.timing import (
    BEST_EFFORT_ENV,
    check_slice_us,
    fair_slice_us,
    parse_best_effort_nice,
    set_autogroup_nice,
    set_fair_slice,
    set_normal_priority,
)

log = logging.getLogger("telesurg.launcher")

#: ``telesurg up`` and ``demo`` wait for the master's first sample once the site is up (a serial
#: board resets for ~1.5 s when its port opens).
MASTER_WAIT_S = 15.0
#: The service table (:mod:`telesurg.shared.service_table`): one row per site process.
TABLE = {s.name: s for s in SERVICE_ROWS}
#: Start order (the router first, then these; :data:`ON_REQUEST` last).
SERVICES = tuple(s.name for s in sorted(SERVICE_ROWS, key=lambda s: s.start) if s.start and not s.on_request)
#: Stop order: the console, then the watchdog, whose last word revokes every lease (the slave holds
#: by permission, not on a fault), then the rest; the mirror after the others, to record
#: everything; the router last.
STOP_ORDER = tuple(s.name for s in sorted(SERVICE_ROWS, key=lambda s: s.stop))
#: Started only when asked (``--master web`` / ``--console``), after the others: the web console
#: (``telesurg console --web``), which with ``--master web`` is also the site's master.
ON_REQUEST = tuple(s.name for s in sorted(SERVICE_ROWS, key=lambda s: s.start) if s.on_request)
#: Best-effort services: started at normal priority, they step down to :func:`best_effort_nice`
#: once they are up (``SCHED_IDLE`` and their autogroup's nice; shared/timing.py ``step_down``),
#: so they only get the CPU the control loops and the host's other programs leave; the launcher
#: lifts them back before it asks them to stop, so they can save what they hold.
NICE = tuple(s.name for s in SERVICE_ROWS if s.best_effort)
#: The nice value the best-effort services step down to once up (1..19; 0: they stay at normal
#: priority, level with the host's other programs). ``$TELESURG_BEST_EFFORT_NICE`` overrides.
BEST_EFFORT_NICE = 19
#: Services a site runs without when they cannot start (the camera without OpenGL): the launcher
#: says so and sets the others as :data:`OPTIONAL_OFF` says.
OPTIONAL = tuple(s.name for s in SERVICE_ROWS if s.optional)
#: What a :class:`SiteSpec` starts by default: every service but the optional ones (``telesurg up``
#: and ``demo`` add the camera; a test or bench names it when it wants video).
CONTROL_SERVICES = tuple(s for s in SERVICES if s not in OPTIONAL)
OPTIONAL_OFF = {s.name: {k: list(v) for k, v in s.without.items()} for s in SERVICE_ROWS if s.optional}


#: The control path's processes run at this nice value (all their threads: the loops, zenoh's
#: runtime threads, the Python threads that take the samples), so other programs at normal
#: priority on the host cannot starve them; best-effort work (:data:`NICE`) stays below.
#: Lowering nice needs root or CAP_SYS_NICE (docs/deploy.md); where refused the process runs at
#: nice 0 and the launcher says so. ``$TELESURG_CONTROL_NICE`` overrides (0: leave as is).
CONTROL_NICE = -10
#: A fair-scheduler slice (µs) to ask for every thread of theirs (Linux ≥ 6.12, no privilege
#: needed; :func:`telesurg.shared.timing.set_fair_slice`), so a waking control thread preempts a
#: CPU hog instead of waiting out the hog's slice. 0: the kernel's. Off by default;
#: ``$TELESURG_CONTROL_SLICE_US`` asks for one.
CONTROL_SLICE_US = 0
CONTROL = tuple(s.name for s in SERVICE_ROWS if s.control)
#: The subscribers a control stream waits for at the router (services/router congestion_rules):
#: each gets a zenoh session id of the launcher's (:attr:`SiteSpec.zids`), which the router is told.
#: Every other subscriber (mirror, camera, console, a recorder, anyone) gets control streams as
#: DROP: when it falls behind it loses samples instead of holding them up for these.
ZID_SERVICES = tuple(s.name for s in SERVICE_ROWS if s.zid)


def _new_zid() -> str:
    # 16 hex digits, the first 8-f (zenoh refuses an id written with a leading 0)
    return f"{secrets.randbits(63) | 1 << 63:x}"


def _new_zids() -> dict[str, str]:
    return {name: _new_zid() for name in ZID_SERVICES}


def control_nice() -> int:
    """The nice value for the control processes (``$TELESURG_CONTROL_NICE`` or
    :data:`CONTROL_NICE`)."""
    try:
        return int(os.environ.get("TELESURG_CONTROL_NICE", CONTROL_NICE))
    except ValueError:
        return CONTROL_NICE


def control_slice_us() -> float:
    """The fair-scheduler slice for the control processes, µs (``$TELESURG_CONTROL_SLICE_US``
    or :data:`CONTROL_SLICE_US`; 0: the kernel's default). ConfigError when out of bounds."""
    raw = os.environ.get("TELESURG_CONTROL_SLICE_US", "").strip()
    try:
        us = float(raw) if raw else float(CONTROL_SLICE_US)
    except ValueError:
        raise ConfigError(f"TELESURG_CONTROL_SLICE_US={raw!r}: a number of µs") from None
    check_slice_us(us)
    return us


def best_effort_nice() -> int:
    """The nice value for the best-effort services (``$TELESURG_BEST_EFFORT_NICE`` or
    :data:`BEST_EFFORT_NICE`). ConfigError unless 0..19."""
    return parse_best_effort_nice(os.environ.get(BEST_EFFORT_ENV, ""), BEST_EFFORT_NICE)


def _foreground(slice_us: float = 0.0) -> None:
    """preexec_fn of a control process: :func:`control_nice`, if permitted (else nice 0), and
    the scheduler slice ``slice_us`` (0: the kernel's; :func:`control_slice_us`, read and checked
    by the launcher before the fork), inherited by every thread the process starts."""
    n = control_nice()
    if n:
        with contextlib.suppress(AttributeError, OSError):
            os.setpriority(os.PRIO_PROCESS, 0, n)
        # (its session's autogroup too: each service runs in a session, so an autogroup, of its
        # own, and the CPU is shared between autogroups first — see set_autogroup_nice)
        set_autogroup_nice(0, n)
    set_fair_slice(slice_us)  # a refusal is read back and reported by the launcher


#: service → its ``telesurg`` command
CLI_NAME = {s.name: s.cli for s in SERVICE_ROWS}
#: service → its config class (module, name): the launcher checks each site-file table before it
#: starts anything, so a typo is one error naming the file and key, not a service that dies.
CONFIG_CLASSES = {s.name: (s.module, s.config) for s in SERVICE_ROWS}


def deploy_dir() -> Path:
    """The site folders shipped with the package (``telesurg.deploy``: the checkout's deploy/)."""
    root = importlib.resources.files("telesurg.deploy")
    if not isinstance(root, Path):  # a zipped install: no files to hand to the services
        raise ConfigError(f"the packaged site files are not on the file system ({root})")
    return root


def default_config_dir() -> Path:
    """The packaged ``deploy/local`` site folder."""
    return deploy_dir() / "local"


def config_class(name: str) -> type[Any]:
    """The config dataclass of service ``name`` (imported on demand)."""
    module, cls = CONFIG_CLASSES[name]
    out: type[Any] = getattr(importlib.import_module(module), cls)
    return out


def check_site(site_file: Path | None, services: Sequence[str], overrides: dict[str, list[str]]) -> None:
    """Build the config of each of ``services``, of each service with a table in the site file and
    of each with an override (ConfigError naming the file, table and key); the services validate
    the values themselves when they start."""
    tables = read_site(site_file).tables if site_file is not None else {}
    for name in CONFIG_CLASSES:
        if name in services or name in tables or name in overrides:
            load_config(config_class(name), site_file, overrides.get(name, []), table=name)


def free_port(host: str = "127.0.0.1") -> int:
    """A TCP port free on ``host`` right now."""
    with socket.socket() as s:
        s.bind((host, 0))
        port: int = s.getsockname()[1]
        return port


def wait_port(host: str, port: int, timeout: float) -> bool:
    """True once a TCP connect to host:port succeeds, False after ``timeout`` s."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        try:
            with socket.create_connection((host, port), timeout=0.2):
                return True
        except OSError:
            time.sleep(0.05)
    return False


@dataclass
class SiteSpec:
    """What to start."""

    site: str = "local"  # key prefix telesurg/<site>
    host: str = "127.0.0.1"  # router listen address (loopback for a local site)
    port: int = 7447  # router TCP port
    config_dir: Path | None = None  # site folder holding site.toml (None: every service's defaults)
    services: tuple[str, ...] = CONTROL_SERVICES  # which services to start (the CLIs add the camera)
    overrides: dict[str, list[str]] = field(default_factory=dict)  # service → ["key=value"]
    log_dir: Path | None = None  # per-service log files (None: inherit the terminal)
    log_level: str = "INFO"  # service log level
    # service → endpoint it connects to instead of the router (e.g. through a link impairer)
    connect: dict[str, str] = field(default_factory=dict)
    listen: tuple[str, ...] = ()  # more router endpoints, e.g. tls/0.0.0.0:7447 for remote consoles
    router_flags: tuple[str, ...] = ()  # router-only flags: --tls-ca/--tls-cert/--tls-key/--mtls/--acl
    plugins: tuple[str, ...] = ()  # robot plugin files, passed to every service as --plugin FILE
    # local PKI directory (services/launcher/lockdown.py): the router's local listener is mutual
    # TLS with it and each service connects with its own certificate (None: plain TCP, open)
    local_pki: Path | None = None
    # the site keyring, passed to every service as --keyring DIR; made if absent (None: the default,
    # shared/auth.py default_keys_dir)
    keys_dir: Path | None = None
    # service → a keyring of its own instead (a service that runs as another host's identity, with
    # that host's keyring: the console host's master in a one-machine test of the two-host split)
    service_keys: dict[str, Path] = field(default_factory=dict)
    # zenoh session id of each of ZID_SERVICES (random for each spec, kept over restarts): the
    # router waits for these sessions alone when a control stream's subscriber falls behind
    zids: dict[str, str] = field(default_factory=_new_zids)
    # other ports its services will listen on, as (what, port, hint): checked with the router's
    # before anything starts (check_ports); 0 = a free one, not checked
    ports: tuple[tuple[str, int, str], ...] = ()
    # s to wait, once every service is up, for master_capture's first sample; none by then stops
    # the site with the reason master_capture gave (a refused or silent device). 0: no wait (a
    # test that plugs its device in later); telesurg up / demo: MASTER_WAIT_S
    master_wait_s: float = 0.0
    # record the whole site into this MCAP file (telesurg record), from before any service starts
    # to after every one stopped: a recording a replay can compare from its start (None: none)
    record: Path | None = None

    @property
    def site_file(self) -> Path | None:
        """``config_dir/site.toml``, the file every service reads its table of."""
        return self.config_dir / SITE_FILE if self.config_dir else None

    @property
    def endpoint(self) -> str:
        """Router endpoint, e.g. ``tcp/127.0.0.1:7447`` (``tls/...`` on a locked-down site)."""
        return f"{'tls' if self.local_pki else 'tcp'}/{self.host}:{self.port}"

    def client_bus(self, name: str = "operator") -> BusConfig:
        """Bus config of a client of this site's router: on a locked-down site with the local
        certificate of ``name`` (a service, ``launcher`` or ``operator``)."""
        from telesurg.services.launcher.lockdown import LocalPki

        cfg = BusConfig(connect=[self.endpoint])
        if self.keys_dir is not None:
            cfg.keys_dir = str(self.keys_dir)
        if self.local_pki:
            pki = LocalPki(self.local_pki)
            cfg.tls_root_ca, cfg.tls_cert, cfg.tls_key = str(pki.ca), str(pki.cert(name)), str(pki.key(name))
            cfg.mtls = True
        return cfg


def service_argv(spec: SiteSpec, name: str) -> list[str]:
    """Command line that starts service ``name`` of ``spec``."""
    argv = [sys.executable, "-m", "telesurg.services.cli", CLI_NAME[name], "--site", spec.site]
    argv += ["--log-level", spec.log_level, "--parent-pid", str(os.getpid())]
    if name == ROUTER:
        local = spec.endpoint
        if spec.local_pki:
            from telesurg.services.launcher.lockdown import LocalPki

            local = LocalPki(spec.local_pki).listen_endpoint(spec.host, spec.port)
        for ep in (local, *spec.listen):
            argv += ["--listen", ep]
        argv += spec.router_flags
        if spec.keys_dir is not None:  # (the link guard's events are signed as router)
            argv += ["--keyring", str(spec.keys_dir)]
    else:
        argv += ["--connect", spec.connect.get(name, spec.endpoint)]
        if spec.local_pki:
            from telesurg.services.launcher.lockdown import LocalPki

            argv += LocalPki(spec.local_pki).client_flags(name)
        if (keys := spec.service_keys.get(name, spec.keys_dir)) is not None:
            argv += ["--keyring", str(keys)]
        for plugin in spec.plugins:
            argv += ["--plugin", plugin]
    argv += TABLE[name].args
    if spec.site_file is not None:
        argv += ["--config", str(spec.site_file), "--table", name]
    if name == ROUTER:
        zids = [spec.zids[s] for s in ZID_SERVICES if s in spec.zids and s in spec.services]
        argv += ["--set", f"control_zids={json.dumps(zids)}"]
    elif name in spec.zids:
        argv += ["--set", f"bus.zid={json.dumps(spec.zids[name])}"]
    for item in spec.overrides.get(name, []):
        argv += ["--set", item]
    return argv


class Site:
    """The running processes of a local site; a context manager that always stops them."""

    def __init__(self, spec: SiteSpec) -> None:
        self.spec = spec
        self.procs: dict[str, subprocess.Popen[bytes]] = {}
        self._logs: list[IO[bytes]] = []
        self.off: tuple[str, ...] = ()  # optional services that could not start (OPTIONAL)
        # the web console's one-time login token (made here, handed to it in its environment)
        self.login_token = ""

    def start(self) -> None:
        """Start the router, wait for it, then the services stage by stage (the service table's
        ``start``): a stage's services start together and the next stage once each is on the bus
        (its liveliness token is seen). The master starts after the services that follow it: six
        Python processes importing at once saturate a 2-core host for a second or two, and a
        master engaging then would meet a mapping not yet listening.
        """
        control_slice_us(), best_effort_nice()  # a bad environment stops here, before any start
        if self.spec.keys_dir is None:
            self.spec.keys_dir = default_keys_dir(self.spec.site).resolve()
        keys_dir, made = ensure_keyring(self.spec.keys_dir)
        if made:
            log.info("made the site keyring %s (telesurg keys list shows its identities)", keys_dir)
        # another site's router on the port would answer the readiness probe below, and every
        # service would join that site instead (same site id, same keyring): refuse to start
        router_port = ("the router's port", self.spec.port, "--port 0 picks a free one")
        check_ports(self.spec.host, [router_port, *self.spec.ports])
        self._spawn(ROUTER)
        router = self.procs[ROUTER]
        deadline = time.monotonic() + 15.0
        while router.poll() is None and not self._router_ready():
            if time.monotonic() > deadline:
                raise ConnectionError(f"router did not open {self.spec.endpoint} within 15 s")
        if router.poll() is not None:  # (also when what answered was not this site's router)
            raise ConnectionError(f"router exited with code {router.returncode} (see its log)")
        from telesurg.shared.bus import open_session
        from telesurg.shared.keys import Keys

        keys = Keys(self.spec.site)
        if "camera" in self.spec.services:
            self._camera_first()
        session = open_session(self.spec.client_bus("launcher"))
        try:
            if self.spec.record is not None:
                self._spawn_tool("record", ["record", "--out", str(self.spec.record)])
                if not self._wait_alive(session, keys.alive("record"), 30.0):
                    raise SiteStartError(
                        f"the recorder did not start (exit code {self.procs['record'].poll()})"
                    )
            wait_master = self._watch_master(session)
            names = [n for n in (*SERVICES, *ON_REQUEST) if n in self.spec.services]
            for _stage, group in itertools.groupby(names, key=lambda n: TABLE[n].start):
                stage = list(group)
                for name in stage:  # a stage's services start together, then each must be up
                    self._spawn(name)
                for name in stage:
                    if self._wait_alive(session, keys.alive(name), 30.0):
                        continue
                    rc = self.procs[name].poll()
                    if name in OPTIONAL:
                        self._without(name, rc)
                        continue
                    raise SiteStartError(
                        f"{name} did not come up within 30 s"
                        if rc is None
                        else f"{name} exited with code {rc} before it came up (its log says why)"
                    )
            if wait_master is not None:
                wait_master()
        finally:
            session.close()  # type: ignore[no-untyped-call]
        if self.spec.log_dir:
            pids = {n: p.pid for n, p in self.procs.items()}
            (self.spec.log_dir / "pids.json").write_text(json.dumps(pids, indent=2))

    def _router_ready(self) -> bool:
        """The router accepts connections (on a locked-down site: a full TLS handshake with the
        launcher's certificate, so the router logs no failed handshake for the probe)."""
        if not self.spec.local_pki:
            return wait_port(self.spec.host, self.spec.port, 0.2)
        from telesurg.services.launcher.lockdown import LocalPki
        from telesurg.shared.tlsdiag import TlsFiles, handshake

        pki = LocalPki(self.spec.local_pki)
        files = TlsFiles(str(pki.ca), str(pki.cert("launcher")), str(pki.key("launcher")))
        if handshake(self.spec.host, self.spec.port, files) == "":
            return True
        time.sleep(0.2)
        return False

    def _camera_first(self) -> None:
        """Before anything starts: can the camera run here (a simulated one needs OpenGL and a
        scene with its camera)? If not, the site runs without video and the launcher says why.
        Otherwise the site watches the video it will have (:meth:`_watch_video`); the camera
        itself starts last."""
        spec = self.spec
        cam = load_config(
            config_class("camera"), spec.site_file, spec.overrides.get("camera", []), table="camera"
        )
        why = importlib.import_module(CONFIG_CLASSES["camera"][0]).unavailable(cam)
        if why:
            log.warning("camera is OFF: %s; the site runs without video", why)
            spec.services = tuple(s for s in spec.services if s != "camera")
            for svc, items in OPTIONAL_OFF["camera"].items():
                spec.overrides.setdefault(svc, []).extend(items)
            self.off = (*self.off, "camera")
            return
        self._watch_video(cam.camera)

    def _watch_video(self, camera: str) -> None:
        """A site that runs a camera watches its video: the watchdog's ``video_camera``, the
        mapping's ``camera`` (the view frame) and slave_control's ``camera`` (the ``work`` jog
        frame) name it, unless the site file or ``--set`` says otherwise."""
        spec = self.spec
        for svc, key in (("watchdog", "video_camera"), ("mapping", "camera"), ("slave_control", "camera")):
            if svc not in spec.services:
                continue
            items = spec.overrides.get(svc, [])
            cfg = load_config(config_class(svc), spec.site_file, items, table=svc)
            if getattr(cfg, key) == "" and not any(i.startswith(f"{key}=") for i in items):
                spec.overrides.setdefault(svc, []).append(f"{key}={json.dumps(camera)}")
        log.info("camera %s is on: the watchdog watches its video; mapping, work jogs: its view", camera)

    def _without(self, name: str, rc: int | None) -> None:
        """Go on without optional service ``name`` (it exited or never came up), saying why."""
        p = self.procs.pop(name)
        if p.poll() is None:
            p.kill()
            p.wait()
        where = f"see {self.spec.log_dir / (name + '.log')}" if self.spec.log_dir else "see its log above"
        log.error(
            "%s did not start (exit code %s; %s): the arms hold while the watchdog watches a video "
            'that never comes (watchdog.video_camera="" runs the site without video)',
            name,
            rc,
            where,
        )
        self.off = (*self.off, name)

    def _wait_alive(self, session: object, key: str, timeout: float) -> bool:
        """Poll the liveliness tokens ``key`` until one is present (True) or timeout / exit (False)."""
        from telesurg.shared.keys import Keys

        name = Keys(self.spec.site).service_of_alive(key)
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline and self.procs[name].poll() is None:
            replies = session.liveliness().get(key, timeout=0.5)  # type: ignore[attr-defined]
            if any(r.ok is not None for r in replies):
                return True
            time.sleep(0.05)
        return False

    def _watch_master(self, session: Any) -> Callable[[], None] | None:
        """If ``up`` waits for the master (:attr:`SiteSpec.master_wait_s`): listen, before
        master_capture starts, for its first sample and its ``master_device`` events (why it does
        not publish: a refused board, …); return the wait, which raises SiteStartError naming
        the cause when no sample came in time. None: no wait."""
        from telesurg.shared.keys import Keys
        from telesurg.shared.messages import SafetyEvent, decode

        spec = self.spec
        if "master_capture" not in spec.services or spec.master_wait_s <= 0 or spec.local_pki:
            return None  # (a locked-down site's launcher may only ask for liveliness)
        table = "master_capture"
        cfg = load_config(config_class(table), spec.site_file, spec.overrides.get(table, []), table=table)
        keys = Keys(spec.site)
        got = threading.Event()
        why: list[str] = []

        def on_event(sample: Any) -> None:
            with contextlib.suppress(Exception):  # (read for the message below only)
                msg = decode(bytes(sample.payload))
                if isinstance(msg, SafetyEvent) and msg.kind == "master_device":
                    why.append(msg.text)

        subs = [
            session.declare_subscriber(keys.master(cfg.arm, "measured_cp"), lambda _s: got.set()),
            session.declare_subscriber(keys.events(cfg.service), on_event),
        ]

        def wait() -> None:
            try:
                p = self.procs[table]
                deadline = time.monotonic() + spec.master_wait_s
                while not got.wait(0.1) and time.monotonic() < deadline and p.poll() is None:
                    pass
            finally:
                for sub in subs:
                    with contextlib.suppress(Exception):
                        sub.undeclare()
            if got.is_set():
                return
            where = f"; {spec.log_dir / (table + '.log')}" if spec.log_dir else ""
            if p.poll() is not None:
                raise SiteStartError(
                    f"master_capture exited with code {p.returncode} (its log says why{where})"
                )
            cause = why[-1] if why else "its device gave no reading"
            raise SiteStartError(
                f"master_capture published nothing for master {cfg.arm} within "
                f"{spec.master_wait_s:.0f} s: {cause}{where}"
            )

        return wait

    def _spawn_tool(self, name: str, cli: list[str]) -> subprocess.Popen[bytes]:
        """Start a telesurg tool (``telesurg record …``, ``replay …``) on this site's bus as
        process ``name``: its log in the log folder (or the terminal), ended with the launcher."""
        from telesurg.shared.session import die_with_parent

        spec = self.spec
        argv = [sys.executable, "-m", "telesurg.services.cli", *cli, "--connect", spec.endpoint]
        if spec.keys_dir is not None:
            argv += ["--keyring", str(spec.keys_dir)]
        out: IO[bytes] | None = None
        if spec.log_dir:
            spec.log_dir.mkdir(parents=True, exist_ok=True)
            out = (spec.log_dir / f"{name}.log").open("ab")
            self._logs.append(out)
        p = subprocess.Popen(
            argv,
            stderr=out,
            start_new_session=True,
            preexec_fn=functools.partial(die_with_parent, signal.SIGINT),
        )
        self.procs[name] = p
        log.info("started %-15s pid %d", name, p.pid)
        return p

    def _spawn(self, name: str, table: str = "", extra: Sequence[str] = ()) -> None:
        """Start service ``name`` (an instance of service ``table``, default ``name``; ``extra``
        arguments after its own)."""
        table = table or name
        out: IO[bytes] | None = None
        if self.spec.log_dir:
            self.spec.log_dir.mkdir(parents=True, exist_ok=True)
            out = (self.spec.log_dir / f"{name}.log").open("ab")
            self._logs.append(out)
        argv = [*service_argv(self.spec, table), *extra]
        slice_us = control_slice_us() if table in CONTROL else 0.0
        preexec: Callable[[], None] | None = None
        env: dict[str, str] | None = None
        if table in NICE:  # it only watches: it steps down below the control path once up
            env = {**os.environ, BEST_EFFORT_ENV: str(best_effort_nice())}
        elif table in CONTROL:
            preexec = functools.partial(_foreground, slice_us)
        if name == "console":  # its login token: in the environment, never on the command line
            from telesurg.shared.door import LOGIN_ENV

            self.login_token = secrets.token_urlsafe(32)
            env = {**(env or os.environ), LOGIN_ENV: self.login_token}
        log.debug("starting %s: %s", name, " ".join(argv))
        self.procs[name] = subprocess.Popen(
            argv,
            stdout=out,
            stderr=subprocess.STDOUT if out else None,
            start_new_session=True,
            preexec_fn=preexec,
            env=env,
        )
        pid = self.procs[name].pid
        if table in CONTROL and control_nice():
            try:
                got = os.getpriority(os.PRIO_PROCESS, pid)
            except OSError:  # already gone: its own exit is reported
                got = control_nice()
            if got != control_nice():
                log.warning(
                    "%s runs at nice %d, not %d: lowering nice needs root or CAP_SYS_NICE "
                    "(docs/deploy.md); other programs on this host can starve it",
                    name,
                    got,
                    control_nice(),
                )
        if slice_us:
            try:
                now = fair_slice_us(pid)
            except OSError:  # gone already (reported), or no sched_getattr on this system
                now = slice_us
            if now is not None and abs(now - slice_us) > 1:
                log.warning(
                    "%s has the kernel's %g µs scheduler slice, not %g µs (Linux ≥ 6.12 takes a "
                    "requested slice): a CPU hog can delay its threads' wake-ups by up to that",
                    name,
                    now,
                    slice_us,
                )
        log.info("started %-15s pid %d", name, pid)

    def spawn_instance(self, name: str, table: str, sets: Sequence[str] = ()) -> None:
        """Start another instance ``name`` of service ``table`` (a second master_capture of a
        two-master site: ``service`` and the ``arm`` it reads set in ``sets``), connected where
        ``table`` connects, with ``table``'s settings and ``sets`` after them; stopped with the
        site."""
        extra = ["--set", f"service={json.dumps(name)}", "--set", f"bus.zid={json.dumps(_new_zid())}"]
        for item in sets:
            extra += ["--set", item]
        self._spawn(name, table, extra)

    def restart(self, name: str) -> None:
        """Start ``name`` again (after it died or was killed); the old process must be gone."""
        old = self.procs.get(name)
        if old is not None and old.poll() is None:
            raise RuntimeError(f"{name} (pid {old.pid}) is still running")
        self._spawn(name)

    def pid(self, name: str) -> int:
        """PID of the current ``name`` process."""
        return self.procs[name].pid

    def dead(self) -> dict[str, int]:
        """Services that exited on their own: name → exit code."""
        return {n: rc for n, p in self.procs.items() if (rc := p.poll()) is not None}

    def _stacks(self, name: str, p: subprocess.Popen[bytes]) -> str:
        """Ask a hung service for its threads' stacks (written to its log); where to read them."""
        try:
            p.send_signal(STACKS_SIGNAL)
        except OSError:
            return ""
        time.sleep(0.5)  # the dump is written from the signal handler: a few ms
        if not self.spec.log_dir:
            return " (its threads' stacks are on the launcher's stderr)"
        return f" (its threads' stacks are in {self.spec.log_dir / f'{name}.log'})"

    def stop(self, timeout: float = 10.0) -> dict[str, int]:
        """SIGINT each running process in :data:`STOP_ORDER`, wait, SIGKILL stragglers.

        Returns the exit codes of the processes that were still running (a process that died
        earlier was reported when it died; it is not part of a clean or unclean shutdown).
        """
        codes: dict[str, int] = {}
        order = (*STOP_ORDER[:-1], "record", "replay", STOP_ORDER[-1])  # the recorder, then the router
        order = (*(n for n in self.procs if n not in order), *order)  # (spawn_instance's first)
        if running := [n for n in order if n in self.procs and self.procs[n].poll() is None]:
            log.info("stopping %s", ", ".join(running))
        for name in order:
            p = self.procs.get(name)
            if p is None or p.poll() is not None:
                continue
            if name in NICE:  # a starved mirror could not save its recording in time
                set_normal_priority(p.pid)
            p.send_signal(signal.SIGINT)
            try:
                codes[name] = p.wait(timeout)
            except subprocess.TimeoutExpired:
                where = self._stacks(name, p)
                log.error("%s did not stop within %.0f s; killing pid %d%s", name, timeout, p.pid, where)
                p.kill()
                codes[name] = p.wait()
        for f in self._logs:
            f.close()
        self._logs.clear()
        return codes

    def __enter__(self) -> Site:
        try:
            self.start()
        except BaseException:
            self.stop()
            raise
        return self

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        self.stop()


def add_site_args(parser: argparse.ArgumentParser) -> None:
    """Flags shared by ``up`` and ``demo``."""
    parser.add_argument("--site", default="local", help="site id (default: local)")
    parser.add_argument("--host", default="127.0.0.1", help="router address (default: 127.0.0.1)")
    parser.add_argument("--port", type=tcp_port, default=7447, help="router TCP port (0: pick a free one)")
    parser.add_argument(
        "--config-dir",
        type=Path,
        metavar="DIR",
        help=f"site folder: DIR/{SITE_FILE} holds a table per service (default: the packaged "
        "deploy/local; others: deploy/plas, deploy/vip, ... or telesurg site init DIR)",
    )
    parser.add_argument("--log-dir", type=Path, help="write each service's log to DIR/<service>.log")
    parser.add_argument("--log-level", default="INFO", help="service log level (default: INFO)")
    parser.add_argument(
        "--set",
        action="append",
        default=[],
        metavar="SERVICE.KEY=VALUE",
        help="override a service config key, e.g. mapping.scale=0.3",
    )
    parser.add_argument(
        "--seconds",
        type=duration_s,
        default=0.0,
        help="stop after this many seconds (default: run until Ctrl-C)",
    )
    parser.add_argument(
        "--keys",
        type=Path,
        metavar="DIR",
        help="site keyring, made if absent (default: $TELESURG_KEYS or $XDG_STATE_HOME/telesurg/<site>/keys)",
    )
    parser.add_argument(
        "--plugin",
        action="append",
        default=[],
        metavar="FILE",
        help="plugin file (robots, master devices, safety rules), passed to every service (repeatable)",
    )
    parser.add_argument(
        "--master",
        choices=("scripted", "web"),
        default="scripted",
        help="scripted: master_capture plays the site file's path (default); web: no master_capture, "
        "the web console's page is the master (a surgeon at a browser: mouse and keyboard, phone, "
        "gamepad; implies --console)",
    )
    parser.add_argument(
        "--console", action="store_true", help="also start the web surgeon console (telesurg console --web)"
    )
    parser.add_argument(
        "--console-port",
        type=tcp_port,
        default=8470,
        help="the web console's port (default 8470; 0: a free one)",
    )


def with_console(args: argparse.Namespace, services: Sequence[str]) -> list[str]:
    """``services`` with the web console added (``--console``, ``--demo``) and, for ``--master
    web``, without master_capture (the console's page is the master)."""
    out = [s for s in services if not (args.master == "web" and s == "master_capture")]
    if args.master == "web" or getattr(args, "console", False):
        out.append("console")
    return out


def console_url(args: argparse.Namespace, spec: SiteSpec) -> str:
    """Set the web console's port (and, with a scripted master, turn its browser master off) in
    ``spec``; its page URL ("" if it is not started)."""
    if "console" not in spec.services:
        return ""
    port = args.console_port or free_port(args.host)
    items = spec.overrides.setdefault("console", [])
    items.insert(0, f"web.port={port}")
    if args.master != "web":  # the page shows and commands; master_capture is the master
        items.insert(0, 'web.master_service=""')
    return f"http://{args.host}:{port}/"


def check_ports(host: str, ports: Sequence[tuple[str, int, str]]) -> None:
    """SiteStartError naming every ``(what, port, hint)`` that something already listens on at
    ``host`` (a second demo on this machine: each port a flag of its own); :meth:`Site.start`
    checks the router's and ``SiteSpec.ports`` before anything starts. Port 0 (a free one, picked
    later) is skipped."""
    taken = []
    for what, port, hint in ports:
        if port:
            try:
                check_port_free(host, port, what)
            except ConnectionError as exc:
                taken.append(f"{exc} ({hint})")
    if taken:
        raise SiteStartError("; ".join(taken) + " — is another telesurg demo or up running?")


def spec_from_args(args: argparse.Namespace, services: Sequence[str]) -> SiteSpec:
    """SiteSpec from the shared flags (loads the ``--plugin`` files, so a bad one fails here)."""
    overrides: dict[str, list[str]] = {}
    for item in args.set:
        service, dot, rest = item.partition(".")
        if not dot or service not in CLI_NAME:
            raise ConfigError(f"--set {item!r} must start with a service name: {', '.join(CLI_NAME)}")
        overrides.setdefault(service, []).append(rest)
    config_dir = args.config_dir if args.config_dir is not None else default_config_dir()
    if not (config_dir / SITE_FILE).is_file():
        raise ConfigError(
            f"site file {config_dir / SITE_FILE} not found (--config-dir {config_dir}"
            + ("" if config_dir.is_dir() else ": no such folder")
            + "; site folders: deploy/<site>/ or telesurg site init DIR)"
        )
    from telesurg.shared import robots

    plugins = tuple(str(Path(p).resolve()) for p in args.plugin)
    # here too: a bad plugin fails before any service starts (the services load the site file's
    # [site] plugins themselves, from the site file they are given)
    for plugin in [*plugins, *site_plugins(config_dir / SITE_FILE)]:
        robots.load_plugin(str(plugin))
    check_site(config_dir / SITE_FILE, services, overrides)
    port = args.port or free_port(args.host)
    return SiteSpec(
        args.site,
        args.host,
        port,
        config_dir,
        tuple(services),
        overrides,
        args.log_dir,
        args.log_level,
        plugins=plugins,
        keys_dir=(args.keys or default_keys_dir(args.site)).resolve(),
        master_wait_s=MASTER_WAIT_S,
    )


def router_security_flags(args: argparse.Namespace) -> list[str]:
    """The router's TLS / access-control flags from ``telesurg up``'s arguments."""
    flags: list[str] = []
    for name in ("tls_ca", "tls_cert", "tls_key", "acl"):
        if value := getattr(args, name):
            flags += [f"--{name.replace('_', '-')}", str(Path(value).resolve())]
    for name in ("mtls", "allow_insecure_listen"):
        if getattr(args, name):
            flags.append(f"--{name.replace('_', '-')}")
    if args.zenoh_log:
        flags += ["--zenoh-log", args.zenoh_log]
    if getattr(args, "acl_log", None):
        flags += ["--set", f"acl_log={json.dumps(args.acl_log)}"]
    return flags


def lock_down(spec: SiteSpec, credentials_dir: str | Path | None = None, tls_cert: str = "") -> None:
    """Make the local PKI (services/launcher/lockdown.py) in ``credentials_dir`` (default: the
    per-user state directory) and use it for the router's local listener and every service of
    ``spec`` (``telesurg up --acl`` does). Without ``tls_cert`` (the consoles' TLS) the router's
    own TLS settings are the local ones."""
    from telesurg.services.launcher.lockdown import default_dir, make_local_pki

    root = Path(credentials_dir) if credentials_dir else default_dir(spec.site, spec.port)
    pki = make_local_pki(root.resolve(), spec.services)
    spec.local_pki = pki.root
    if not tls_cert:
        spec.router_flags += (
            "--tls-ca",
            str(pki.ca),
            "--tls-cert",
            str(pki.cert("router")),
            "--tls-key",
            str(pki.key("router")),
            "--mtls",
        )
    log.info("local credentials (mutual TLS on %s): %s", spec.endpoint, pki.root)


def router_bus(spec: SiteSpec) -> BusConfig:
    """The router's bus config as its command line will build it (to validate it up front)."""
    parser = argparse.ArgumentParser(add_help=False)
    add_bus_args(parser)
    args, _ = parser.parse_known_args(list(spec.router_flags))  # the router's own flags: --acl-log
    return bus_from_args(args, BusConfig(mode="router", listen=[spec.endpoint, *spec.listen]))


def login_url(page_url: str, token: str) -> str:
    """The web console's one-time login URL (``page_url`` ends with ``/``)."""
    return f"{page_url}login?token={token}"


def announce_login(page_url: str, token: str) -> None:
    """Print the web console's one-time login URL once its page is served (stdout only: the
    launcher's log may be readable by others)."""
    u = urllib.parse.urlsplit(page_url)
    wait_port(u.hostname or "127.0.0.1", u.port or 80, 30.0)
    print(f"web surgeon console (one-time login): {login_url(page_url, token)}", flush=True)


def run_site(
    spec: SiteSpec, seconds: float, stop: threading.Event, console: str = "", replay: Sequence[str] = ()
) -> int:
    """Run ``spec`` until ``stop`` or ``seconds``; 0 if every process stopped cleanly. ``console``:
    the web console's page URL (its one-time login URL is printed once the site is up).
    ``replay``: ``telesurg replay`` arguments (the file first), run once the site is up; the site
    stops when it ends, and its exit code is the result (docs/console.md)."""
    deadline = time.monotonic() + seconds if seconds > 0 else float("inf")
    replay_rc: int | None = None
    with Site(spec) as site:
        eps = ", ".join((spec.endpoint, *spec.listen))
        log.info("site %r up on %s; Ctrl-C stops everything", spec.site, eps)
        if console and site.login_token:
            announce_login(console, site.login_token)
        player = site._spawn_tool("replay", ["replay", *replay, "--site", spec.site]) if replay else None
        reported: set[str] = set()
        while not stop.wait(0.2) and time.monotonic() < deadline:
            if player is not None and (replay_rc := player.poll()) is not None:
                break
            for name, rc in site.dead().items():
                if name not in reported:
                    reported.add(name)
                    log.error("%s exited with code %d (the watchdog holds the slave)", name, rc)
        codes = site.stop()
    if player is not None:
        codes.pop("replay", None)
        if replay_rc is None:
            log.error("the replay did not finish")
            replay_rc = 1
    bad = {n: c for n, c in codes.items() if c != 0}
    if bad:
        log.error("unclean exits: %s", bad)
        return replay_rc or 1
    log.info("all processes stopped cleanly")
    return replay_rc or 0


def main(argv: Sequence[str] | None = None) -> int:
    """``telesurg up``."""
    parser = argparse.ArgumentParser(
        prog="telesurg up",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    add_site_args(parser)
    parser.add_argument("--no-mirror", action="store_true", help="do not start the mirror")
    parser.add_argument("--save", metavar="FILE.rrd", help="mirror writes this .rrd")
    parser.add_argument("--serve", action="store_true", help="mirror serves the rerun web viewer")
    parser.add_argument(
        "--record",
        type=Path,
        metavar="FILE.mcap",
        help="record the whole session from before any service starts (telesurg record)",
    )
    parser.add_argument(
        "--replay",
        type=Path,
        metavar="FILE.mcap",
        help="a site without master_capture: replay FILE's master streams once it is up, compare, "
        "stop; exits with telesurg replay's code (0: the slave did the same)",
    )
    parser.add_argument("--replay-json", type=Path, metavar="FILE", help="with --replay: its report as JSON")
    parser.add_argument(
        "--services",
        metavar="LIST",
        help=f"comma-separated services to start (default: all; from {', '.join(SERVICES)})",
    )
    g = parser.add_argument_group("router security (the router only; see docs/deploy.md)")
    g.add_argument("--listen", action="append", default=[], metavar="ENDPOINT", help="more router endpoints")
    g.add_argument("--tls-ca", metavar="FILE", help="CA certificate that verifies the consoles")
    g.add_argument("--tls-cert", metavar="FILE", help="the router's certificate (CN slave-site)")
    g.add_argument("--tls-key", metavar="FILE", help="its private key")
    g.add_argument("--mtls", action="store_true", help="require a client certificate from --tls-ca")
    g.add_argument("--acl", metavar="FILE", help="access-control rules (e.g. deploy/slave-site/acl.json5)")
    g.add_argument(
        "--allow-insecure-listen",
        action="store_true",
        help="let a secured router listen on plain tcp/udp beyond loopback (development only)",
    )
    g.add_argument(
        "--zenoh-log",
        metavar="FILTER",
        help="the router's zenoh log, e.g. zenoh::net::routing::interceptor::access_control=trace",
    )
    g.add_argument(
        "--acl-log",
        choices=("off", "denied", "all"),
        help="the router logs access-control denials only (denied) or every decision (all)",
    )
    g.add_argument(
        "--credentials-dir",
        metavar="DIR",
        help="with --acl: where the local services' certificates are made at every start "
        "(default: $XDG_STATE_HOME/telesurg/<site>-<port> or ~/.local/state/telesurg/<site>-<port>)",
    )
    args = parser.parse_args(argv)
    setup_logging("INFO", "launcher")
    if args.services:
        wanted = [s.strip() for s in args.services.split(",") if s.strip()]
        unknown = [s for s in wanted if s not in SERVICES]
        if unknown:
            print(f"telesurg up: unknown service(s) {unknown}; valid: {', '.join(SERVICES)}", file=sys.stderr)
            return 2
    else:
        wanted = list(SERVICES)
    services = [
        s
        for s in SERVICES
        if s in wanted and not (s == "mirror" and (args.no_mirror or not (args.save or args.serve)))
    ]
    services = with_console(args, services)
    replay: list[str] = []
    if (args.record or args.replay) and args.acl:
        print("telesurg up: --record / --replay run on an open local site, not with --acl", file=sys.stderr)
        return 2
    if args.replay:
        if not args.replay.is_file():
            print(f"telesurg up: --replay {args.replay}: no such file", file=sys.stderr)
            return 2
        services = [s for s in services if s != "master_capture"]  # the replay takes its place
        replay = [str(args.replay), *(["--json", str(args.replay_json)] if args.replay_json else [])]
    try:
        spec = spec_from_args(args, services)
        spec.record = args.record
        spec.listen, spec.router_flags = tuple(args.listen), tuple(router_security_flags(args))
        if args.acl:  # a secured router: the local services authenticate too
            lock_down(spec, args.credentials_dir, args.tls_cert or "")
        router_bus(spec).validate()
    except ConfigError as exc:
        print(f"telesurg up: {exc}", file=sys.stderr)
        return 2
    if args.save:
        spec.overrides.setdefault("mirror", []).append(f"save={json.dumps(str(args.save))}")
    if args.serve:
        spec.overrides.setdefault("mirror", []).append("serve=true")
    if url := console_url(args, spec):
        log.info("web surgeon console: %s (its one-time login URL is printed once it is up)", url)
    stop = threading.Event()
    install_stop_handlers(stop)
    if "console" in spec.services:
        spec.ports = (("the web console's port", args.console_port, "--console-port 0 picks a free one"),)
    try:
        return run_site(spec, args.seconds, stop, url, replay)
    except (TelesurgError, ConnectionError) as exc:  # (what had started is stopped: Site.__enter__)
        print(f"telesurg up: {exc}", file=sys.stderr)
        return 1
