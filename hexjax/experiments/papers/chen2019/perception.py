"""Chen 2019's rugged patch walked on a perceived DEM (issue: perception in the loop): the support planner
(`SupportPlanController`, Chen 2019 Sects. 2.2 and 3.1) handed the true elevation map ("planned", as in the
`chen2019` experiment) against the same planner mapping the patch itself with a depth camera on its torso
("perceived", `PerceivingSupportPlan`: scans -> 2.5D grid of mean heights, Zhao 2018 Sect. 5 -> RANSAC
ground -> unknown cells filled), over the same randomised patches, rollout keys and physics
(`hexjax.experiments.papers.chen2019.patch.run_chen2019`, which runs both). Reported: capsizes, crossings, tilt,
and how far the final map is from the true DEM over the patch.
"""

from __future__ import annotations

from typing import Dict

import numpy as np

from hexjax.sim.engines import RANGE_SENSORS, TRACES
from hexjax.experiments.papers.chen2019 import patch
from hexjax.perceive.sensors import get_sensor

NEEDS = frozenset({RANGE_SENSORS, TRACES})  # the walks' traces, the torso's range sensor (the runner picks once)


def run(o, entry) -> Dict:
    p = entry.preset
    return patch.run_chen2019(n=o.batch, seed=o.seed, robot=o.robot, duration=o.duration, stride=p["stride"],
                              phase_time=p["phase_time"], fixed_step_heights=(), chunk=o.chunk,
                              sensor=get_sensor(o.sensor), perceive_every=o.every, physics=o.physics, progress=True)


def report(res: Dict) -> str:
    c, m = res["config"], res["perceived"]["map"]
    s = c["sensor"]
    lines = [patch.report(res),
             f"perceived: {s['kind']} {s['fov_h']:g} x {s['fov_v']:g} deg, {s['n_h'] * s['n_v']} rays, "
             f"{s['range_min']:g}-{s['range_max']:g} m, a scan every {c['perceive_every']} control steps "
             f"({res['perceived']['scans_per_walk']:.0f} per walk)",
             f"final map over the patch: {100 * m['seen_share']:.1f} % of its cells seen; height error (perceived - "
             f"true) on seen cells: mean |e| {1000 * m['seen_cells']['mean_abs']:.1f} mm, bias "
             f"{1000 * m['seen_cells']['bias']:+.1f} mm, p95 {1000 * m['seen_cells']['p95_abs']:.1f} mm; on every "
             f"cell (unseen ones filled): mean |e| {1000 * m['all_cells']['mean_abs']:.1f} mm"]
    return "\n".join(lines)


def plot(res: Dict, png: str, env: int = 0) -> None:
    """One patch: the true DEM, the perceived one at the end of the walk, their difference, and both torso
    paths over the true heights."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from hexjax.world.dem import dem_layout

    origin, (nx, ny), cell = dem_layout(patch.patch_spec())
    true, seen = res["_true_dem"][env], np.asarray(res["_perceived_dem"][env])
    ext = (origin[0], origin[0] + nx * cell, origin[1], origin[1] + ny * cell)
    fig, ax = plt.subplots(1, 3, figsize=(14, 4.4))
    vmax = float(true.max())
    for a, h, title in ((ax[0], true, "true DEM"), (ax[1], seen, "perceived DEM (end of walk)")):
        im = a.imshow(h.T, origin="lower", extent=ext, cmap="terrain", vmin=0.0, vmax=vmax)
        a.set_title(title)
        fig.colorbar(im, ax=a, label="height (m)")
    d = ax[2].imshow((seen - true).T, origin="lower", extent=ext, cmap="RdBu_r", vmin=-0.05, vmax=0.05)
    ax[2].set_title("perceived - true")
    fig.colorbar(d, ax=ax[2], label="m")
    for name, style in (("planned", "k-"), ("perceived", "m-")):
        tr = res["_records"][name]["trace"][env]
        for a in ax:
            a.plot(tr[:, 0], tr[:, 1], style, lw=1.2, label=name)
    ax[0].legend(fontsize=7)
    for a in ax:
        a.set_xlabel("x (m)")
        a.set_ylabel("y (m)")
    ok = lambda n: "capsized" if res["_records"][n]["fell"][env] else "upright"
    fig.suptitle(f"chen2019-perception patch {env}: planned {ok('planned')}, perceived {ok('perceived')}; capsized "
                 f"of {res['config']['patches']}: planned {res['planned']['capsized']}, perceived "
                 f"{res['perceived']['capsized']}", fontsize=10)
    fig.tight_layout()
    fig.savefig(png, dpi=110)
    plt.close(fig)
