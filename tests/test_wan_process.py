"""The console across a lossy WAN: the master's pose over the datagram link keeps the arm following.

Two network namespaces joined by a packet link (``tools/bench/impair.py`` ``PacketLink``, in a
process of its own) with the ``5g-microhand`` profile: 57 ms each way and 1.2 % random loss per
packet and direction, on every protocol (the TLS connection loses packets too; its TCP
retransmits them). The slave namespace runs ``deploy/slave-site.sh --datagram-port 7449``
(router with mutual TLS and the ACL, watchdog, slave_control on MuJoCo, mapping); the console
namespace ``deploy/console.sh --datagram 7449 --no-console`` (master_capture: pose and buttons
best effort over UDP, everything else over the mutual-TLS session). A probe on the slave site's
loopback listener records what it shows.

A user notices, and the test checks, over one engagement of 20 s: the slave follows the whole time
(no HOLD, no drop out of follow), DEGRADED (a change of motion scale) comes only where
docs/safety.md says, and the tip follows the command within 1 mm. The poses' age at the slave
site and the gaps between them are reported (printed, and written with ``TELESURG_PERF_DIR``),
not asserted. (The same over TLS alone stalls for a round trip at each loss and holds the arm:
``telesurg bench transport``, docs/deploy.md.) The profile and the engaged time are the
environment's (``TELESURG_WAN_PROFILES``, ``TELESURG_WAN_SECONDS``; below). A second test cuts
the link.

Also, on the datagram listener, a stranger (no certificate, plain UDP) can neither read the site
nor put anything but the master's streams, and its forged pose and pedal are refused by the
message authentication and move nothing.

Root and ``ip netns`` are required (skipped otherwise).
"""

from __future__ import annotations

import contextlib
import itertools
import json
import os
import re
import signal
import subprocess
import sys
import threading
import time
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from helpers import clutch_flags
from telesurg.services.keys import export
from telesurg.shared.auth import IDENTITIES, KEYS_ENV, init_keyring
from telesurg.tools.bench.impair import NetNamespace, PacketLink
from telesurg.tools.bench.netprofile import LinkProfile, profile
from test_two_hosts import REPO, SITE, TwoHosts, _log_tail, needs_two_hosts

pytestmark = [pytest.mark.process, pytest.mark.timeout(300)]

SLAVE_ADDR, CONSOLE_ADDR = "198.18.1.1", "198.18.1.2"  # RFC 2544 benchmark range, on the packet link
TLS_PORT, LOCAL_PORT, DATAGRAM_PORT = 7447, 7448, 7449
DEADLINE_MS = 80.0  # the watchdog's master_deadline_ms default
# one engagement this long, on each of these profiles (tools/bench/netprofile.py; NAME+FIELD=VALUE
# overrides a field, e.g. 5g-microhand+loss=0.05+burst=4); the 5 minutes on three of issue #41:
# TELESURG_WAN_SECONDS=300 TELESURG_WAN_PROFILES=fibre-30km,5g-microhand,lindbergh
ENGAGED_S = float(os.environ.get("TELESURG_WAN_SECONDS", "20"))
PROFILES = os.environ.get("TELESURG_WAN_PROFILES", "5g-microhand").split(",")


def _profile(spec: str) -> LinkProfile:
    """``NAME+FIELD=VALUE...``: the named profile with those fields."""
    name, *over = spec.split("+")
    fields = {k: (float(v) if k != "jitter" else v) for k, _, v in (o.partition("=") for o in over)}
    for k in ("queue", "bucket_bytes"):
        if k in fields:
            fields[k] = int(fields[k])
    return profile(name, **fields)


