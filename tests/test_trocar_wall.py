"""The MH3F's trocar wall: the forceps through the trocar moves freely while the software RCM holds,
and is pushed back towards the trocar when its shaft strays from it (shared/robots/mh3f/scene.xml's
``port_trocar``; ``Port`` in services/slave_control/backends.py). What the surgeon feels and the
watchdog watches is the slave's contact wrench (``measured_cf``): it carries the wall's push."""

from __future__ import annotations

import mujoco
import numpy as np
import pytest
from telesurg.services.slave_control.backends import MujocoBackend, Port
from telesurg.shared.errors import ConfigError
from telesurg.shared.robots.mh3f.trocar import STRAIGHT_FORCEPS, rcm_error, trocar_ik

TROCAR = np.array([0.5, 0.0, 0.2])  # the scene's trocar site (config trocar_mm)
HOME = (0.0, 0.2, 0.3, 0.0, -0.6, 0.0)  # the MH3F's home: the forceps above the patient
TIP = TROCAR + np.array([0.07, 0.0, -0.05])  # 86 mm through the trocar
STIFFNESS_N_MM, CLEARANCE_MM = 0.5, 1.5  # the scene's declaration


def _inserted(off_mm: np.ndarray) -> tuple[float, np.ndarray]:
    """(RCM error mm, contact wrench) with the forceps through the trocar, its shaft crossing the
    trocar's plane ``off_mm`` from the trocar (the arm commanded and settled there)."""
    geom = STRAIGHT_FORCEPS.arm_geometry()
    q0 = trocar_ik(TIP, TROCAR, HOME, geom=geom)
    off = np.asarray(off_mm) / 1e3
    q = trocar_ik(TIP + off, TROCAR + off, q0, geom=geom)
    with MujocoBackend("mh3f", tuple(q)) as b:
        b.command(q)
        b.step(200)
        r = b.read()
        assert r.contact_wrench is not None
        return rcm_error(r.position, TROCAR, geom) * 1e3, r.contact_wrench


@pytest.mark.parametrize("off", [0.0, 1.0])
def test_within_the_clearance_the_wall_does_not_touch(off: float) -> None:
    rcm_mm, w = _inserted(np.array([0.0, off, 0.0]))
    assert rcm_mm == pytest.approx(off, abs=0.05)
    assert np.allclose(w, 0.0), w


@pytest.mark.parametrize(
    "off", [np.array([0.0, 3.0, 0.0]), np.array([-5.0, 0.0, 0.0]), np.array([3.0, -4.0, 0.0])]
)
def test_beyond_it_the_wall_pushes_the_shaft_back_towards_the_trocar(off: np.ndarray) -> None:
    rcm_mm, w = _inserted(off)
    # the shaft crosses the trocar's (horizontal) plane |off| from the trocar: the push is in that
    # plane, back towards the trocar, 0.5 N per mm beyond the 1.5 mm clearance
    dist = float(np.linalg.norm(off))
    want = -STIFFNESS_N_MM * (dist - CLEARANCE_MM) * off / dist
    assert np.allclose(w[:3], want, atol=0.03 * np.linalg.norm(want)), (w[:3], want)
    assert rcm_mm > CLEARANCE_MM  # the RCM error the operating state reports is what it pushes on


def test_the_forceps_outside_the_patient_feels_nothing_of_the_trocar() -> None:
    with MujocoBackend("mh3f", HOME) as b:
        b.step(50)
        r = b.read()
        assert r.contact_wrench is not None and np.allclose(r.contact_wrench, 0.0)


@pytest.mark.parametrize(
    ("data", "site", "why"),
    [
        ("500 0.0015", "trocar", "need stiffness"),
        ("-1 0.0015 0.02", "trocar", "need stiffness"),
        ("500 0.03 0.02", "trocar", "clearance m < capture"),
        ("500 0.0015 0.02", "nowhere", "no site 'nowhere'"),
    ],
)
def test_a_malformed_port_is_refused_naming_it(data: str, site: str, why: str) -> None:
    xml = f"""<mujoco><custom><numeric name="port_{site}" data="{data}"/></custom>
      <worldbody><site name="trocar" pos="0.5 0 0.2"/></worldbody></mujoco>"""
    with pytest.raises(ConfigError, match=f"port_{site}.*{why}"):
        Port.declared(mujoco.MjModel.from_xml_string(xml))
