"""``telesurg.gym``: every registered environment passes Gymnasium's checker, is deterministic with
a seed, steps faster than real time (the figure is printed), and moves the slave as the services
do: the same action sequence drives the robot's mapping strategy into slave_control's own arm core
(:class:`~telesurg.services.slave_control.arm.ArmCore`, the code the service runs every period,
here without the bus) stepping the same MuJoCo scene at 1 kHz, and the tips agree within 0.1 mm.
"""

from __future__ import annotations

import json
import time
from pathlib import Path

import gymnasium
import numpy as np
import pytest
import telesurg.gym
from gymnasium.utils.env_checker import check_env
from telesurg.gym.env import EPOCH_S, MASTER, TeleopReachEnv, _Pair
from telesurg.services.common import gl_backend
from telesurg.services.slave_control import SlaveControlConfig
from telesurg.services.slave_control.arm import ArmCore
from telesurg.services.slave_control.backends import MujocoBackend
from telesurg.services.slave_control.control import Lease
from telesurg.shared.messages import Header, JointSetpoint

IDS = sorted(telesurg.gym.ENVIRONMENTS)


@pytest.mark.parametrize("env_id", IDS)
def test_the_checker_passes_and_a_seed_repeats_an_episode(env_id: str) -> None:
    env = gymnasium.make(env_id)
    # (the render check renders offscreen: with EGL or OSMesa; test_the_image_observation... says
    # when it cannot)
    check_env(env.unwrapped, skip_render_check=not gl_backend())
    runs = []
    for _ in range(2):
        obs, _info = env.reset(seed=7)
        actions = np.random.default_rng(3).uniform(-1, 1, (40, *env.action_space.shape)).astype(np.float32)
        tips = [obs["tip"]]
        for a in actions:
            obs, reward, _term, _trunc, info = env.step(a)
            tips.append(obs["tip"])
            assert reward == pytest.approx(-info["distance_m"], abs=1e-6)
        runs.append((obs["goal"], np.array(tips)))
    assert np.array_equal(runs[0][0], runs[1][0]) and np.array_equal(runs[0][1], runs[1][1])
    moved = np.linalg.norm(runs[0][1][-1] - runs[0][1][0])
    assert moved > 1e-4, f"{env_id}: the tip did not move ({moved * 1e3:.3f} mm)"
    other, _ = env.reset(seed=8)
    assert not np.array_equal(other["goal"], runs[0][0])  # another seed, another goal
    env.close()


@pytest.mark.parametrize("env_id", IDS)
def test_a_step_is_faster_than_real_time(env_id: str) -> None:
    env = gymnasium.make(env_id)
    env.reset(seed=0)
    rng = np.random.default_rng(0)
    times = []
    for _ in range(150):
        a = rng.uniform(-1, 1, env.action_space.shape).astype(np.float32)
        t = time.perf_counter()
        _obs, _r, term, trunc, _i = env.step(a)
        times.append(time.perf_counter() - t)
        if term or trunc:
            env.reset()
    median_ms = float(np.median(times)) * 1e3
    sim_ms = 1e3 / 100.0
    print(
        f"{env_id}: one step (10 ms simulated) {median_ms:.3f} ms median, {sim_ms / median_ms:.0f}× real time"
    )
    assert median_ms < sim_ms  # wide margin: faster than real time even on a loaded host
    env.close()


class _CoreNode:
    """What ArmCore uses of its node without a bus: arrival times on the simulated clock."""

    def __init__(self) -> None:
        self.now = 0.0

    def received(self, key: str) -> float:
        return self.now

    def event(self, *args: object, **kwargs: object) -> None:
        return None


def _service_tips(env: TeleopReachEnv, actions: np.ndarray) -> np.ndarray:
    """The slave's tip after each action, driven as the services drive it: the robot's mapping
    strategy (a fresh one) → servo_jp → ArmCore (the slave's rules, interpolation, limits) at 1 kHz."""
    task = env.task
    cfg = SlaveControlConfig(model=task.model, arm=task.arm)
    node = _CoreNode()
    with MujocoBackend(task.model, (), env.backend.sites, env.backend.home) as backend:
        qa = backend.read().position.copy()
        qa[env.index] = env.q0
        backend.reset(qa)
        core = ArmCore(env.profile, env.index, cfg, backend.dt, node=node, interpolate=True)  # type: ignore[arg-type]
        core.start(core.arm_reading(backend.read()))
        core.lease = Lease(True, 1e18, "")
        pair = _Pair(env.cfg, task.arm)
        strategy = env.make_strategy(pair)
        master = np.zeros_like(env.master)
        key = f"slave/{task.arm}/servo_jp"

        def sample(t: float) -> None:
            h = Header("master_capture", 0, round((t + EPOCH_S) * 1e9))
            env.t, env.master = t, master  # the env's own message builder, nothing else of it
            msg = env._master_msg()
            assert msg.header.stamp_ns == h.stamp_ns
            with pair.lock:
                pair.q_meas = backend.read().position[env.index]
                pair.slave_state = env.pair.slave_state if env.pair is not None else None
            strategy.on_master(msg, "")
            strategy.process()
            sp = pair.node.outlets[pair.node.keys.slave(task.arm, "servo_jp")].last
            assert isinstance(sp, JointSetpoint)
            node.now = t + EPOCH_S
            core.on_setpoint(sp, key)

        # the slave is armed by a setpoint without follow (the mapping sends them before engaging)
        q0 = tuple(float(v) for v in env.q0)
        core.on_setpoint(
            JointSetpoint(Header("mapping", 0, time.time_ns()), env.profile.joint_names, q0), key
        )
        core.control(EPOCH_S, core.arm_reading(backend.read()))  # (read, no physics step: it arms)
        tips = []
        cycle = 0
        n = env.n_phys
        sample(0.0)
        for k, a in enumerate(actions):
            master = master + np.clip(a, -1, 1) * env.max_step
            sample((k + 1) * env.dt_ctrl)
            for i in range(n):
                now = EPOCH_S + k * env.dt_ctrl + (i + 1) * backend.dt
                reading = core.arm_reading(backend.read())
                q = core.control(now, reading)
                ctrl = backend._d.ctrl[: len(backend.joint_names)].copy()  # the arm servos (the jaws follow)
                ctrl[env.index] = q
                backend.command(ctrl)
                backend.step()
                cycle += 1
                core.after_period(cycle, core.arm_reading(backend.read()))
            tips.append(env.profile.tip(backend.read().position[env.index]))
        assert core.ctl.following and not core.rejected, (core.ctl.reason, core.rejected, core.ctl.holds)
    return np.array(tips)