@contextlib.contextmanager
def wan(
    tmp: Path,
    *,
    datagram: bool = True,
    link_profile: str = "5g-microhand",
    clutch: str = "",
    repeat_s: float = 14.0,
    camera: list[str] | None = None,
) -> Iterator[TwoHosts]:
    """The slave site and the console in two namespaces on a packet link with ``link_profile``
    (``h.link``), the probe on the slave site's local listener; the console engaged once for
    ``ENGAGED_S``, or as ``clutch`` says (``[[on, off]]``, again every ``repeat_s``; 0: once);
    ``camera``: the site's camera too, with these ``key=value`` settings."""
    from telesurg.services.certs import CertsConfig, make_certs

    certs, logs = tmp / "certs", tmp / "logs"
    logs.mkdir(parents=True)
    make_certs(CertsConfig(out=certs, hosts=("localhost", "127.0.0.1", SLAVE_ADDR)))
    site_keys = init_keyring(tmp / "site-keys", IDENTITIES)
    export(site_keys, ["master_capture", "console"], "console", "slave-site", tmp / "console-keys")
    env = dict(os.environ, PYTHONPATH=str(REPO), PYTHONUNBUFFERED="1", **{KEYS_ENV: str(site_keys)})
    tag = os.getpid() % 100000
    with NetNamespace(f"tswan-slave-{tag}") as ns_s, NetNamespace(f"tswan-console-{tag}") as ns_c:
        h = TwoHosts(ns_s, ns_c, certs, certs, logs, env, tmp / "console-keys")
        try:
            # the packet link in a process of its own: this one's garbage collection and the
            # probe's JSON must not hold up its forwarding thread (they did: 100 ms once in 5 min)
            argv = [sys.executable, str(Path(__file__).resolve()), "packetlink", ns_s.name, ns_c.name]
            link = subprocess.Popen(
                [*argv, f"tw{tag}", link_profile],
                env=env,
                stdin=subprocess.PIPE,
                stdout=subprocess.PIPE,
                text=True,
                start_new_session=True,
            )
            h.procs["link"] = link
            assert link.stdout is not None and link.stdout.readline().strip() == "ready", "no packet link"
            h.link = LinkControl(link)  # type: ignore[attr-defined]
            site = [str(REPO / "deploy" / "slave-site.sh"), "--site", SITE, "--certs", str(certs)]
            site += ["--listen", f"tls/0.0.0.0:{TLS_PORT}", "--local-port", str(LOCAL_PORT)]
            site += ["--log-dir", str(logs / "slave"), "--credentials-dir", str(tmp / "local-creds")]
            if datagram:
                site += ["--datagram-port", str(DATAGRAM_PORT)]
            if camera is not None:
                site += ["--camera", *(a for kv in camera for a in ("--set", f"camera.{kv}"))]
            h.spawn("slave-site", ns_s, site)
            deadline = time.monotonic() + 90.0
            while "up on" not in (logs / "slave-site.out").read_text(errors="replace"):
                assert h.procs["slave-site"].poll() is None, f"slave site exited\n{_log_tail(logs)}"
                assert time.monotonic() < deadline, f"slave site not up in 90 s\n{_log_tail(logs)}"
                time.sleep(0.2)
            probe_argv = [sys.executable, str(REPO / "tests" / "two_hosts_probe.py")]
            probe_argv += [f"tls/127.0.0.1:{LOCAL_PORT}", str(tmp / "local-creds"), "--master-times"]
            probe = h.spawn("probe", ns_s, probe_argv, pipe=True)
            assert probe.stdout is not None
            threading.Thread(target=h.probe.feed, args=(probe.stdout,), daemon=True).start()
            assert h.probe.wait("ready", lambda r: True, timeout=30.0), "probe did not start"
            console = [str(REPO / "deploy" / "console.sh"), SLAVE_ADDR, "--no-console", "--site", SITE]
            console += ["--certs", str(certs), "--log-dir", str(logs / "console")]
            if datagram:
                console += ["--datagram", str(DATAGRAM_PORT)]
            # one long engagement: pressed from 3 s (the watchdog's first leases) for ENGAGED_S
            schedule = clutch or f"[[3.0, {3.0 + ENGAGED_S}]]"
            console += [*clutch_flags(), "--set", f"master_capture.scripted.clutch={schedule}"]
            repeat = repeat_s if clutch else 0.0
            console += ["--set", f"master_capture.scripted.clutch_repeat_s={repeat}"]
            h.spawn("console", ns_c, console)
            yield h
        finally:
            h.shut_down(("console-web", "console", "probe", "slave-site", "link"))


