"""Top-view picture of the adversary env's current state (matplotlib, off-screen).

Shows the road; in light red what is never feasible for an obstacle (the reference motion areas
of all windows and the added participants), in red the motion areas of the current window (the
road minus them is eq. 4's non-invasive area); the reference path (dashed), the ego's path so
far, the ego (blue), the seed participants (grey) and the added ones (dark red)."""

from __future__ import annotations

from typing import Any

import numpy as np
import shapely

from deft_gym.viz.plot import draw_map
from deft_gym.world.geometry import box_corners


def _fill(ax: Any, geom: shapely.Geometry, **kw: Any) -> None:
    for g in getattr(geom, "geoms", [geom]):
        if isinstance(g, shapely.Polygon) and not g.is_empty:
            xs, ys = g.exterior.xy
            ax.fill(xs, ys, lw=0, **kw)


def render_state(env: Any, size: tuple[float, float] = (8.0, 6.0), dpi: int = 80, span: float = 45.0) -> np.ndarray:
    """RGB array (H, W, 3) of the env's current state."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    ctx, sim = env.ctx, env.sim
    w = sim.world
    fig, ax = plt.subplots(figsize=size, dpi=dpi)
    draw_map(ax, ctx.roadmap)
    k = ctx.areas.window(w.time + 1e-6)
    areas = ctx.areas
    _fill(ax, areas.static_forbidden, color="#f4a6a6", alpha=0.35)
    _fill(ax, areas.forbidden[k], color="#e05050", alpha=0.35)
    for p in env.layout.placed:
        g = p.area if p.kind == "static" else p.windows.get(k)
        if g is not None:
            _fill(ax, g, color="#e05050", alpha=0.35)
    ax.plot(ctx.path.xy[:, 0], ctx.path.xy[:, 1], "k--", lw=1.0, label="reference path")
    ego_rows = env.recorder.ego_rows()
    ax.plot(ego_rows[:, 0], ego_rows[:, 1], color="tab:blue", lw=1.5, label="ego path")
    for p in w.present_participants():
        o = p.obj
        c = box_corners(np.array([o.position[0]]), np.array([o.position[1]]), np.array([o.heading]),
                        o.LENGTH, o.WIDTH)[0]
        color = "darkred" if p.id in env.added_ids else "tab:gray"
        ax.fill(c[:, 0], c[:, 1], color=color, alpha=0.9, zorder=4)
    e = w.ego
    c = box_corners(np.array([e.position[0]]), np.array([e.position[1]]), np.array([e.heading]), e.LENGTH, e.WIDTH)[0]
    ax.fill(c[:, 0], c[:, 1], color="tab:blue", zorder=5)
    ax.set_xlim(e.position[0] - span, e.position[0] + span)
    ax.set_ylim(e.position[1] + span * size[1] / size[0], e.position[1] - span * size[1] / size[0])
    ax.set_aspect("equal")
    ax.set_title(f"{ctx.name}  t = {w.time:.1f} s  window {k}  added {len(env.layout.placed)}")
    ax.legend(loc="upper right", fontsize=7)
    fig.tight_layout()
    fig.canvas.draw()
    img = np.asarray(fig.canvas.buffer_rgba())[..., :3].copy()
    plt.close(fig)
    return img
