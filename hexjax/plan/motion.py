"""Motion generation of Zhao 2018, Sect. 4: tripod sequence, body motion planner (Eqs. 7-12),
foothold planner (Eqs. 13-18) and the semi-ellipse swing, for any hexjax `RobotSpec` (the closed loop
drives the MJX hexapod, not Octopus-III).

Per step T_S one tripod supports and the other swings (Sect. 4.1, Fig. 10); legs LF, LM, LH, RF, RM, RH
are the paper's FLF, MLF, RLF, FRF, MRF, RRF, so group 0 (LF, LH, RM) is {FLF, RLF, MRF} and group 1
(LM, RH, RF) is {MLF, RRF, FRF}, each listed counter-clockwise (`TRIPODS`).

* `body_move`: the farthest body displacement d along the walking direction alpha (Eqs. 7-8) such that
  the CoG projection keeps a margin delta_s inside the support triangle (Eq. 9) and every support foot
  stays in its leg's horizontal workspace, w_min <= |foot - hip| <= w_max (Eqs. 10-12). As in the paper
  the candidates are a finite set of distances along alpha; the largest valid one wins. Eq. 9 names only
  the leading edge l(FRF, MLF) of a forward walk; for any alpha we require the margin to all three edges
  (the trailing ones only bind if the start was already near them).
* `footholds`: the farthest next footholds of the swing tripod along alpha (Eqs. 13-14), each leg's
  stride from its own candidate set, such that the body's target position keeps delta_s inside the new
  support triangle (Eq. 15) and each foothold lies in its workspace at that target (Eqs. 16-18). All
  stride combinations are scored at once (n^3 for n candidates) and the largest total stride wins.
* `swing_path`: the semi-ellipse from a foot's lift-off point to its foothold, apex `height` (Sect. 4.3).

The CoG is taken at the torso centre (the MJX robots are symmetric). When no candidate is valid the body
waits (d = 0) and the returned `ok` flag is False.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
from flax import struct

from hexjax.plan.support import side_distances
from hexjax.world.robot import RobotSpec, hip_positions, leg_ik

TRIPODS = (np.array([0, 2, 4]), np.array([1, 5, 3]))  # CCW in the torso frame: (LF, LH, RM), (LM, RH, RF)


@struct.dataclass
class MotionParams:
    """delta_s () m stability margin; w_min, w_max () m: horizontal foot-to-hip range (Fig. 12);
    max_step () m: the longest body move / stride tried; hips (6, 2) m: hip xy in the torso frame."""

    delta_s: jax.Array
    w_min: jax.Array
    w_max: jax.Array
    max_step: jax.Array
    hips: jax.Array


def motion_params_for(robot: RobotSpec, delta_s: float = 0.02, margin: float = 0.9) -> MotionParams:
    """Workspace from the robot's leg IK: the range of horizontal foot distances reachable at the neutral
    hip height, shrunk by `margin` towards its middle."""
    r = np.linspace(0.0, robot.coxa_length + robot.femur_length + robot.tibia_length, 400)
    pts = np.stack([r, np.zeros_like(r), -np.full_like(r, robot.hip_height - robot.foot_radius)], -1)
    _, ok = leg_ik(robot, jnp.asarray(pts, jnp.float32))
    reach = r[np.asarray(ok)]
    if reach.size == 0:
        raise ValueError(f"robot {robot.name!r}: no foot distance is reachable at its hip height")
    lo, hi = float(reach.min()), float(reach.max())
    mid, half = 0.5 * (lo + hi), 0.5 * (hi - lo) * margin
    return MotionParams(delta_s=jnp.float32(delta_s), w_min=jnp.float32(mid - half), w_max=jnp.float32(mid + half),
                        max_step=jnp.float32(hi - lo), hips=jnp.asarray(hip_positions(robot)[:, :2], jnp.float32))


def _rot(yaw):
    c, s = jnp.cos(yaw), jnp.sin(yaw)
    return jnp.array([[c, -s], [s, c]])


def edge_margins(point, tri):
    """(3,) signed distances from point (2,) to the edges of a CCW triangle (3, 2): > 0 inside."""
    return side_distances(point, tri, jnp.ones(3, bool))[0]


def _in_workspace(feet, body_xy, yaw, legs, p: MotionParams):
    hips = body_xy + p.hips[legs] @ _rot(yaw).T
    dist = jnp.linalg.norm(feet - hips, axis=-1)
    return jnp.all((dist >= p.w_min) & (dist <= p.w_max), -1)


def body_move(body_xy, yaw, alpha, support_feet, support_legs, p: MotionParams, n: int = 64):
    """Eqs. 7-12: (target body xy (2,), distance d (), ok ()) for the support tripod's feet (3, 2) (CCW),
    legs (3,) their indices; the body keeps its yaw."""
    u = jnp.array([jnp.cos(alpha), jnp.sin(alpha)])
    d = jnp.linspace(0.0, 1.0, n) * p.max_step
    pos = body_xy + d[:, None] * u  # Eq. 8: along alpha
    stable = jax.vmap(lambda q: jnp.all(edge_margins(q, support_feet) > p.delta_s))(pos)  # Eq. 9
    reach = jax.vmap(lambda q: _in_workspace(support_feet, q, yaw, support_legs, p))(pos)  # Eqs. 10-12
    valid = stable & reach
    k = jnp.max(jnp.where(valid, jnp.arange(n), -1))  # Eq. 7: the farthest valid candidate
    ok = k > 0
    k = jnp.maximum(k, 0)
    return pos[k], jnp.where(ok, d[k], 0.0), ok


def footholds(body_target, yaw, alpha, swing_feet, swing_legs, p: MotionParams, n: int = 12):
    """Eqs. 13-18: (new footholds (3, 2), total stride (), ok ()) for the swing tripod's current feet (3, 2)
    (CCW) given the body's target xy for the end of the step."""
    u = jnp.array([jnp.cos(alpha), jnp.sin(alpha)])
    s = jnp.linspace(0.0, 1.0, n) * 2.0 * p.max_step  # a foot can pass the body: strides up to 2x its move
    grid = jnp.stack(jnp.meshgrid(s, s, s, indexing="ij"), -1).reshape(-1, 3)  # (n^3, 3) strides
    new = swing_feet[None] + grid[:, :, None] * u  # Eq. 14: each stride along alpha

    def valid(f):
        return (jnp.all(edge_margins(body_target, f) > p.delta_s)  # Eq. 15
                & _in_workspace(f, body_target, yaw, swing_legs, p))  # Eqs. 16-18

    ok = jax.vmap(valid)(new)
    total = jnp.sum(grid, -1)
    k = jnp.argmax(jnp.where(ok, total, -1.0))  # Eq. 13: the largest total stride
    return new[k], jnp.where(ok[k], total[k], 0.0), ok[k]


def swing_path(start, end, height, s):
    """Semi-ellipse swing (Sect. 4.3): foot position (len(s), 3) at phases s in [0, 1] from start (3,) to
    end (3,), `height` m above the straight line at mid-swing."""
    s = jnp.asarray(s)[:, None]
    lin = start + (end - start) * 0.5 * (1.0 - jnp.cos(jnp.pi * s))
    return lin + jnp.array([0.0, 0.0, 1.0]) * height * jnp.sin(jnp.pi * s)