@dataclass
class LinkControl:
    """Cut and restore the packet link of ``packetlink_main`` (a line each on its stdin)."""

    proc: subprocess.Popen[str]

    def _say(self, line: str) -> None:
        assert self.proc.stdin is not None and self.proc.stdout is not None
        self.proc.stdin.write(line + "\n")
        self.proc.stdin.flush()
        assert self.proc.stdout.readline().strip() == f"ok {line}"

    def cut(self) -> None:
        self._say("cut")

    def restore(self) -> None:
        self._say("restore")


def packetlink_main(ns_a: str, ns_b: str, name: str, spec: str) -> int:
    """A :class:`PacketLink` between the two namespaces with ``spec``'s profile until stdin ends
    or SIGTERM/SIGINT; ``cut`` / ``restore`` lines cut and restore it (each answered ``ok ...``)."""
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, signal.default_int_handler)
    with PacketLink(ns_a, ns_b, addr_a=SLAVE_ADDR, addr_b=CONSOLE_ADDR, name=name, seed=11) as link:
        link.set_profile(_profile(spec))
        print("ready", flush=True)
        with contextlib.suppress(KeyboardInterrupt):
            for line in sys.stdin:
                cmd = line.strip()
                if cmd == "cut":
                    link.cut()
                elif cmd == "restore":
                    link.restore()
                print(f"ok {cmd}", flush=True)
    return 0


def _engagement(h: TwoHosts, after: int = 0, timeout: float = 60.0) -> dict[str, Any]:
    """Wait for the (next, ``after``) engagement and its end; what the slave site saw during it."""
    engaged = h.probe.wait("op", lambda r: r["follow"], after=after, timeout=timeout)
    assert engaged is not None, f"the slave never followed the console\n{_log_tail(h.logs)}"
    t0 = engaged["t"]
    time.sleep(max(0.0, ENGAGED_S - 2.0 - (time.monotonic_ns() - t0) / 1e9))  # (no polling meanwhile)
    release = h.probe.wait("clutch", lambda c: not c["v"], after=t0, timeout=20.0)
    assert release is not None, f"no clutch release\n{_log_tail(h.logs)}"
    t1 = release["t"] - 200_000_000  # up to the release (its state change takes a moment)
    ops = h.probe.of("op", t0, t1)
    drops = [r for r in ops if not r["follow"]]
    holds = [s for s in h.probe.of("safety", t0, t1) if s["state"] == "HOLD"]
    degraded = [s for s in h.probe.of("safety", t0, t1) if s["state"] == "DEGRADED"]
    summaries = h.probe.of("ms", t0 + 1_000_000_000, t1)  # (each: the second before it)
    ages = np.array([a for r in summaries for a in r["age"]] or [np.inf])
    gaps = np.array([g for r in summaries for g in r["gap"]] or [np.inf])
    # tracking: the slave's tip against the mapping's commanded tip (interpolated), at the lag
    # that fits best (the servo's own, a few ms): what is left is the error the surgeon would see.
    # Both are placed at their senders' stamps (the mapping and the slave share the slave host's
    # clock), not at the probe's arrival: the probe's own scheduling on a loaded host is not the arm's
    t_end = min([t1, *(r["t"] for r in drops)])  # while the slave follows
    sps = h.probe.of("sp", t0, t_end)
    tips = h.probe.of("tip", t0 + 500_000_000, t_end)
    err, lag_ms = np.array([np.inf]), float("nan")
    if len(sps) > 1 and tips:
        sp_t = np.array([r["ts"] for r in sps], dtype=np.float64)
        sp_p = np.array([r["p"] for r in sps])
        tip_t = np.array([r["ts"] for r in tips], dtype=np.float64)
        tip_p = np.array([r["p"] for r in tips])

        def errors(lag_ns: float) -> np.ndarray:
            at = tip_t - lag_ns
            cmd = np.stack([np.interp(at, sp_t, sp_p[:, j]) for j in range(3)], axis=1)
            return np.linalg.norm(tip_p - cmd, axis=1) * 1e3

        lag_ms = min(range(0, 101, 5), key=lambda ms: float(np.mean(errors(ms * 1e6))))
        err = errors(lag_ms * 1e6)
    p50 = [s["p50"] for s in h.probe.of("safety", t0, t1)]
    causes = sorted(
        {c for s in h.probe.of("safety", t0, t1) if s["state"] == "DEGRADED" for c in s["causes"]}
    )
    hold_causes = sorted({c for s in holds for c in s["causes"]})
    out: dict[str, Any] = {
        "engaged_s": (t1 - t0) / 1e9,
        "out_of_follow": float(len(drops)),
        "holds": float(len(holds)),
        "degraded_reports": float(len(degraded)),
        "master_samples": float(len(ages)),
        "gap_p99_ms": float(np.percentile(gaps, 99)),
        "gap_max_ms": float(gaps.max()),
        "age_p50_ms": float(np.percentile(ages, 50)),
        "age_p99_ms": float(np.percentile(ages, 99)),
        "tracking_p99_mm": float(np.percentile(err, 99)),
        "tracking_max_mm": float(err.max()),
        "tracking_lag_ms": lag_ms,
        "latency_p50_ms": float(np.median(p50)) if p50 else float("nan"),
        "tip_travel_mm": h.probe.motion_mm(t0, t1),
        "degraded_causes": causes,
        "hold_causes": hold_causes,
    }
    return out


