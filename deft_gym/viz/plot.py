"""Pictures of an episode: a matplotlib plot and a video rendered with highway-env's graphics.

:class:`EpisodeTrace` hooks into a :class:`~deft_gym.sim.simulation.Simulation` (``on_step``) and
keeps what the pictures need: the ego path and speed, every participant's path, and (from the
bus) the planned trajectories. With ``video=True`` it also grabs highway-env ``rgb_array``
frames (pygame, off-screen) at ``fps``.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any

import numpy as np

from deft_gym.world.roadmap import RoadMap


class EpisodeTrace:
    """Collects ego/participant paths, planned trajectories and optional video frames."""

    def __init__(self, sim: Any, video: bool = False, fps: int = 10, screen: tuple[int, int] = (720, 480),
                 scaling: float = 5.0) -> None:
        self.roadmap: RoadMap = sim.roadmap
        self.t: list[float] = []
        self.ego: list[tuple[float, float, float, float]] = []
        self.parts: dict[str, list[tuple[float, float, float]]] = {}
        self.kinds: dict[str, tuple[str, float, float]] = {}
        self.plans: list[dict[str, Any]] = []
        self.frames: list[np.ndarray] = []
        self.video = video
        self.every = max(1, round(sim.ads.world_hz / fps))
        self.fps = fps
        self._n = 0
        self._viewer = None
        self._screen, self._scaling = screen, scaling
        t_plan = sim.ads.topic("planning")
        sim.on_step.append(self._on_step)
        sim.bus.taps.append(lambda m: self.plans.append(m.payload) if m.topic == t_plan else None)

    def _on_step(self, sim: Any) -> None:
        w = sim.world
        e = w.ego
        self.t.append(w.time)
        self.ego.append((float(e.position[0]), float(e.position[1]), float(e.heading), float(e.speed)))
        for p in w.present_participants():
            self.parts.setdefault(p.id, []).append((w.time, float(p.obj.position[0]), float(p.obj.position[1])))
            self.kinds[p.id] = (p.kind, float(p.obj.LENGTH), float(p.obj.WIDTH))
        if self.video and self._n % self.every == 0:
            self.frames.append(self._grab(w))
        self._n += 1

    def _grab(self, world: Any) -> np.ndarray:
        os.environ.setdefault("SDL_VIDEODRIVER", "dummy")
        os.environ.setdefault("SDL_AUDIODRIVER", "dummy")
        os.environ.setdefault("PYGAME_HIDE_SUPPORT_PROMPT", "1")
        import pygame
        from highway_env.road.graphics import RoadGraphics, WorldSurface

        if self._viewer is None:
            pygame.display.init()
            pygame.font.init()
            surf = WorldSurface(self._screen, 0, pygame.Surface(self._screen))
            surf.scaling = self._scaling
            surf.centering_position = [0.5, 0.5]
            self._viewer = surf
        surf = self._viewer
        surf.move_display_window_to(world.ego.position)
        RoadGraphics.display(world.road, surf)
        RoadGraphics.display_road_objects(world.road, surf, offscreen=True)
        RoadGraphics.display_traffic(world.road, surf, simulation_frequency=20, offscreen=True)
        return np.moveaxis(pygame.surfarray.array3d(surf), 0, 1).copy()

    # -- outputs ------------------------------------------------------------------------------
    def save_video(self, path: Path | str) -> Path | None:
        """Write the frames as MP4 (imageio-ffmpeg) or, failing that, GIF. None without frames."""
        if not self.frames:
            return None
        import imageio.v2 as imageio

        path = Path(path)
        try:
            imageio.mimsave(path, self.frames, fps=self.fps, macro_block_size=1)
            return path
        except Exception:  # ffmpeg missing: fall back to GIF
            gif = path.with_suffix(".gif")
            imageio.mimsave(gif, self.frames, duration=1.0 / self.fps)
            return gif

    def save_plot(self, path: Path | str, title: str = "", collision: dict[str, Any] | None = None,
                  n_plans: int = 8) -> Path:
        """Top view: lanes, ego path coloured by speed, participants, a few planned trajectories."""
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt

        fig, ax = plt.subplots(figsize=(10, 7))
        draw_map(ax, self.roadmap)
        ego = np.array(self.ego) if self.ego else np.zeros((0, 4))
        if len(ego):
            sc = ax.scatter(ego[:, 0], ego[:, 1], c=ego[:, 3], cmap="viridis", s=4, zorder=3, label="ego path")
            fig.colorbar(sc, ax=ax, label="ego speed [m/s]", shrink=0.7)
            _box(ax, *ego[-1, :3], 4.8, 2.0, color="tab:red", alpha=0.9)
        for pid, pts in self.parts.items():
            arr = np.array(pts)
            kind, length, width = self.kinds[pid]
            color = {"static": "goldenrod", "scripted": "tab:purple", "reactive": "tab:green"}[kind]
            ax.plot(arr[:, 1], arr[:, 2], color=color, lw=1.2, alpha=0.7)
            if len(arr) > 1:
                h = float(np.arctan2(arr[-1, 2] - arr[-2, 2], arr[-1, 1] - arr[-2, 1]))
            else:
                h = 0.0
            _box(ax, arr[-1, 1], arr[-1, 2], h, length, width, color=color, alpha=0.8)
            ax.annotate(pid, (arr[-1, 1], arr[-1, 2]), fontsize=7, color=color)
        if self.plans:
            idx = np.linspace(0, len(self.plans) - 1, min(n_plans, len(self.plans))).astype(int)
            for i in idx:
                tr = self.plans[i]["trajectory"]
                ax.plot(tr["x"], tr["y"], color="tab:blue", lw=0.8, alpha=0.6)
            ax.plot([], [], color="tab:blue", lw=0.8, label="planned trajectories")
        if collision:
            ax.scatter([collision["x"]], [collision["y"]], marker="X", s=160, color="red", zorder=5,
                       label=f"collision with {collision['participant']} at {collision['time']:.1f} s")
        if len(ego):
            pad = 25.0
            xs = np.concatenate([ego[:, 0]] + [np.array(p)[:, 1] for p in self.parts.values()])
            ys = np.concatenate([ego[:, 1]] + [np.array(p)[:, 2] for p in self.parts.values()])
            ax.set_xlim(xs.min() - pad, xs.max() + pad)
            ax.set_ylim(ys.max() + pad, ys.min() - pad)  # highway-env: y points down
        ax.set_aspect("equal")
        ax.set_xlabel("x [m]")
        ax.set_ylabel("y [m] (down, as highway-env renders)")
        ax.set_title(title)
        ax.legend(loc="upper right", fontsize=8)
        fig.tight_layout()
        path = Path(path)
        fig.savefig(path, dpi=110)
        plt.close(fig)
        return path


def draw_map(ax: Any, roadmap: RoadMap) -> None:
    """Lane surfaces and centre lines of a road map."""
    for g in roadmap.geoms.values():
        s = np.linspace(0.0, g.length, max(2, int(g.length / 2.0) + 1))
        left, right = g.xy(s, -g.width / 2), g.xy(s, g.width / 2)
        poly = np.concatenate([left, right[::-1]])
        ax.fill(poly[:, 0], poly[:, 1], color="0.88", lw=0)
        c = g.xy(s)
        ax.plot(c[:, 0], c[:, 1], color="0.75", lw=0.5, ls="--")
    for sl in roadmap.stop_lines:
        g = roadmap.geom(sl.lane)
        a, b = g.xy(np.array(sl.s), -g.width / 2), g.xy(np.array(sl.s), g.width / 2)
        ax.plot([a[0], b[0]], [a[1], b[1]], color="k", lw=1.5)


def _box(ax: Any, x: float, y: float, h: float, length: float, width: float, **kw: Any) -> None:
    c, s = np.cos(h), np.sin(h)
    pts = np.array([[-length / 2, -width / 2], [length / 2, -width / 2], [length / 2, width / 2],
                    [-length / 2, width / 2]]) @ np.array([[c, s], [-s, c]]) + [x, y]
    ax.fill(pts[:, 0], pts[:, 1], zorder=4, **kw)
