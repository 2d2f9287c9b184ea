"""The vectorised IK gives, target by target, what the scalar solvers give — and refuses what they refuse."""

from __future__ import annotations

import numpy as np
import pytest
from telesurg.shared.errors import IKError, KinematicsError
from telesurg.shared.robots.mh3f.kinematics import MH3F, fk, ik
from telesurg.shared.robots.mh3f.trocar import rcm_error, trocar_ik
from telesurg.tools.bench.ik_batch import ik_batch, trocar_ik_batch

Q_HOME = np.array([0.0, 0.2, 0.3, 0.0, -0.6, 0.0])
TROCAR = np.array([0.5, 0.0, 0.2])


def _scalar(fn, *args):  # type: ignore[no-untyped-def]
    try:
        return fn(*args)
    except IKError:
        return None


def test_ik_batch_matches_the_scalar_ik_on_random_poses() -> None:
    rng = np.random.default_rng(3)
    lo, hi = np.array(MH3F.lower), np.array(MH3F.upper)
    qs = rng.uniform(lo, hi, (400, 6))
    poses = np.array([fk(q) for q in qs])
    # also poses beyond the reach: shift some far away
    poses[::17, :3, 3] += 2.0
    q_ref = rng.uniform(lo, hi)
    q, ok = ik_batch(poses, q_ref)
    refused = 0
    for i, T in enumerate(poses):
        want = _scalar(ik, T, q_ref)
        if want is None:
            refused += 1
            assert not ok[i] and np.all(np.isnan(q[i]))
        else:
            assert ok[i]
            np.testing.assert_allclose(q[i], want, atol=1e-9)
            np.testing.assert_allclose(fk(q[i]), T, atol=1e-9)
    assert refused >= 400 // 17


def test_trocar_ik_batch_matches_the_scalar_trocar_ik() -> None:
    rng = np.random.default_rng(5)
    q_in = trocar_ik(TROCAR + np.array([0.06, 0.0, -0.03]), TROCAR, Q_HOME)
    tip0 = fk(q_in)[:3, 3]
    tips = tip0 + rng.uniform(-0.04, 0.04, (500, 3))
    tips[::25] = TROCAR + 0.001 * (tips[::25] - TROCAR)  # within 5 mm of the trocar: refused
    q, ok = trocar_ik_batch(tips, TROCAR, q_in)
    n_ok = 0
    for i, t in enumerate(tips):
        want = _scalar(trocar_ik, t, TROCAR, q_in)
        assert ok[i] == (want is not None), i
        if want is not None:
            n_ok += 1
            np.testing.assert_allclose(q[i], want, atol=1e-9)
            assert np.linalg.norm(fk(q[i])[:3, 3] - t) < 1e-9
            assert rcm_error(q[i], TROCAR) < 1e-9
    assert 400 <= n_ok < 500


def test_bad_input_is_refused_with_the_shape() -> None:
    with pytest.raises(KinematicsError, match=r"\(N, 3\)"):
        trocar_ik_batch(np.zeros((4, 2)), TROCAR, Q_HOME)
    with pytest.raises(KinematicsError, match="q_ref"):
        ik_batch(np.tile(np.eye(4), (2, 1, 1)), [0.0] * 5)
    with pytest.raises(KinematicsError, match="finite"):
        ik_batch(np.full((1, 4, 4), np.nan), Q_HOME)