def stranger_main(endpoint: str) -> int:
    """A process with no certificate on the datagram listener: listens to the whole site, puts
    forged samples of every kind (unsigned: it has no key) for 2 s; prints what the site sent it."""
    import zenoh
    from telesurg.shared.bus import BusConfig, open_session
    from telesurg.shared.keys import Keys
    from telesurg.shared.messages import CartesianPose, EStop, JointSetpoint, MasterButtons, Sequencer

    k = Keys(SITE)
    session = open_session(BusConfig(mode="client", connect=[endpoint]))
    heard: list[str] = []
    _sub = session.declare_subscriber(f"{k.prefix}/**", lambda s: heard.append(str(s.key_expr)))
    pose = session.declare_publisher(k.master("m1", "measured_cp"), reliability=zenoh.Reliability.BEST_EFFORT)
    seq = Sequencer("master_capture")
    for i in range(200):
        pose.put(CartesianPose(seq.next(), "master", (0.05, 0.0, 0.02 * (i % 2))).encode())
        session.put(
            k.master("m1", "buttons"), MasterButtons(seq.next(), clutch=True, operator_present=True).encode()
        )
        sp = JointSetpoint(seq.next(), ("j1",), (0.3,), follow=True)
        session.put(k.slave("arm1", "servo_jp"), sp.encode())
        if i % 50 == 0:
            session.put(k.estop, EStop(seq.next(), "*", "estop", "stranger").encode())
        time.sleep(0.01)
    replies = list(session.get(k.command("arm1"), timeout=1.0))
    own = {k.master("m1", "measured_cp"), k.master("m1", "buttons"), k.slave("arm1", "servo_jp"), k.estop}
    # what the site sent it (its own puts reach its own subscriber inside its session)
    print(json.dumps({"heard": sum(key not in own for key in heard), "replies": len(replies)}), flush=True)
    session.close()  # type: ignore[no-untyped-call]
    return 0


