"""The measures behind the Yu 2019 experiments: phase locking of the free network (Eq. 5, `yu2019-network`), the
paired comparison of reflex variants and the ditch-floor reading (`yu2019-step`, `yu2019-ditch`)."""

import types

import numpy as np

from hexjax.experiments.papers.yu2019.steps import _comparisons, _floor_gap
from hexjax.experiments.papers.yu2019.network import lock_times
from hexjax.world.presets import get_robot


def test_followers_lock_and_stronger_coupling_locks_sooner():
    """Every random state locks within the horizon, and ten times Table 1's coupling locks sooner in the median
    (the coupling pulls the followers at a rate of about k / 2)."""
    slow = lock_times(0.1, 16, 0, 120.0, 0.01, 0.1)
    fast = lock_times(1.0, 16, 0, 120.0, 0.01, 0.1)
    assert np.all(np.isfinite(slow)) and np.all(np.isfinite(fast))
    assert np.median(fast) < 0.5 * np.median(slow)
    assert np.all(fast >= 0)


def test_a_short_horizon_reports_unlocked_states_as_infinite():
    """With 1 s of integration and k = 0.1 the followers of random states are not yet locked: inf, not a time."""
    t = lock_times(0.1, 16, 0, 1.0, 0.01, 0.1)
    assert np.isinf(t).sum() >= 8


def test_comparisons_pair_the_variants_env_for_env():
    """Success = crossed and not fallen. Reflexes 3 of 4, the other variant 1 of 4 on the same envs: +50 points,
    and a paired interval from the per-env differences (1, 0, 1, 0): mean 0.5, sd 0.577, half-width 0.566."""
    per = lambda crossed, fell: {"per_env": {"crossed": crossed, "fell": fell}}
    res = {"ditch40": {"reflexes": per([True, True, True, False], [False, False, False, True]),
                       "no-search": per([False, True, False, False], [True, False, False, False])}}
    d = _comparisons(res)["ditch40"]["reflexes - no-search"]
    assert d["success_pts"][0] == 50.0
    np.testing.assert_allclose(d["success_pts"][1:], [50 - 56.58, 50 + 56.58], atol=0.01)
    assert d["fall_pts"][0] == 0.0  # one fall each, on different envs


def test_floor_gap_reads_only_feet_wholly_over_the_ditch():
    """A 40 mm ditch from x = 0.30 to 0.38 m (floor at z = -0.04): a foot centre at x = 0.34, one radius above the
    floor, stands on it (gap 0); a foot at the wall (x = 0.305) is not wholly over the ditch and does not count;
    an env whose feet never enter reads inf."""
    robot = get_robot("yu2019")
    r = robot.foot_radius
    terrain = types.SimpleNamespace(box_pos=np.array([[[-0.35, 0, -0.02], [1.0, 0, -0.02]]] * 2),
                                    box_half=np.array([[[0.65, 0.5, 0.02], [0.62, 0.5, 0.02]]] * 2),
                                    ground_z=np.array([-0.04, -0.04]))
    feet = np.zeros((2, 3, 6, 3))
    feet[..., 2] = 0.05  # every foot in the air, away from the ditch, unless set below
    feet[0, 1, 2] = (0.34, 0.1, -0.04 + r)
    feet[0, 2, 3] = (0.305, 0.1, -0.06)  # deep, but at the wall
    gap = _floor_gap(types.SimpleNamespace(foot_trace=feet), terrain, robot)
    np.testing.assert_allclose(gap[0], 0.0, atol=1e-9)
    assert np.isinf(gap[1])
