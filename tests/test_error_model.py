"""Luneckas 2020 Eqs. 8-14 against numbers worked by hand."""

import math

import numpy as np
import pytest

from hexjax.experiments.papers.luneckas2020 import error_model as em


def test_equations_hand_worked():
    # dL = 1 cm lost per blocked leg, robot width a = 30 cm (the paper's robot is 30 x 30 cm)
    dL, a = 0.01, 0.30
    # Eq. 12: beta = arccos(0.01 / 0.6) = arccos(0.016667) = 90 deg - 0.95497 deg = 89.04503 deg
    assert math.degrees(em.beta(dL, a)) == pytest.approx(89.04503, abs=1e-4)
    # Eqs. 13-14: alpha_k = 180 - 2 beta = 1.90995 deg (about dL / a = 1.9099 deg for small dL)
    assert math.degrees(em.alpha_k(dL, a)) == pytest.approx(1.90995, abs=1e-4)
    # Eq. 8: 4 obstacles, each met by n/2 = 3 legs: dx = 4 * 3 * 1 cm = 12 cm
    assert em.dx_sum(dL, 4) == pytest.approx(0.12)
    assert em.dx_sum(dL, 4, n_legs=4) == pytest.approx(0.08)
    # Eq. 11 with sides: obstacles left, left, right, left -> net 2 obstacles x 3 legs x 1.90995 deg = 11.4597 deg
    ak = em.alpha_k(dL, a)
    da = em.dalpha_sum(np.full(4, 3 * ak), signs=[1, 1, -1, 1])
    assert math.degrees(da) == pytest.approx(11.4597, abs=1e-3)
    # Eq. 10: d = 1 m, S = 13 steps of l_i = 4 cm: R = 1 - 0.52 = 0.48 m
    assert em.remaining_distance(1.0, 13, 0.04) == pytest.approx(0.48)
    # Eq. 9: dy = (0.48 - 0.12) sin(11.4597) / sin(78.5403) = 0.36 * tan(11.4597 deg) = 0.072979 m
    assert em.dy_from(0.48, 0.12, da) == pytest.approx(0.072979, abs=1e-5)
    # no turn, no lateral error; turn to the other side, the other sign
    assert em.dy_from(0.48, 0.12, 0.0) == 0.0
    assert em.dy_from(0.48, 0.12, -da) == pytest.approx(-0.072979, abs=1e-5)


def test_bad_inputs_raise():
    with pytest.raises(ValueError, match="dL"):
        em.beta(0.7, 0.3)  # a loss longer than the triangle's two sides cannot close it
    with pytest.raises(ValueError, match="90 deg"):
        em.dy_from(1.0, 0.1, math.pi / 2)


def test_obstacles_in_path_and_prediction():
    """Boxes: left lane at x 0.3, right lane at 0.6, one under the body centre (not met by legs), one far
    beyond the walk, one padding entry. Two are met -> dx = 2 * 3 * dL; opposite sides cancel the turn."""
    pos = np.array([[0.3, 0.15, 0.02], [0.6, -0.15, 0.02], [0.5, 0.0, 0.02], [1.6, 0.15, 0.02], [0.4, 0.15, 0.02]])
    half = np.array([[0.01, 0.02, 0.02]] * 5)
    valid = np.array([True, True, True, True, False])
    in_path, side = em.path_obstacles(pos, half, valid, 1.0)
    np.testing.assert_array_equal(in_path, [True, True, False, False, False])
    np.testing.assert_array_equal(side[:2], [1, -1])
    pred = em.predict_from_obstacles(0.01, 0.3, pos[None], half[None], valid[None], 1.0)
    assert pred["n_obstacles"][0] == 2
    assert pred["dx"][0] == pytest.approx(0.06)
    assert pred["dalpha"][0] == pytest.approx(0.0) and pred["dy"][0] == pytest.approx(0.0)
    assert pred["R"][0] == pytest.approx(0.4)  # the last obstacle met is at x = 0.6
    # only the left one: turn left by 3 alpha_k, dy = (R - dx) tan(3 alpha_k) with R = 1 - 0.3
    valid2 = valid.copy(); valid2[1] = False
    p2 = em.predict_from_obstacles(0.01, 0.3, pos[None], half[None], valid2[None], 1.0)
    assert p2["dalpha"][0] == pytest.approx(3 * em.alpha_k(0.01, 0.3))
    assert p2["dy"][0] == pytest.approx((0.7 - 0.03) * math.tan(3 * em.alpha_k(0.01, 0.3)))
    # least-squares dL through the origin recovers a planted value
    n = np.array([2, 4, 6, 8])
    assert em.fit_dL(n * 3 * 0.012, n) == pytest.approx(0.012)


def test_torso_strikes_read_box_tops_under_the_turned_torso():
    """One 4 cm box centred 0.3 m ahead: the torso above it with its underside 3 mm over the top strikes, 10 mm
    over does not; beside it (0.5 m to the left) nothing is under the footprint; turned 90 deg the footprint
    (long along y then) still covers the box; a padded (invalid) box never counts."""
    import types

    from hexjax.experiments.papers.luneckas2020.walks import torso_strikes
    from hexjax.world.presets import luneckas2020

    robot = luneckas2020()
    under = 0.04 + 0.5 * robot.body_thickness  # torso centre height with its underside on the box top
    trace = np.array([[[0.3, 0.0, under + 0.003, 0.0], [0.3, 0.0, under + 0.010, 0.0], [0.3, 0.5, under, 0.0],
                       [0.3, 0.0, under + 0.003, np.pi / 2]]] * 2)
    terrain = types.SimpleNamespace(box_pos=np.array([[[0.3, 0.0, 0.02]]] * 2),
                                    box_half=np.array([[[0.02, 0.02, 0.02]]] * 2),
                                    box_valid=np.array([[True], [False]]))
    hit = torso_strikes(robot, trace, terrain)
    assert hit[0].tolist() == [True, False, False, True]
    assert not hit[1].any()


def test_error_causes_add_up_to_the_cells_mean():
    """Five runs of 1 m, one fallen: the upright four split into stuck (0.5 m short), struck (0.1 m) and two clean
    (0.02, 0.04 m); each class's part is its share times its mean, and the parts add to the cell's 16.5 %."""
    from hexjax.experiments.papers.luneckas2020.matrix import _causes

    dx = np.array([0.5, 0.1, 0.02, 0.04, 0.9])
    dy = np.zeros(5)
    bad = np.array([False, False, False, False, True])
    stuck = np.array([True, False, False, False, True])
    struck = np.array([True, True, False, False, False])
    c = _causes(dx, dy, bad, stuck, struck, 1.0)
    assert c["stuck"]["share"] == 0.25 and c["torso_struck"]["share"] == 0.25 and c["clean"]["share"] == 0.5
    np.testing.assert_allclose([c["stuck"]["part_pct"], c["torso_struck"]["part_pct"], c["clean"]["part_pct"]],
                               [12.5, 2.5, 1.5])
    assert math.isclose(sum(v["part_pct"] for v in c.values()), 16.5)
