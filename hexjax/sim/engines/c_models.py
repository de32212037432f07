"""MuJoCo C's models: one `MjModel` per env, copied once from a template and then refilled for every chunk with
that env's terrain boxes, ground height and perturbation draw (`hexjax.sim.engines.c`).

The terrain boxes are geoms of the world body, laid on the template's square grid of slots (`build_mjcf`'s
`terrain_boxes`). A geom with no body of its own costs MuJoCo its kinematics at every step and nothing else:
neither the broadphase's sweep over bodies nor the body kinematics sees it, and the world body's bounding-volume
tree (mid-phase) finds the few boxes a foot, pad or the torso can touch. The compiler built that tree over the
placeholder grid; here each env's boxes are placed so that neighbouring slots hold neighbouring boxes and the
tree's boxes are recomputed from its leaves up (`_refit`), so it prunes exactly what it covers. On 800 boxes (the
`waves` family) one thread steps the robot 5x faster than with one static body per box, whose every body was swept
and moved at every step.
"""

from __future__ import annotations

import dataclasses
import functools

import jax
import mujoco
import numpy as np

from hexjax.sim import perturb
from hexjax.sim.config import PhysicsConfig
from hexjax.sim.mjcf import PARKED_Z, build_mjcf, compile_mjcf, sensor_layout
from hexjax.sim.perturb import MIN_FRICTION
from hexjax.world.robot import RobotSpec

_FULL = mujoco.mjtState.mjSTATE_FULLPHYSICS
EMPTY_HALF = 1e-6  # m: the half sizes of an empty slot's box (it never collides: conaffinity 0)


@dataclasses.dataclass
class _Template:
    model: mujoco.MjModel
    k: int  # the box slots' grid side: k * k box geoms in the world body (`build_mjcf`'s placeholder grid)
    box_geoms: np.ndarray  # (k * k,) geom ids; slot j is column j // k, row j % k
    bvh0: int  # the world body's first node in the model's bounding-volume arrays (the plane is not in its tree)
    leaves: np.ndarray  # (k * k,) the node (counted from bvh0) of each box slot's geom
    levels: list  # [(nodes, first child, second child)] of the tree's inner nodes, deepest level first
    ground_geom: int
    torso_body: int
    qpos0: np.ndarray
    ctrl0: np.ndarray
    nstate: int
    pool: list  # MjModel copies reused across calls (filling one costs a few us, copying one ~0.3 ms)


@functools.lru_cache(maxsize=8)  # a call's lanes may each take their own grid side
def _template(robot: RobotSpec, physics: PhysicsConfig, k: int) -> _Template:
    phys = dataclasses.replace(physics, slots_per_leg=0, torso_slots=0)
    # the ground plane moves with each env's ground_z (`_models` writes its geom_pos): see `compile_mjcf`
    m = compile_mjcf(build_mjcf(robot, phys, contact_sensors=True, terrain_boxes=k * k))
    gid = lambda n: mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_GEOM, n)
    key = mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_KEY, "stance")
    assert m.nsensordata == sensor_layout()["size"]
    a, nb = int(m.body_bvhadr[0]), int(m.body_bvhnum[0])
    child, node = np.asarray(m.bvh_child[a:a + nb]), np.asarray(m.bvh_nodeid[a:a + nb])
    depth = np.asarray(m.bvh_depth[a:a + nb])
    boxes = np.array([gid(f"terrain_{j}") for j in range(k * k)], dtype=int)
    # the refit below reads a slot's box as its position plus its half sizes (unrotated, centred)
    assert np.allclose(m.geom_quat[boxes], [1, 0, 0, 0]) and np.allclose(m.geom_aabb[boxes, :3], 0)
    is_leaf = (child < 0).all(1)
    leaf_of = {int(node[i]): i for i in np.flatnonzero(is_leaf)}
    levels = []
    for d in range(int(depth.max()), -1, -1):
        inner = np.flatnonzero(~is_leaf & (depth == d))
        if inner.size:  # a missing child (-1) stands in for its sibling
            c0, c1 = child[inner, 0], child[inner, 1]
            levels.append((inner, np.where(c0 < 0, c1, c0), np.where(c1 < 0, c0, c1)))
    return _Template(model=m, k=k, box_geoms=boxes, bvh0=a, leaves=np.array([leaf_of[int(g)] for g in boxes]),
                     levels=levels, ground_geom=gid("ground"),
                     torso_body=mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_BODY, "torso"),
                     qpos0=np.array(m.key_qpos[key]), ctrl0=np.array(m.key_ctrl[key]),
                     nstate=mujoco.mj_stateSize(m, _FULL), pool=[])


