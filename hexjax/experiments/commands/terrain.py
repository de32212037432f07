"""`hexjax terrain`: one sampled terrain of a family drawn as a height map, with the robot's start outline; with
`--difficulty 0,0.5,1` one panel per difficulty (`TerrainSpec.at_difficulty`, lengths scaled to `--robot`)."""

from __future__ import annotations

from typing import Dict, Sequence

import jax
import numpy as np

from hexjax.world.presets import get_robot, get_terrain
from hexjax.world.terrain import heightmap, leg_scale, sample


def draw_terrain(preset: str, seed: int, png: str, difficulties: Sequence[float] = (),
                 robot: str = "luneckas2020") -> Dict:
    """Sample terrain `preset` with `seed` and draw its top heights (cm) to `png`, one panel per entry of
    `difficulties` (none: the preset as written). Returns what was drawn."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    base = get_terrain(preset)
    scale = leg_scale(get_robot(robot))
    specs = [base] if not difficulties else [base.at_difficulty(d, scale) for d in difficulties]
    xr = (-0.2, base.start_x + base.length + 0.1)
    yr = (-0.5 * base.width - 0.05, 0.5 * base.width + 0.05)
    maps, rows = [], []
    for spec in specs:
        t = jax.tree_util.tree_map(lambda x: x[0], sample(spec, jax.random.PRNGKey(seed), 1))
        maps.append(100 * heightmap(t, xr, yr, res=0.0025))
        rows.append({"difficulty": spec.difficulty, "boxes": int(np.asarray(t.box_valid).sum()),
                     "ground_z": float(t.ground_z), "top_cm": float(maps[-1].max()),
                     "bottom_cm": float(maps[-1].min())})
    lo, hi = min(m.min() for m in maps), max(m.max() for m in maps)
    # matplotlib's "terrain" ends in white, the page's colour: stop it at 85 % so the highest ground shows
    from matplotlib.colors import LinearSegmentedColormap
    cmap = LinearSegmentedColormap.from_list("terrain_no_white", plt.get_cmap("terrain")(np.linspace(0.0, 0.85, 256)))
    aspect = (yr[1] - yr[0]) / (xr[1] - xr[0])
    fig, axs = plt.subplots(len(specs), 1, figsize=(10, len(specs) * (10 * aspect + 0.6) + 0.6), squeeze=False)
    for ax, h, spec, row in zip(axs[:, 0], maps, specs, rows):
        im = ax.imshow(h.T, origin="lower", extent=(*xr, *yr), cmap=cmap, aspect="equal", vmin=lo,
                       vmax=hi if hi > lo else lo + 1)
        fig.colorbar(im, ax=ax, label="height (cm)", shrink=0.8)
        ax.add_patch(plt.Rectangle((-0.1, -0.05), 0.2, 0.1, fill=False, ec="k", lw=1.5))
        ax.set_ylabel("y (m)")
        d = "" if spec.difficulty is None else f", difficulty {spec.difficulty:g}"
        ax.set_title(f"terrain {preset}{d}, seed {seed}: {row['boxes']} boxes, heights "
                     f"{row['bottom_cm']:.1f} to {row['top_cm']:.1f} cm", fontsize=10)
    axs[-1, 0].set_xlabel("x (m), walking direction (box: the robot's torso at the start)")
    fig.tight_layout()
    fig.savefig(png, dpi=110)
    plt.close(fig)
    return {"preset": preset, "seed": seed, "robot": robot, "leg_scale": scale, "panels": rows, "png": png,
            "boxes": rows[0]["boxes"], "ground_z": rows[0]["ground_z"]}


# The command (configs/commands/terrain.yaml) -------------------------------------------------------------------
def run(o, entry) -> Dict:
    return draw_terrain(o.preset, o.seed, o.png, [float(d) for d in o.difficulty], o.robot)


def report(res: Dict) -> str:
    lines = [f"wrote {res['png']}"]
    for r in res["panels"]:
        d = "as written" if r["difficulty"] is None else f"difficulty {r['difficulty']:g}"
        lines.append(f"  {res['preset']} {d}: {r['boxes']} boxes, heights {r['bottom_cm']:.1f} to {r['top_cm']:.1f} cm")
    return "\n".join(lines)