@pytest.mark.parametrize("env_id", IDS)
def test_the_trajectory_is_the_services_for_the_same_actions(env_id: str) -> None:
    env = gymnasium.make(env_id).unwrapped
    assert isinstance(env, TeleopReachEnv)
    env.reset(seed=1)
    rng = np.random.default_rng(5)
    actions = np.clip(np.cumsum(rng.normal(0, 0.3, (120, *env.action_space.shape)), axis=0) * 0.2, -1, 1)
    tips = np.array([env.step(a.astype(np.float32))[0]["tip"] for a in actions], dtype=float)
    pair = env.pair
    env.reset(seed=1)
    env.pair = pair  # (the trocar state the reference's mapping reads)
    ref = _service_tips(env, actions)
    err = np.linalg.norm(tips - ref, axis=1)
    travel = np.linalg.norm(tips[-1] - tips[0])
    print(f"{env_id}: tip travel {travel * 1e3:.1f} mm, env vs services max {err.max() * 1e3:.4f} mm")
    assert travel > 5e-3  # the actions moved it
    assert err.max() < 1e-4, err.max()
    assert MASTER == "m1"
    env.close()


def test_the_image_observation_is_the_endoscope_view() -> None:
    if not gl_backend():
        pytest.skip(
            "no OpenGL for MuJoCo's offscreen renderer (libEGL or libOSMesa): image observation untested"
        )
    try:
        env = gymnasium.make("telesurg/VIP-Reach-v0", image=True, width=64, height=48)
        obs, _ = env.reset(seed=0)
    except Exception as e:  # a GL library that is installed but does not work here
        pytest.skip(f"MuJoCo's offscreen renderer does not start here: {e}")
    assert obs["image"].shape == (48, 64, 3) and obs["image"].dtype == np.uint8
    assert env.observation_space.contains(obs)
    assert obs["image"].std() > 1.0  # a picture, not a blank
    env.close()


def test_reset_starts_at_the_given_joints_and_bad_ones_are_refused() -> None:
    env = gymnasium.make("telesurg/VIP-Reach-v0").unwrapped
    assert isinstance(env, TeleopReachEnv)
    q = (env.q0 + 0.5 * env.lower + 0.5 * env.upper) / 2  # between the start pose and mid-range
    obs, info = env.reset(seed=0, options={"joints": q})
    assert np.allclose(obs["joints"], q, atol=1e-6)
    assert np.allclose(info["tip_m"], env.profile.tip(q), atol=1e-9)
    obs, _r, _t, _tr, _i = env.step(np.zeros(3, dtype=np.float32))  # a still master: the arm stays
    assert np.linalg.norm(obs["tip"] - info["tip_m"]) < 1e-4
    n = len(env.profile.joint_names)
    with pytest.raises(ValueError, match=f"{n} finite values"):
        env.reset(options={"joints": [0.0] * (n - 1)})
    with pytest.raises(ValueError, match="outside the joint limits"):
        env.reset(options={"joints": env.upper + 0.1})
    with pytest.raises(ValueError, match="unknown; valid: joints"):
        env.reset(options={"pose": q})
    obs, _ = env.reset(seed=0)  # no options: the task's start pose
    assert np.allclose(obs["joints"], env.q0, atol=1e-6)
    env.close()


def test_the_gym_bench_writes_each_environments_step_cost(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    from telesurg.gym import ENVIRONMENTS
    from telesurg.gym.bench import main

    out = tmp_path / "gym.json"
    assert main(["--steps", "5", "--runs", "2", "--json", str(out)]) == 0
    r = json.loads(out.read_text())
    assert set(r["environments"]) == set(ENVIRONMENTS)
    for e in r["environments"].values():
        c = e["step_ms"]
        assert len(e["step_ms_per_run"]) == 2 and 0 < c["min"] <= c["median"] <= c["max"]
    bad = tmp_path / "bad.json"
    assert main(["--steps", "0", "--json", str(bad)]) == 2
    assert "--steps and --runs must be positive" in capsys.readouterr().err and not bad.exists()
