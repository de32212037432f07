"""`hexjax terrain`: one sampled terrain of a family drawn as a height map, with the robot's start outline."""

from __future__ import annotations

from typing import Dict

import jax
import numpy as np

from hexjax.world.presets import get_terrain
from hexjax.world.terrain import heightmap, sample


def draw_terrain(preset: str, seed: int, png: str) -> Dict:
    """Sample terrain `preset` with `seed` and draw its top heights (cm) to `png`. Returns what was drawn."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    spec = get_terrain(preset)
    t = jax.tree_util.tree_map(lambda x: x[0], sample(spec, jax.random.PRNGKey(seed), 1))
    xr = (-0.2, spec.start_x + spec.length + 0.1)
    yr = (-0.5 * spec.width - 0.05, 0.5 * spec.width + 0.05)
    h = heightmap(t, xr, yr, res=0.0025)
    fig, ax = plt.subplots(figsize=(10, 10 * (yr[1] - yr[0]) / (xr[1] - xr[0]) + 1.2))
    im = ax.imshow(100 * h.T, origin="lower", extent=(*xr, *yr), cmap="terrain", aspect="equal")
    fig.colorbar(im, ax=ax, label="height (cm)", shrink=0.8)
    ax.add_patch(plt.Rectangle((-0.1, -0.05), 0.2, 0.1, fill=False, ec="k", lw=1.5))
    ax.set_xlabel("x (m), walking direction")
    ax.set_ylabel("y (m)")
    n = int(np.asarray(t.box_valid).sum())
    ax.set_title(f"terrain {preset}, seed {seed}: {n} boxes, ground at {100 * float(t.ground_z):.1f} cm "
                 f"(robot torso outline at the start)")
    fig.tight_layout()
    fig.savefig(png, dpi=110)
    plt.close(fig)
    return {"preset": preset, "seed": seed, "boxes": n, "ground_z": float(t.ground_z), "png": png}


# The command (configs/commands/terrain.yaml) -------------------------------------------------------------------
def run(o, entry) -> Dict:
    return draw_terrain(o.preset, o.seed, o.png)


def report(res: Dict) -> str:
    return f"wrote {res['png']} ({res['boxes']} boxes)"
