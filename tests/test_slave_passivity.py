"""TDPA's slave port on the mapping's targets (shared/haptics/slave_pc.py): the slave never takes
more energy out of the network than the master put in; it backs off along the force to do so, and
walks the drift back when the master's energy allows."""

from __future__ import annotations

import numpy as np
import pytest
from telesurg.shared.haptics.slave_pc import SlavePassivity

DT = 0.002
K_TISSUE = 400.0  # N/m: the scenes' tissue
SURFACE = 0.0  # m: the tissue's top (z)


def press(
    pc: SlavePassivity, e_in_m: list[float], depth_m: float = 0.008, seconds: float = 2.0
) -> list[float]:
    """The target goes from 5 mm above the tissue to ``depth_m`` into it over ``seconds``; the
    tissue pushes back on the commanded tip; ``e_in_m`` gives the master's energy each period.
    Returns the tip's z each period."""
    n = round(seconds / DT)
    zs = []
    pc.engage(e_in_m[0])
    for i in range(n):
        z_target = 0.005 - (0.005 + depth_m) * min(1.0, i / (0.8 * n))
        x = pc.step(np.array([0.0, 0.0, z_target]), e_in_m[min(i, len(e_in_m) - 1)], 1.0, DT)
        pc.force = np.array([0.0, 0.0, K_TISSUE * max(0.0, SURFACE - x[2])])
        zs.append(float(x[2]))
    return zs


def test_a_master_that_put_in_no_energy_cannot_push_the_tissue() -> None:
    pc = SlavePassivity(force_scale=0.5)
    zs = press(pc, [0.0])
    deepest = -min(zs)
    print(f"no master energy: deepest {deepest * 1e3:.2f} mm of 8; W_s min {pc.w_min * 1e3:.3f} mJ")
    assert deepest < 0.002  # held near the surface (the first contact's period, then backed off)
    assert pc.w_min > -1e-3  # the observer never below −1 mJ
    assert pc.offset_max > 0.005 and pc.offset[2] > 0  # the price: the drift, upward (off the tissue)


def test_enough_master_energy_leaves_the_target_alone() -> None:
    pc = SlavePassivity(force_scale=0.5)
    zs = press(pc, [0.0, 1.0])  # the master put in 1 J: far more than 0.5 × ½ k d² ≈ 6 mJ
    assert min(zs) == pytest.approx(-0.008, abs=1e-6) and pc.offset_max == 0.0 and pc.dissipated == 0.0


def test_the_drift_walks_back_once_the_master_supplies_the_energy() -> None:
    pc = SlavePassivity(force_scale=0.5, drift_time_s=0.5)
    press(pc, [0.0], seconds=1.0)
    assert pc.offset_max > 0.005
    drifted = float(np.linalg.norm(pc.offset))
    # the master now pays: the offset decays towards zero (each step at most the cap)
    for _ in range(round(3.0 / DT)):
        x = pc.step(np.array([0.0, 0.0, -0.008]), 1.0, 1.0, DT)
        pc.force = np.array([0.0, 0.0, K_TISSUE * max(0.0, SURFACE - x[2])])
    print(f"drift {drifted * 1e3:.2f} mm → {np.linalg.norm(pc.offset) * 1e3:.3f} mm")
    assert np.linalg.norm(pc.offset) < 0.05 * drifted


def test_a_new_engage_starts_the_count_and_the_offset_afresh() -> None:
    pc = SlavePassivity(force_scale=0.5)
    press(pc, [0.0], seconds=1.0)
    pc.engage(5.0)
    assert not pc.offset.any() and pc.e_out == 0.0 and pc.e_in0 == 5.0