def _slot_layout(box_pos, box_half, box_valid, k: int):
    """Each env's boxes laid on the template's k x k slot grid so that neighbouring slots hold neighbouring boxes
    (sort-tile packing: columns of boxes by x, each column by y), whence the tree the compiler built over the grid
    stays tight once refitted. (pos, half, valid) of the k * k slots, (n, k * k, ...); an empty slot copies the
    position of a filled one nearby (same column, or the last column) with a box of no size, and never collides."""
    n, m = box_valid.shape
    kk = k * k
    cnt = box_valid.sum(1)
    assert cnt.max(initial=0) <= kk
    rows = np.maximum(1, -(-cnt // k))  # boxes per column
    inf = lambda x: np.where(box_valid, x, np.inf)
    by_x = np.argsort(inf(box_pos[..., 0]), axis=1, kind="stable")
    q = np.arange(m)[None]
    col = np.where(q < cnt[:, None], q // rows[:, None], k)  # the q-th box by x goes to this column
    y = np.take_along_axis(inf(box_pos[..., 1]), by_x, 1)
    order = np.take_along_axis(by_x, np.lexsort((y, col), axis=-1), 1)  # boxes by (column, y)
    slot = np.where(q < cnt[:, None], (q // rows[:, None]) * k + q % rows[:, None], -1)
    pos = np.zeros((n, kk, 3))
    pos[..., 2] = PARKED_Z
    half = np.zeros((n, kk, 3))
    valid = np.zeros((n, kk), bool)
    e, i = np.nonzero(slot >= 0)
    src = order[e, i]
    pos[e, slot[e, i]], half[e, slot[e, i]], valid[e, slot[e, i]] = box_pos[e, src], box_half[e, src], True
    # empty slots: the filled slot at the same row (or the last row) of the same column (or the last column)
    cols = -(-cnt // rows)
    last = cnt - (cols - 1) * rows  # boxes in the last filled column
    c, r = np.divmod(np.arange(kk), k)
    cc = np.minimum(c[None], cols[:, None] - 1)
    rr = np.minimum(r[None], np.where(cc < cols[:, None] - 1, rows[:, None], last[:, None]) - 1)
    near = np.where(cnt[:, None] > 0, cc * k + rr, 0)
    pos = np.where(valid[..., None], pos, np.take_along_axis(pos, near[..., None], 1))
    half = np.where(valid[..., None], half, EMPTY_HALF)
    return pos, half, valid


def _models(tp: _Template, box_pos, box_half, box_valid, ground_z, pert=None, start: int = 0):
    """One MjModel per env (from the reused pool) with that env's terrain boxes in the world body's slots
    (`_slot_layout`) and its ground height, the world body's bounding-volume tree refitted to them (`_refit`), and
    with `pert` (a host copy of the chunk's `Perturbation`) its draw's model fields (`_perturb_model`). start: the
    first pooled copy to fill (the models of two lanes of one template do not share copies)."""
    n = box_pos.shape[0]
    while len(tp.pool) < start + n:
        tp.pool.append(mujoco.MjModel.__copy__(tp.model))
    pos, half, valid = _slot_layout(box_pos, box_half, box_valid, tp.k)
    bits = np.where(valid, tp.model.geom_conaffinity[tp.box_geoms][None], 0)
    aabb = _refit(tp, pos, half)
    out = tp.pool[start:start + n]
    b0, nb = tp.bvh0, len(aabb[0])
    for i, mi in enumerate(out):
        place_boxes(mi, tp.box_geoms, tp.ground_geom, pos[i], half[i], bits[i], ground_z[i])
        mi.bvh_aabb[b0:b0 + nb] = aabb[i]  # the world body's tree, refitted
        _perturb_model(tp, mi, None if pert is None else jax.tree_util.tree_map(lambda x: x[i], pert))
    return out


def place_boxes(m: mujoco.MjModel, box_geoms, ground_geom: int, pos, half, conaffinity, ground_z) -> None:
    """One env's slot layout (`_slot_layout`: pos, half (k * k, 3)) written into the box geoms of model `m`, with the
    slots' conaffinity (0 for an empty slot) and the ground plane's height. Collision culling reads each geom's
    bounding sphere and own box, which the compiler made for the placeholder size: both are set too (the world
    body's tree is the caller's: `_refit`)."""
    m.geom_pos[box_geoms] = pos
    m.geom_size[box_geoms] = half
    m.geom_rbound[box_geoms] = np.linalg.norm(half, axis=-1)
    m.geom_aabb[box_geoms, 3:] = half
    m.geom_conaffinity[box_geoms] = conaffinity
    m.geom_pos[ground_geom, 2] = ground_z


def _refit(tp: _Template, pos, half):
    """(n, nodes, 6) boxes (centre, half sizes) of the world body's tree for each env's slots (n, k * k, 3): the
    compiler's tree, its leaves moved to the env's boxes and every inner node the box around its two children.
    The tree's shape stays the compiler's; only its boxes change, so it prunes exactly what it covers."""
    n = pos.shape[0]
    nb = int(tp.model.body_bvhnum[0])
    lo, hi = np.zeros((n, nb, 3)), np.zeros((n, nb, 3))
    lo[:, tp.leaves], hi[:, tp.leaves] = pos - half, pos + half
    for nodes, c0, c1 in tp.levels:
        lo[:, nodes] = np.minimum(lo[:, c0], lo[:, c1])
        hi[:, nodes] = np.maximum(hi[:, c0], hi[:, c1])
    return np.concatenate([(lo + hi) / 2, (hi - lo) / 2], -1)


def _perturb_model(tp: _Template, mi: mujoco.MjModel, p) -> None:
    """MjModel `mi` (a pooled copy: every field is written from the template, so a reused copy keeps nothing of
    its last env) with the draw `p` of one env, as `hexjax.sim.perturb.model` does to an mjx.Model: the robot's
    ground contacts are declared pairs (their friction set), its terrain-box contacts take the larger of their
    two geoms' friction (every geom's set). A limp leg's gains are zeroed later, at its onset (`rollout_c`)."""
    m0, b = tp.model, tp.torso_body
    if p is None:
        for f in ("geom_friction", "pair_friction", "body_mass", "body_ipos", "body_inertia", "actuator_gainprm",
                  "actuator_biasprm", "actuator_forcerange", "dof_damping"):
            getattr(mi, f)[:] = getattr(m0, f)
        return
    f = float(p.friction)
    mi.geom_friction[:] = m0.geom_friction
    mi.pair_friction[:] = m0.pair_friction
    if f >= 0:
        mi.geom_friction[:, 0] = max(f, MIN_FRICTION)
        mi.pair_friction[:, :2] = max(f, MIN_FRICTION)
    p64 = p.replace(torso_mass_scale=float(p.torso_mass_scale), payload_kg=float(p.payload_kg),
                    payload_offset=np.asarray(p.payload_offset, np.float64))
    mi.body_mass[:] = m0.body_mass
    mi.body_ipos[:] = m0.body_ipos
    mi.body_inertia[:] = m0.body_inertia
    mi.body_mass[b], mi.body_ipos[b], mi.body_inertia[b] = perturb.torso_with_payload(
        m0.body_mass[b], m0.body_ipos[b], m0.body_inertia[b], p64, xp=np)
    _gains(tp, mi, float(p.kp_scale) * np.ones(m0.nu))
    mi.actuator_forcerange[:] = m0.actuator_forcerange * float(p.torque_scale)
    mi.dof_damping[:] = m0.dof_damping
    mi.dof_damping[6:] *= float(p.damping_scale)


def _gains(tp: _Template, mi: mujoco.MjModel, scale) -> None:
    """Servo gains kp and kv of `mi` set to the template's times `scale` (nu,)."""
    mi.actuator_gainprm[:] = tp.model.actuator_gainprm
    mi.actuator_biasprm[:] = tp.model.actuator_biasprm
    mi.actuator_gainprm[:, 0] *= scale
    mi.actuator_biasprm[:, 1:3] *= scale[:, None]