@pytest.mark.timeout(ENGAGED_S + 240)
@pytest.mark.parametrize("link_profile", PROFILES)
def test_the_arm_follows_through_a_lossy_wan_on_the_datagram_link(tmp_path: Path, link_profile: str) -> None:
    needs_two_hosts()
    prof = _profile(link_profile)
    with wan(tmp_path, datagram=True, link_profile=link_profile) as h:
        dg = _engagement(h)
        # a stranger on the datagram listener, once the arm is out of follow
        time.sleep(1.0)
        t_s = time.monotonic_ns()
        argv = [
            sys.executable,
            str(Path(__file__).resolve()),
            "stranger",
            f"udp/{SLAVE_ADDR}:{DATAGRAM_PORT}",
        ]
        r = subprocess.run(h.console.cmd(argv), env=h.env, capture_output=True, text=True, timeout=60)
        assert r.returncode == 0, r.stdout + r.stderr
        stranger = json.loads(r.stdout.strip().splitlines()[-1])
        t_e = time.monotonic_ns()
        time.sleep(0.5)
        refused = [e for e in h.probe.of("event", t_s) if e["kind"] == "unauthenticated"]
        moved_mm = h.probe.motion_mm(t_s, t_e + 300_000_000)
        followed = [r for r in h.probe.of("op", t_s) if r["follow"]]
        estops = [s for s in h.probe.of("safety", t_s) if "estop" in " ".join(s["causes"]).lower()]
    dg = {"profile": link_profile, "link": prof.describe(), **dg}
    print(f"\n{link_profile}, the master's pose over the datagram link: {json.dumps(dg)}")
    if perf := os.environ.get("TELESURG_PERF_DIR"):
        name = link_profile.replace("+", "_").replace("=", "")
        (Path(perf) / f"wan-{name}.json").write_text(json.dumps(dg, indent=1) + "\n")
    assert dg["engaged_s"] > 0.8 * ENGAGED_S
    # what the surgeon notices: the arm never held nor dropped out of follow, and its tip stayed
    # on the command (the mapping's, at the servo's lag) within 1 mm
    assert dg["out_of_follow"] == 0 and dg["holds"] == 0, dg
    assert dg["master_samples"] > 0.5 * 500 * (dg["engaged_s"] - 1.0), dg  # the poses flowed
    assert dg["tip_travel_mm"] > 5.0 and dg["tracking_max_mm"] < 1.0, dg
    # DEGRADED (half the motion scale) only for a cause docs/safety.md names: latency p90 above
    # budget, or more than 10 % of a second's poses lost (a loaded host's stall adds the sender's
    # own drops to the link's). The poses' age and the gaps are figures, not asserted: timing
    # goals belong to the run above with TELESURG_PERF_DIR (docs/deploy.md)
    documented = re.compile(r"latency p90 .* (> budget|not yet below)|% of the master's poses lost")
    assert all(documented.search(c) for c in dg["degraded_causes"]), dg
    # the stranger: read nothing, no reply, its e-stop and setpoints never arrived, its forged
    # poses and buttons arrived and were refused by the message authentication; nothing moved
    print(
        f"stranger on the datagram listener: {stranger}; refusal events {len(refused)}; "
        f"moved {moved_mm:.3f} mm"
    )
    assert stranger == {"heard": 0, "replies": 0}
    assert refused and all(e["src"] in ("mapping", "watchdog", "probe") for e in refused), refused
    assert not followed and not estops
    assert moved_mm < 0.1


@pytest.mark.timeout(300)
def test_outages_hold_the_arm_and_only_a_fresh_press_resumes_it(tmp_path: Path) -> None:
    """Over ``5g-microhand``, the link cut for 0.3 s and then for 10 s (the sessions' lease, 1 s,
    runs out: both reconnect) while the arm follows: the slave holds within the lease of the last
    pose that reached it, does not move while held, and follows again only after a clutch release
    and a fresh press, without a jump."""
    needs_two_hosts()
    # pressed 10 s of every 14 s: each outage starts 2 s into an engagement
    with wan(tmp_path, clutch="[[2.0, 12.0]]") as h:
        link = h.link  # type: ignore[attr-defined]
        figures = []
        for outage_s in (0.3, 10.0):
            press = h.probe.wait("clutch", lambda c: c["v"], after=time.monotonic_ns(), timeout=40.0)
            assert press is not None, f"no clutch press\n{_log_tail(h.logs)}"
            eng = h.probe.wait("op", lambda r: r["follow"], after=press["t"], timeout=8.0)
            assert eng is not None, f"no engagement after the press\n{_log_tail(h.logs)}"
            time.sleep(2.0)
            t_cut = time.monotonic_ns()
            link.cut()
            time.sleep(outage_s)
            t_restore = time.monotonic_ns()
            link.restore()
            hold = h.probe.wait("op", lambda r: not r["follow"], after=t_cut, timeout=5.0)
            assert hold is not None and hold["t"] < t_restore, "the slave kept following through the cut"
            again = h.probe.wait("op", lambda r: r["follow"], after=t_restore, timeout=45.0)
            assert again is not None, f"no re-engage after the outage\n{_log_tail(h.logs)}"
            silent_ms = (hold["t"] - hold["m_last"]) / 1e6
            # a fresh press: a release, then a press, after the hold and before the re-engage (the
            # press and the slave's state reach the probe on different paths: 0.3 s between them)
            clutch = h.probe.of("clutch", hold["t"])
            release = next((c for c in clutch if not c["v"]), None)
            repress = next((c for c in clutch if c["v"] and release and c["t"] > release["t"]), None)
            assert release and repress and repress["t"] <= again["t"] + 300_000_000, (clutch, again)
            held_mm = h.probe.motion_mm(hold["t"] + 100_000_000, again["t"])
            tips = [
                r for r in h.probe.of("tip", again["t"] - 200_000_000) if r["t"] <= again["t"] + 500_000_000
            ]
            steps = [np.linalg.norm(np.subtract(b["p"], a["p"])) * 1e3 for a, b in itertools.pairwise(tips)]
            jump_mm = float(max(steps, default=0.0))
            figures.append(
                {
                    "outage_s": outage_s,
                    "hold_after_last_pose_ms": round(silent_ms, 1),
                    "moved_while_held_mm": round(held_mm, 3),
                    "largest_tip_step_at_reengage_mm": round(jump_mm, 3),
                    "reengaged_after_s": round((again["t"] - t_restore) / 1e9, 2),
                }
            )
            print(f"\noutage {outage_s:g} s: {figures[-1]}")
            assert hold["m_last"] > 0 and silent_ms < 250.0, figures[-1]  # the watchdog's lease
            assert held_mm < 0.5 and jump_mm < 1.0, figures[-1]
    if perf := os.environ.get("TELESURG_PERF_DIR"):
        (Path(perf) / "wan-outages.json").write_text(json.dumps(figures, indent=1) + "\n")


