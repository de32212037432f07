"""Host-side checks of the Yu 2019 CPG controller's params (`CPGParams`), run before anything is traced."""

from __future__ import annotations

import numpy as np

from hexjax.control.base import shown
from hexjax.control.cpg.converter import converter_points
from hexjax.control.cpg.params import CPGParams
from hexjax.world.robot import N_LEGS, RobotSpec, leg_ik


def check_params(robot: RobotSpec, stance_radial: float, p: CPGParams) -> None:
    """Concrete params (shared or batched) checked field by field; one ValueError line naming the field and
    value: positive and non-negative fields, the 0/1 switches, the gait's slots, sigma of Eq. 15, the clearances,
    the converter trims, and every converter point within reach of `robot`'s legs."""
    def arr(name):
        obj = p
        for part in name.split("."):
            obj = getattr(obj, part)
        return np.asarray(obj, dtype=float)

    positive = ("net.eps", "net.b", "net.omega", "step_length", "clearance", "elevated_clearance",
                "body_height", "ramp_time", "search_sigma", "search_freq", "temp_force", "temp_phase",
                "temp_height", "raised_tolerance")
    for f in positive:
        v = arr(f)
        bad = ~np.isfinite(v) | (v <= 0)
        if np.any(bad):
            raise ValueError(f"cpg.{f}={shown(v, bad)}: must be finite and > 0")
    for f in ("net.k", "f_contact", "search_amp"):
        v = arr(f)
        bad = ~np.isfinite(v) | (v < 0)
        if np.any(bad):
            raise ValueError(f"cpg.{f}={shown(v, bad)}: must be finite and >= 0")
    for f in ("feedback", "elevator", "searching", "smooth", "walk_on"):
        v = arr(f)
        bad = (v != 0) & (v != 1)
        if np.any(bad):
            raise ValueError(f"cpg.{f}={shown(v, bad)}: must be 0 (off) or 1 (on)")
    duty = arr("duty")
    if np.any(duty < 2):
        raise ValueError(f"cpg.duty={shown(duty, duty < 2)}: gait indicator gamma must be >= 2 (Eq. 16)")
    slot = arr("leg_slot")
    if slot.shape[-1] != N_LEGS or np.any(slot < 0) or np.any(slot > np.asarray(duty)[..., None] - 1):
        raise ValueError(f"cpg.leg_slot={shown(slot)}: six slots in [0, duty - 1]")
    sigma = arr("search_sigma")
    if np.any(sigma < 1):
        raise ValueError(f"cpg.search_sigma={shown(sigma, sigma < 1)}: must be >= 1 (Eq. 15)")
    he, h = np.broadcast_arrays(arr("elevated_clearance"), arr("clearance"))
    if np.any(he < h):
        raise ValueError(f"cpg.elevated_clearance={shown(he, he < h)}: must be >= clearance={shown(h, he < h)}")
    for f, shape in (("lc_trim", (2, 2, 3)), ("leg_trim", (N_LEGS, 2, 2, 3)), ("leg_clearance", (N_LEGS,)),
                     ("leg_f_scale", (N_LEGS, 3))):
        v = arr(f)
        if v.shape[v.ndim - len(shape):] != shape or not np.all(np.isfinite(v)):
            raise ValueError(f"cpg.{f} shape={v.shape!r}: must be finite with shape {shape}")
    scale = arr("leg_f_scale")
    if np.any(scale <= 0):
        raise ValueError(f"cpg.leg_f_scale={shown(scale, scale <= 0)}: must be > 0 (a factor on f_contact)")
    # every converter point, at both clearances with each leg's offset, must be reachable (batched params: each
    # member)
    lead = np.broadcast_shapes(*(arr(f).shape for f in ("step_length", "clearance", "elevated_clearance",
                                                        "body_height")), arr("leg_clearance").shape[:-1])
    cols = [np.broadcast_to(arr(f), lead).reshape(-1) for f in ("step_length", "clearance", "elevated_clearance",
                                                                "body_height")]
    legs = np.broadcast_to(arr("leg_clearance"), lead + (N_LEGS,)).reshape(-1, N_LEGS)
    for sl, h, he, bh, dl in set(zip(*(c.tolist() for c in cols), map(tuple, legs.tolist()))):
        for name, cl in (("clearance", h), ("elevated_clearance", he)):
            per_leg = cl + np.asarray(dl)
            if np.any(per_leg <= 0):
                raise ValueError(f"cpg.{name}={cl!r} with cpg.leg_clearance={list(dl)!r}: each leg's must be > 0")
            _, ok = leg_ik(robot, converter_points(robot, sl, per_leg, bh, stance_radial))
            if not bool(np.all(np.asarray(ok))):
                raise ValueError(
                    f"cpg.step_length={sl!r}, cpg.{name}={cl!r}, cpg.leg_clearance={list(dl)!r}, "
                    f"cpg.body_height={bh!r}: the converter's AEP/PEP/apex are out of reach of robot {robot.name!r}")
