"""Why the trocar arm's RCM error from its measured joints was mm-scale, and that it no longer is
(issue #20, acceptance 1).

The slave's own follow pieces (``ServoFollow`` with its ``SetpointInterpolator``, the
``FollowController``), the MuJoCo MH3F (1 ms physics, the MJCF's position servos) and the
mapping's clamped trocar IK (``clamped_trocar_ik``) run here on one simulated clock, as
``slave_control.run`` runs them — including its stall rule (the arm holds its command through all
but the last 20 missed periods, replays those). The master is the virtual-trocar master of the
process test: a 60 mm circle then an 80 mm figure-eight at scale 0.5, 110 mm deep. What a user
would see on the real site is injected on that clock: setpoints arriving in bursts (a loaded
host's scheduling), the mapping skipping samples (its own stall) and the slave loop stalling.

Every setpoint the mapping sends is RCM-exact (kinematic error ~1e-16 m). The measured joints
left the RCM by millimetres only where the servos were handed a step: the newest setpoint after a
burst or a stall, reached by a speed-clipped jump that each joint's servo answers at its own pace.
Interpolating every setpoint on the master's clock (as the joint-space arms already did), pausing
that timeline while the arm held its command through a stall of its loop and making the delay up
at up to 2× within 0.875 × the joint speeds keeps the measured RCM error in the tenths of a
millimetre.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
from telesurg.services.slave_control.arm import (
    CATCHUP,
    CATCHUP_SPEED_FRACTION,
    INTERP_WINDOW,
    REPLAY_MAX_PERIODS,
    ServoFollow,
)
from telesurg.services.slave_control.backends import MujocoBackend
from telesurg.services.slave_control.control import FollowController, Lease, Setpoint, SetpointInterpolator
from telesurg.shared.robots.mh3f.kinematics import MH3F, fk, ik
from telesurg.shared.robots.mh3f.trocar import insertion_depth, posture_adjust, rcm_error, trocar_ik
from telesurg.shared.robots.mh3f.trocar_limits import TROCAR_SPEED_FRACTION, clamped_trocar_ik
from telesurg.tools.experiment.jinno import STARTS, TROCAR

#: 12 s of 1 kHz MuJoCo per run: make test runs them, make test-fast does not
pytestmark = pytest.mark.slow

DT = 0.001  # s: the slave's period (MuJoCo step)
MASTER_DT = 0.004  # s: 250 Hz master, one servo_jp per mapped sample
T_END = 11.6  # s: 0.3 s still, the 5 s circle, the 6 s figure-eight, 0.3 s still


def handle(t: float) -> np.ndarray:
    """The master handle (m) at ``t`` s: as tests/test_trocar_reach_process.py draws it."""
    if 0.0 <= t < 5.0:
        a = 2 * math.pi * t / 5.0
        return np.array([0.03 * (1 - math.cos(a)), 0.03 * math.sin(a), 0.0])
    if 5.0 <= t < 11.0:
        a = 2 * math.pi * (t - 5.0) / 6.0
        return np.array([0.04 * math.sin(a), 0.02 * math.sin(2 * a), 0.0])
    return np.zeros(3)


def dummy_tip(h: np.ndarray) -> np.ndarray:
    """The virtual-trocar master point (fulcrum 100 mm below the handle, 250 mm dummy forceps)."""
    d = np.array([0.0, 0.0, -0.1]) - h
    out: np.ndarray = h + 0.25 * d / np.linalg.norm(d)
    return out


def inserted(start: str, depth: float) -> np.ndarray:
    q = posture_adjust(np.array(STARTS[start]), TROCAR)
    T = fk(q)
    T[:3, 3] += (depth - insertion_depth(q, TROCAR)) * T[:3, 0]
    return ik(T, q)


def follow(
    start: str, *, faults: bool, smooth: bool, seed: int = 1, frozen: bool = False
) -> dict[str, float]:
    """Run the drawing; the RCM error (mm) from the measured joints at every 1 ms period.

    ``frozen``: the stalls are of the whole slave process (descheduled or SIGSTOPped, its
    transport threads too), ordered as ``slave_control.run`` orders them: at the thaw the setpoints
    queued through the stall all arrive at once, stamped with the thaw time, and are polled before
    the command of the first missed period is computed (at that period's time)."""
    rng = np.random.default_rng(seed)
    q0 = inserted(start, 0.11)
    p0, m0 = fk(q0)[:3, 3], dummy_tip(np.zeros(3))
    # the mapping: one RCM-exact setpoint per master sample (skipping 14 in a row every 2 s: stalls)
    sps: list[tuple[float, np.ndarray]] = []
    q_map, last = q0.copy(), None
    for k in range(int(T_END / MASTER_DT)):
        t = k * MASTER_DT
        if faults and 1 <= k % 500 <= 14:
            continue
        dt = MASTER_DT if last is None else min(t - last, 0.012)  # services/mapping/trocar.py
        q_map = clamped_trocar_ik(p0 + 0.5 * (dummy_tip(handle(t - 0.3)) - m0), TROCAR, q_map, dt).q
        sps.append((t, q_map.copy()))
        last = t
    arrive, free = [], 0.0
    for t, _ in sps:  # 1 ms transport; with faults 1 in 5 late by ~4 ms: they come in bursts
        late = rng.exponential(0.004) if faults and rng.random() < 0.2 else 0.0
        free = max(t + 0.001 + late, free)
        arrive.append(free)
    stalls = {round(s / DT): int(rng.uniform(25, 150)) for s in (2.0, 4.2, 6.5, 8.1, 10.3)} if faults else {}

    ctl = FollowController(np.array(MH3F.max_velocity))
    vmax = CATCHUP_SPEED_FRACTION * np.array(MH3F.max_velocity)
    servo = ServoFollow(
        smooth, SetpointInterpolator(0.1, window=INTERP_WINDOW, catchup=CATCHUP, max_speed=vmax)
    )
    lease = Lease(True, math.inf, "")
    errs: list[float] = []
    with MujocoBackend("mh3f", tuple(q0)) as sim:
        q_cmd, newest, i, prev_poll = q0.copy(), None, 0, 0.0
        ctl.update(0.0, q0, q_cmd, lease, Setpoint(q0.copy(), False, 0.0), DT)  # armed (clutch up)

        def poll(t: float, thaw: bool = False) -> list[Setpoint]:
            nonlocal i, newest, prev_poll
            got = []
            while i < len(sps) and arrive[i] <= t:
                newest = Setpoint(sps[i][1], True, t if thaw else prev_poll, source_time=sps[i][0])
                got.append(newest)
                i += 1
            prev_poll = t
            return got

        def command(t: float, arrived: list[Setpoint]) -> None:
            nonlocal q_cmd
            ref = servo.reference(newest, arrived, t)
            sp = None if ref is None else Setpoint(ref.position, True, t)
            q_cmd = ctl.update(t, sim.read().position, q_cmd, lease, sp, DT)
            sim.command(q_cmd)

        n = 0
        while n < round(T_END / DT):
            t = n * DT
            if frozen and (missed := stalls.get(n, 0)):  # asleep from period n on
                command(t, poll((n + missed) * DT, thaw=True))  # the first missed period
                held = max(0, missed - REPLAY_MAX_PERIODS)
                sim.step(1 + held)
                servo.interp.pause(held * DT)
                for period in range(held + 1, missed + 1):
                    command(t + period * DT, [])
                    sim.step(1)
                    errs.append(rcm_error(sim.read().position, TROCAR) * 1e3)
                n += 1 + missed
                continue
            command(t, poll(t))
            missed = stalls.get(n, 0)
            held = max(0, missed - REPLAY_MAX_PERIODS)
            sim.step(1 + held)  # slave_control.run: the arm held its command through these
            if smooth:
                servo.interp.pause(held * DT)
            if missed:
                t_wake = (n + 1 + missed) * DT
                arrived = poll(t_wake)
                for late in range(missed - held, 0, -1):  # the last 20 replayed at their own times
                    command(t_wake - late * DT, arrived)
                    arrived = []
                    sim.step(1)
                    errs.append(rcm_error(sim.read().position, TROCAR) * 1e3)
            n += 1 + missed
            errs.append(rcm_error(sim.read().position, TROCAR) * 1e3)
    e = np.array(errs)
    return {
        "max": float(e.max()),
        "mean": float(e.mean()),
        "clipped": ctl.clipped,
        "behind_ms": servo.interp.behind * 1e3,
    }


@pytest.mark.parametrize("start", sorted(STARTS))
def test_measured_rcm_stays_below_1mm_through_bursts_and_stalls(start: str) -> None:
    clean = follow(start, faults=False, smooth=True)
    loaded = follow(start, faults=True, smooth=True)
    print(f"{start}: RCM from the measured joints, clean {clean}, with bursts and stalls {loaded}")
    assert clean["max"] < 0.1 and loaded["max"] < 1.0
    assert loaded["clipped"] == 0  # the catch-up never runs into the speed limit
    assert loaded["behind_ms"] < 1.0  # every stall made up by the end


@pytest.mark.parametrize("start", sorted(STARTS))
def test_a_frozen_slave_process_resumes_on_the_path(start: str) -> None:
    """A stall of the whole process (CI: 1–2 mm RCM peaks): the queued setpoints arrive at the
    thaw; the timeline must not count the stall twice and step back along the path."""
    loaded = follow(start, faults=True, smooth=True, frozen=True)
    print(f"{start}: RCM from the measured joints through whole-process stalls {loaded}")
    assert loaded["max"] < 1.0 and loaded["clipped"] == 0 and loaded["behind_ms"] < 1.0


def test_the_step_follower_left_the_rcm_by_millimetres() -> None:
    """The cause, as it was: the newest setpoint followed as a step (speed-clipped after a stall)."""
    clean = follow("start_c", faults=False, smooth=False)
    loaded = follow("start_c", faults=True, smooth=False)
    print(f"start_c step follower: clean {clean}, with bursts and stalls {loaded}")
    assert clean["max"] > 0.1 and loaded["max"] > 2.0


def _abrupt_pivot_rcm(start: str, depth: float, direction: np.ndarray, fraction: float) -> float:
    """Largest RCM error (mm, measured joints) of the MuJoCo MH3F handed an RCM-exact pivot that
    starts and stops abruptly, its fastest joint at ``fraction`` of its speed limit for 150 ms."""
    vmax = np.array(MH3F.max_velocity)
    q0 = inserted(start, depth)
    p0 = fk(q0)[:3, 3]
    per_mps = np.abs(trocar_ik(p0 + 1e-4 * direction, TROCAR, q0) - q0) / 1e-4 / vmax  # × limit per m/s
    v = fraction / float(per_mps.max())
    qs, q = [q0.copy()] * 50, q0.copy()
    for k in range(150):
        q = trocar_ik(p0 + direction * v * DT * (k + 1), TROCAR, q)
        qs.append(q.copy())
    qs += [q.copy()] * 200
    errs = []
    with MujocoBackend("mh3f", tuple(q0)) as sim:
        for qq in qs:
            sim.command(qq)
            sim.step(1)
            errs.append(rcm_error(sim.read().position, TROCAR) * 1e3)
    return max(errs)


@pytest.mark.parametrize("start", sorted(STARTS))
def test_the_servos_keep_the_rcm_at_the_speeds_trocar_mode_allows(start: str) -> None:
    """The speed bounds of trocar mode are where the arm's servos keep the forceps on the RCM: an
    abrupt pivot (a master that jumps after its console stalled, chased by the mapping; a stall
    made up by the slave) at the mapping's fraction of the joint speeds and at the catch-up's
    stays within 0.5 mm; at the former bounds (0.7 and 0.875) it reached 1.4 and 3.1 mm (CI:
    2.5 mm in trocar mode on a loaded host)."""
    worst = {f: 0.0 for f in (TROCAR_SPEED_FRACTION, CATCHUP_SPEED_FRACTION, 0.7, 0.875)}
    for depth in (0.06, 0.11):
        for direction in (np.array([1.0, 0.0, 0.0]), np.array([0.0, 1.0, 0.0])):
            for f in worst:
                worst[f] = max(worst[f], _abrupt_pivot_rcm(start, depth, direction, f))
    print(f"{start}: largest RCM error (mm) by fraction of the joint speeds {worst}")
    assert worst[TROCAR_SPEED_FRACTION] < 0.5 and worst[CATCHUP_SPEED_FRACTION] < 0.5