# the link of the video test: 5g-microhand with a bandwidth cap (the profile names none; 10 Mbit/s
# is a modest 5G uplink), and the camera: a 640x480 25 fps clip read through PyAV, as from a
# capture card, each frame also sent as H.264 to the console's page
VIDEO_PROFILE = os.environ.get("TELESURG_WAN_VIDEO_PROFILE", "5g-microhand+rate_kbps=10000")
WEB_PORT = 8471
PAGE_STATS = "JSON.stringify({painted: telesurgH264.painted, rx: telesurgH264.rx, error: telesurgH264.error})"


@pytest.mark.timeout(2 * ENGAGED_S + 300)
@pytest.mark.skipif(
    not os.environ.get("TELESURG_SLOW"),
    reason="issue #41 acceptance 5, not yet seen to pass on a loaded host: both sites, the browser and "
    "the packet link on 2 cores (the clean-clone CI held the arm 23-27 times with the video on): "
    "TELESURG_SLOW=1 runs it",
)
def test_video_reaches_the_page_across_the_wan_and_leaves_the_control_path_alone(tmp_path: Path) -> None:
    """Over ``VIDEO_PROFILE`` the camera's H.264 reaches a web console page on the console host
    (Chromium in the console namespace): it is painted, its rate, age at paint and bandwidth are
    figures; two engagements, the first with no page open (the camera encodes, nothing crosses
    the link) and the second with the video flowing, give the master's pose age at the slave with
    video off and on. Asserted what the surgeon notices: the picture keeps coming, the arm never held
    nor dropped out of follow in either engagement, and the video stays under the link's cap."""
    needs_two_hosts()
    if not Path("/usr/bin/chromium").exists():
        pytest.skip("needs /usr/bin/chromium")
    from helpers import chromium
    from test_video_h264 import H, W, _make_clip
    from test_web_console import js

    clip = tmp_path / "clip.mp4"
    _make_clip(clip)
    camera = ["source='video'", f"url='{clip}'", f"width={W}", f"height={H}", "fps=25", "video='h264'"]
    gap_s = 30.0  # between the engagements: the page opens and paints
    schedule = f"[[3.0, {3.0 + ENGAGED_S}], [{3.0 + ENGAGED_S + gap_s}, {3.0 + 2 * ENGAGED_S + gap_s}]]"
    prof = _profile(VIDEO_PROFILE)
    with wan(tmp_path, link_profile=VIDEO_PROFILE, clutch=schedule, repeat_s=0.0, camera=camera) as h:
        off = _engagement(h)
        after = time.monotonic_ns()
        # the web console on the console host, a viewer only (the scripted master drives)
        web = [str(REPO / "deploy" / "console.sh"), SLAVE_ADDR, "--master", "web", "--site", SITE]
        web += ["--certs", str(h.certs), "--web-port", str(WEB_PORT)]
        web += ["--set", "console.web.master_service=''", "--set", "console.web.video='h264'"]
        h.spawn("console-web", h.console, web)
        out = h.logs / "console-web.out"
        deadline = time.monotonic() + 60.0
        while not (
            m := re.search(r"web console: (http://\S+/login\?token=\S+)", out.read_text(errors="replace"))
        ):
            assert time.monotonic() < deadline, f"no web console\n{_log_tail(h.logs)}"
            time.sleep(0.2)
        wrapper = tmp_path / "chromium-in-console-ns"
        # (under SCHED_IDLE, as the site's camera: on this one host the browser stands for another
        # machine, and takes no CPU the control path could use)
        run_in_ns = f"exec chrt --idle 0 ip netns exec {h.console.name} /usr/bin/chromium"
        wrapper.write_text(f'#!/bin/sh\n{run_in_ns} "$@"\n')
        wrapper.chmod(0o755)
        with chromium(m.group(1), tmp_path / "chromium", browser=wrapper) as (cdp, s):
            ok = js(
                cdp,
                s,
                "new Promise(r => { const t0 = Date.now(); (function f() { "
                "if (window.telesurgH264 && telesurgH264.count > 25) r(true); "
                "else if (Date.now() - t0 > 40000) r(false); else setTimeout(f, 200); })(); })",
            )
            assert ok, f"the page painted no video: {js(cdp, s, PAGE_STATS)}\n{_log_tail(h.logs)}"
            on = _engagement(h, after=after, timeout=gap_s + 30.0)
            page = json.loads(js(cdp, s, PAGE_STATS))
    assert not page["error"], page["error"]
    # the page's figures over the second engagement's last ENGAGED_S - 2 s (its clock: wall, ms)
    t_end = page["painted"][-1][0]
    window_s = min(ENGAGED_S - 2.0, 20.0)
    painted = [a for t, a in page["painted"] if t >= t_end - window_s * 1e3]
    rx_bytes = sum(b for t, b in page["rx"] if t >= t_end - window_s * 1e3)
    video = {
        "painted_fps": round(len(painted) / window_s, 1),
        "age_at_paint_p50_ms": round(float(np.percentile(painted, 50)), 1),
        "age_at_paint_p99_ms": round(float(np.percentile(painted, 99)), 1),
        "kbps": round(rx_bytes * 8 / window_s / 1e3, 1),
    }
    res = {
        "profile": VIDEO_PROFILE,
        "link": prof.describe(),
        "video": video,
        "control_video_off": off,
        "control_video_on": on,
        "age_p99_ratio": round(on["age_p99_ms"] / off["age_p99_ms"], 2),
    }
    print(f"\nvideo over {VIDEO_PROFILE}: {json.dumps(res)}")
    if perf := os.environ.get("TELESURG_PERF_DIR"):
        (Path(perf) / "wan-video.json").write_text(json.dumps(res, indent=1) + "\n")
    assert len(painted) > window_s, video  # the picture kept coming (its rate is a figure)
    for eng in (off, on):  # the arm followed throughout, with and without the video
        assert eng["out_of_follow"] == 0 and eng["holds"] == 0 and eng["tip_travel_mm"] > 5.0, res
    # (with the video on, this one host also runs the browser and the camera's encoder: the
    # tracking error is then a figure of the CPU it shares, reported, not the link's)
    assert off["tracking_max_mm"] < 1.0, res
    assert video["kbps"] < prof.rate_kbps, video


if __name__ == "__main__":
    if sys.argv[1] == "stranger":
        sys.exit(stranger_main(sys.argv[2]))
    if sys.argv[1] == "packetlink":
        sys.exit(packetlink_main(*sys.argv[2:6]))
    sys.exit(f"usage: {sys.argv[0]} stranger ENDPOINT | packetlink NS_A NS_B NAME PROFILE")
