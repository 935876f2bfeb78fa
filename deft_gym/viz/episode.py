"""Pictures of a recorded episode, drawn from its MCAP log alone: a plot and a video.

:func:`load_episode` reads what the pictures need: the lanes (the map message), the ego and
every participant with its id, kind and size (the scene topic, ground truth; logs without one
fall back on localization and perceived obstacles), the planned trajectories, and the outcome
with the collision (who, where, when). :func:`save_plot` draws the whole episode on one page
(tight bounds, legend outside, every participant in its own colour and labelled, the ego's path
coloured by speed, planned trajectories, the collision marker and time); :func:`save_video`
draws it frame by frame around the ego, with the time, the speeds and the ids.
:func:`render_path` takes a log, an adversary episode folder's ``episode.json`` or a folder of
them (what ``deft-gym render`` does).
"""

from __future__ import annotations

import contextlib
import json
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from deft_gym.bus.messages import NS_PER_S, SCENE_TOPIC, log_start_ns
from deft_gym.bus.ros1 import ChannelDecoders
from deft_gym.files import atomic_path

EPISODE_META, OUTCOME_META = "deft_gym.episode", "deft_gym.outcome"
EGO_COLOR, PLAN_COLOR, CRASH_COLOR = "#1f77b4", "#00a0e0", "#d62728"
# participants: one colour each, none of them the ego's blue or the crash's red
PALETTE = ["#2ca02c", "#ff7f0e", "#9467bd", "#8c564b", "#e377c2", "#17becf", "#bcbd22", "#7f7f7f",
           "#aec7e8", "#ffbb78", "#98df8a", "#c5b0d5"]


@dataclass
class Track:
    """One vehicle or object over time: rows ``(t [s], x, y [m], heading [rad], speed [m/s])``."""

    id: str
    kind: str
    length: float
    width: float
    rows: list[tuple[float, float, float, float, float]] = field(default_factory=list)

    def array(self) -> np.ndarray:
        return np.array(self.rows, dtype=float).reshape(-1, 5)

    def at(self, t: float) -> tuple[float, float, float, float] | None:
        """``(x, y, heading, speed)`` at ``t`` (linear between samples; None outside them)."""
        a = self.array()
        if not len(a) or t < a[0, 0] - 1e-9 or t > a[-1, 0] + 1e-9:
            return None
        i = int(np.searchsorted(a[:, 0], t))
        if i <= 0:
            return tuple(a[0, 1:])  # type: ignore[return-value]
        if i >= len(a):
            return tuple(a[-1, 1:])  # type: ignore[return-value]
        t0, t1 = a[i - 1, 0], a[i, 0]
        w = 0.0 if t1 <= t0 else (t - t0) / (t1 - t0)
        h0, h1 = a[i - 1, 3], a[i, 3]
        dh = math.atan2(math.sin(h1 - h0), math.cos(h1 - h0))
        x, y, v = (a[i - 1, [1, 2, 4]] * (1 - w) + a[i, [1, 2, 4]] * w).tolist()
        return x, y, h0 + w * dh, v


@dataclass
class Episode:
    """What the pictures of one episode need (see the module docstring)."""

    log: Path
    scenario: str
    jitter_seed: int | None
    outcome: str
    sim_time: float
    collision: dict[str, Any] | None
    lanes: list[tuple[np.ndarray, float]]  # centre line (n, 2), width [m]
    stop_lines: list[tuple[float, float, float, float]]
    ego: Track
    participants: dict[str, Track]
    plans: list[tuple[float, np.ndarray, np.ndarray]]  # (frame time [s], x, y)
    source: str  # "scene" (ground truth) or "perception"
    verdict: dict[str, Any] | None = None  # an adversary episode's episode.json

    @property
    def failure(self) -> str | None:
        """``collision``, ``nods`` (an adversary's non-optimal decision) or None."""
        if self.verdict and self.verdict.get("failure"):
            return str(self.verdict["failure"])
        return "collision" if self.collision else None

    def title(self) -> str:
        what = self.outcome
        if self.collision:
            what = f"collision with {self.collision.get('participant')} at {float(self.collision['time']):.2f} s"
        elif self.failure:
            what = f"{self.failure} ({self.outcome})"
        seed = f", jitter seed {self.jitter_seed}" if self.jitter_seed is not None else ""
        return f"{self.scenario}: {what}{seed}"


def load_episode(log: Path | str) -> Episode:
    """Read an episode log (see the module docstring). ValueError names the file when it is not
    a readable MCAP log."""
    from mcap.reader import make_reader

    from deft_gym.record import read_metadata

    log = Path(log)
    try:
        meta = read_metadata(log)
    except Exception as exc:  # not MCAP, damaged summary: one line naming the file
        raise ValueError(f"{log}: cannot read the log: {type(exc).__name__}: {exc}") from None
    ep = {k: _json(v) for k, v in meta.get(EPISODE_META, {}).items()}
    oc = {k: _json(v) for k, v in meta.get(OUTCOME_META, {}).items()}
    start = log_start_ns(ep)
    topics = ep.get("topics") or {}
    t_loc, t_obs = topics.get("localization", "/apollo/localization/pose"), topics.get(
        "perception_obstacles", "/apollo/perception/obstacles")
    t_plan, t_map = topics.get("planning", "/apollo/planning"), topics.get("map", "/deft_gym/map")
    ego_size = ep.get("ego") or {}
    ego = Track("ego", "ego", float(ego_size.get("length", 4.8)), float(ego_size.get("width", 2.0)))
    scene_parts: dict[str, Track] = {}
    seen_parts: dict[str, Track] = {}
    loc_rows: list[tuple[float, float, float, float, float]] = []
    plans: list[tuple[float, np.ndarray, np.ndarray]] = []
    lanes: list[tuple[np.ndarray, float]] = []
    stops: list[tuple[float, float, float, float]] = []
    scene_ego: list[tuple[float, float, float, float, float]] = []
    from mcap.stream_reader import CRCValidationError

    with open(log, "rb") as f:
        messages = make_reader(f, validate_crcs=True).iter_messages()  # a flipped bit is not drawn as good
        decode = ChannelDecoders()
        for schema, channel, msg in _crc_checked(messages, log, CRCValidationError):
            topic = channel.topic
            if topic not in (SCENE_TOPIC, t_loc, t_obs, t_plan, t_map):
                continue
            t = (msg.log_time - start) / NS_PER_S
            try:
                p = decode(schema, channel, msg.data)
            except ValueError:
                continue
            if topic == SCENE_TOPIC:
                _scene(p, t, scene_ego, scene_parts)
            elif topic == t_loc:
                loc_rows.append((t, _f(p.get("x")), _f(p.get("y")), _f(p.get("heading")), _f(p.get("v"))))
            elif topic == t_obs:
                for o in p.get("obstacles") or []:
                    oid = f"obstacle {o.get('id')}"
                    tr = seen_parts.setdefault(oid, Track(oid, str(o.get("type", "?")).lower(), _f(o.get("length")),
                                                          _f(o.get("width"))))
                    tr.rows.append((t, _f(o.get("x")), _f(o.get("y")), _f(o.get("heading")), _f(o.get("v"))))
            elif topic == t_plan:
                tr = (p or {}).get("trajectory") or {}
                with contextlib.suppress(KeyError, TypeError, ValueError):
                    plans.append((_f((p.get("header") or {}).get("stamp", t)), _finite(np.asarray(tr["x"], float)),
                                  _finite(np.asarray(tr["y"], float))))
            elif topic == t_map and not lanes:
                lanes, stops = _map(p)
    source = "scene" if scene_parts or scene_ego else "perception"
    ego.rows = loc_rows or scene_ego
    coll = oc.get("collision") if isinstance(oc.get("collision"), dict) else None
    seed = ep.get("jitter_seed")
    return Episode(log, str(ep.get("scenario_name") or log.parent.name), seed if isinstance(seed, int) else None,
                   str(oc.get("outcome", "unknown")), _f(oc.get("sim_time", ego.rows[-1][0] if ego.rows else 0.0)),
                   coll, lanes, stops, ego, scene_parts if source == "scene" else seen_parts, plans, source)


def _crc_checked(messages: Any, log: Path, crc_error: type[Exception]) -> Any:
    """The log's messages; a chunk that fails its CRC is a one-line ValueError naming the file."""
    try:
        yield from messages
    except crc_error as exc:
        raise ValueError(f"{log}: damaged log ({exc}); deft-gym verify {log} says where") from None


def _json(v: str) -> Any:
    try:
        return json.loads(v)
    except ValueError:
        return v


def _f(v: Any) -> float:
    """A number to draw: NaN (not drawn) for what is no finite number - an infinite heading in a
    stress finding's log used to end its plot and video with "math domain error"."""
    try:
        x = float(v)
    except (TypeError, ValueError, OverflowError):
        return float("nan")
    return x if math.isfinite(x) else float("nan")


def _finite(a: np.ndarray) -> np.ndarray:
    """``a`` with every non-finite value NaN (matplotlib leaves NaN points out)."""
    return np.where(np.isfinite(a), a, np.nan)


def _scene(p: dict[str, Any], t: float, ego: list[Any], parts: dict[str, Track]) -> None:
    """Ego and participant rows from one SceneUpdate (y and headings negated back)."""
    for ent in p.get("entities") or []:
        eid = str(ent.get("id", ""))
        cubes = ent.get("cubes") or []
        if not cubes or not (eid == "ego" or eid.startswith("participant/")):
            continue
        c = cubes[0]
        pos, q = c["pose"]["position"], c["pose"]["orientation"]
        heading = -2.0 * math.atan2(_f(q.get("z")), _f(q.get("w")))
        kind = next((kv["value"] for kv in ent.get("metadata") or [] if kv.get("key") == "kind"), "?")
        text = ((ent.get("texts") or [{}])[0]).get("text", "")
        speed = _f(text.rsplit(" ", 2)[-2]) if text.endswith("m/s") else float("nan")
        row = (t, _f(pos["x"]), -_f(pos["y"]), heading, speed)
        if eid == "ego":
            ego.append(row)
        else:
            pid = eid.split("/", 1)[1]
            tr = parts.setdefault(pid, Track(pid, kind, _f(c["size"]["x"]), _f(c["size"]["y"])))
            tr.rows.append(row)


def _map(p: dict[str, Any]) -> tuple[list[tuple[np.ndarray, float]], list[tuple[float, float, float, float]]]:
    lanes = []
    widths: dict[str, float] = {}
    for lane in p.get("lanes") or []:
        try:
            xy = _finite(np.column_stack([np.asarray(lane["x"], float), np.asarray(lane["y"], float)]))
            lanes.append((xy, _f(lane["width"])))
            widths[json.dumps(lane["id"])] = float(lane["width"])
        except (KeyError, TypeError, ValueError):
            continue
    stops = []
    for sl in p.get("stop_lines") or []:
        try:
            key = json.dumps(sl["lane"])
            xy = next(xy for (xy, _), lane in zip(lanes, p["lanes"]) if json.dumps(lane["id"]) == key)
            i = int(np.argmin(np.hypot(xy[:, 0] - float(sl["x"]), xy[:, 1] - float(sl["y"]))))
            d = xy[min(i + 1, len(xy) - 1)] - xy[max(i - 1, 0)]
            stops.append((float(sl["x"]), float(sl["y"]), widths.get(key, 3.5), math.atan2(d[1], d[0])))
        except (KeyError, TypeError, ValueError, StopIteration):
            continue
    return lanes, stops


# -- drawing ------------------------------------------------------------------------------------------
def _edges(xy: np.ndarray, width: float) -> np.ndarray:
    """The lane's outline as a polygon (centre line offset by +-width/2 along its normals)."""
    d = np.gradient(xy, axis=0) if len(xy) > 2 else np.repeat(xy[1:] - xy[:1], len(xy), axis=0)
    n = np.column_stack([-d[:, 1], d[:, 0]])
    n /= np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-9)
    left, right = xy + n * width / 2, xy - n * width / 2
    return np.concatenate([left, right[::-1]])


def draw_lanes(ax: Any, ep: Episode) -> None:
    """Lane surfaces, centre lines and stop lines."""
    for xy, w in ep.lanes:
        poly = _edges(xy, w)
        ax.fill(poly[:, 0], poly[:, 1], color="0.90", lw=0, zorder=0)
        ax.plot(xy[:, 0], xy[:, 1], color="0.78", lw=0.5, ls="--", zorder=1)
    for x, y, w, h in ep.stop_lines:  # across the lane
        dx, dy = -math.sin(h) * w / 2, math.cos(h) * w / 2
        ax.plot([x - dx, x + dx], [y - dy, y + dy], color="k", lw=2, zorder=1)


def _box(x: float, y: float, h: float, length: float, width: float) -> np.ndarray:
    c, s = math.cos(h), math.sin(h)
    pts = np.array([[-length / 2, -width / 2], [length / 2, -width / 2], [length / 2, width / 2],
                    [-length / 2, width / 2]])
    return pts @ np.array([[c, s], [-s, c]]) + [x, y]


def colors(ep: Episode) -> dict[str, str]:
    """One colour per participant, in id order."""
    return {pid: PALETTE[i % len(PALETTE)] for i, pid in enumerate(sorted(ep.participants))}


def _pyplot() -> Any:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def _bounds(ep: Episode, pad: float = 10.0) -> tuple[float, float, float, float]:
    """Tight bounds: the ego's path, the participants it came within 60 m of, the collision."""
    ego = ep.ego.array()
    pts = [ego[:, 1:3]] if len(ego) else []
    for tr in ep.participants.values():
        a = tr.array()
        if not len(a):
            continue
        if len(ego):
            d = np.min(np.hypot(a[:, 1:2] - ego[None, ::10, 1], a[:, 2:3] - ego[None, ::10, 2]))
            if d > 60.0:
                continue
        pts.append(a[:, 1:3])
    if ep.collision:
        pts.append(np.array([[float(ep.collision["x"]), float(ep.collision["y"])]]))
    allp = np.concatenate(pts) if pts else np.zeros((1, 2))
    allp = allp[np.all(np.isfinite(allp), axis=1)]
    if not len(allp):
        allp = np.zeros((1, 2))
    x0, y0 = allp.min(axis=0) - pad
    x1, y1 = allp.max(axis=0) + pad
    w, h = x1 - x0, y1 - y0  # no strips: at most 2.5:1 either way
    if h > 2.5 * w:
        x0, x1 = (x0 + x1) / 2 - h / 5, (x0 + x1) / 2 + h / 5
    elif w > 2.5 * h:
        y0, y1 = (y0 + y1) / 2 - w / 5, (y0 + y1) / 2 + w / 5
    return float(x0), float(x1), float(y0), float(y1)


def save_plot(ep: Episode, path: Path | str, title: str | None = None, n_plans: int = 6) -> Path:
    """The whole episode on one page (see the module docstring); returns ``path`` (PNG)."""
    plt = _pyplot()
    from matplotlib.collections import LineCollection

    x0, x1, y0, y1 = _bounds(ep)
    aspect = (y1 - y0) / max(x1 - x0, 1e-6)
    width = 9.0
    fig, ax = plt.subplots(figsize=(width, float(np.clip(width * aspect * 0.75 + 1.2, 3.2, 9.0))))
    draw_lanes(ax, ep)
    ego = ep.ego.array()
    ok = np.all(np.isfinite(ego[:, 1:3]), axis=1) if len(ego) else np.zeros(0, bool)
    ego = ego[ok]
    if len(ego) > 1:
        seg = np.stack([ego[:-1, 1:3], ego[1:, 1:3]], axis=1)
        lc = LineCollection(seg, cmap="viridis", linewidths=3, zorder=3)
        lc.set_array(np.nan_to_num(ego[:-1, 4]))
        ax.add_collection(lc)
        cb = fig.colorbar(lc, ax=ax, pad=0.01, fraction=0.03)
        cb.set_label("ego speed [m/s]")
    t_end = float(ep.collision["time"]) if ep.collision else (ego[-1, 0] if len(ego) else 0.0)
    plans = [p for p in ep.plans if p[0] <= t_end + 1e-6]
    if plans:
        idx = np.unique(np.linspace(0, len(plans) - 1, min(n_plans, len(plans))).astype(int))
        for j, i in enumerate(idx):
            _, px, py = plans[i]
            ax.plot(px, py, color=PLAN_COLOR, lw=1.0, alpha=0.5, zorder=2,
                    label="planned trajectories" if j == 0 else None)
        _, px, py = plans[-1]
        ax.plot(px, py, color=PLAN_COLOR, lw=2.2, zorder=4, label=f"last plan (t={plans[-1][0]:.2f} s)")
    if len(ego):
        end = ep.ego.at(t_end) or tuple(ego[-1, 1:])
        poly = _box(end[0], end[1], end[2], ep.ego.length, ep.ego.width)
        ax.fill(poly[:, 0], poly[:, 1], color=EGO_COLOR, zorder=5, label=f"ego (at {t_end:.1f} s)")
        ax.annotate("ego", (end[0], end[1]), xytext=(0, 9), textcoords="offset points", ha="center", fontsize=8,
                    color=EGO_COLOR, weight="bold", zorder=9)
    col = colors(ep)
    for pid, tr in sorted(ep.participants.items()):
        a = tr.array()
        a = a[np.all(np.isfinite(a[:, 1:3]), axis=1)]
        if not len(a):
            continue
        c = col[pid]
        if np.ptp(a[:, 1]) + np.ptp(a[:, 2]) > 0.5:
            ax.plot(a[:, 1], a[:, 2], color=c, lw=1.2, ls=":", zorder=3)
        pose = tr.at(min(t_end, a[-1, 0])) or tuple(a[-1, 1:])
        poly = _box(pose[0], pose[1], pose[2], tr.length, tr.width)
        hit = ep.collision and str(ep.collision.get("participant")) == pid
        ax.fill(poly[:, 0], poly[:, 1], color=c, zorder=5, ec=CRASH_COLOR if hit else "none", lw=2 if hit else 0,
                label=f"{pid} ({tr.kind})")
        ax.annotate(pid, (pose[0], pose[1]), xytext=(0, -14), textcoords="offset points", ha="center", fontsize=8,
                    color=c, weight="bold", zorder=9)  # below its box; the ego's label is above
    if ep.collision:
        cx, cy = float(ep.collision["x"]), float(ep.collision["y"])
        ax.scatter([cx], [cy], marker="X", s=150, color=CRASH_COLOR, edgecolor="white", alpha=0.85, zorder=8,
                   label=f"collision with {ep.collision.get('participant')} at {float(ep.collision['time']):.2f} s")
    ax.set_xlim(x0, x1)
    ax.set_ylim(y1, y0)  # highway-env: y points down on screen
    ax.set_aspect("equal")
    ax.set_xlabel("x [m]")
    ax.set_ylabel("y [m]")
    ax.set_title(title or ep.title(), fontsize=10)
    ax.legend(loc="upper left", bbox_to_anchor=(1.12, 1.0), fontsize=8, frameon=False, borderaxespad=0.0)
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    with atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=110, bbox_inches="tight")
    plt.close(fig)
    return path


def save_video(ep: Episode, path: Path | str, fps: int = 5, span: float = 70.0, max_seconds: float | None = None) -> Path:
    """The episode frame by frame around the ego (MP4; GIF when ffmpeg is missing), with the
    time, the ego's speed, every participant's id and speed, the plan in force and the collision.
    ``max_seconds``: only the last so many simulated seconds (None: all)."""
    plt = _pyplot()
    import imageio.v2 as imageio

    ego = ep.ego.array()
    if not len(ego):
        raise ValueError(f"{ep.log}: no ego poses to draw")
    t_end = float(ep.collision["time"]) if ep.collision else float(ego[-1, 0])
    t_start = float(ego[0, 0]) if max_seconds is None else max(float(ego[0, 0]), t_end - max_seconds)
    times = np.arange(t_start, t_end + 1e-9, 1.0 / fps)
    if ep.collision:
        times = np.concatenate([times, np.full(2 * fps, t_end)])  # hold the collision for 2 s
    fig, ax = plt.subplots(figsize=(7.2, 4.3), dpi=100)
    fig.subplots_adjust(0.01, 0.01, 0.99, 0.90)
    draw_lanes(ax, ep)
    ax.set_aspect("equal")
    ax.set_xticks([])
    ax.set_yticks([])
    col = colors(ep)
    ego_patch = ax.fill([0], [0], color=EGO_COLOR, zorder=5)[0]
    ego_txt = ax.text(0, 0, "", fontsize=8, color=EGO_COLOR, weight="bold", ha="center", zorder=7)
    plan_line, = ax.plot([], [], color=PLAN_COLOR, lw=2, zorder=4)
    parts = {pid: (ax.fill([0], [0], color=col[pid], zorder=5)[0],
                   ax.text(0, 0, "", fontsize=8, color=col[pid], weight="bold", ha="center", zorder=7))
             for pid in ep.participants}
    crash = ax.scatter([], [], marker="X", s=260, color=CRASH_COLOR, edgecolor="white", zorder=8)
    header = fig.suptitle("", fontsize=10, x=0.02, ha="left")
    plan_t = np.array([p[0] for p in ep.plans]) if ep.plans else np.zeros(0)
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    frames = []
    for t in times:
        pose = ep.ego.at(float(t)) or tuple(ego[-1, 1:])
        ex, ey = pose[0], pose[1]
        if not (math.isfinite(ex) and math.isfinite(ey)):
            continue
        ego_patch.set_xy(_box(ex, ey, pose[2], ep.ego.length, ep.ego.width))
        ego_txt.set_position((ex, ey - 3.0))
        ego_txt.set_text("ego")
        for pid, (patch, txt) in parts.items():
            ppose = ep.participants[pid].at(float(t))
            visible = ppose is not None and math.isfinite(ppose[0])
            patch.set_visible(visible)
            txt.set_visible(visible)
            if visible:
                tr = ep.participants[pid]
                patch.set_xy(_box(ppose[0], ppose[1], ppose[2], tr.length, tr.width))
                txt.set_position((ppose[0], ppose[1] - 3.0))
                txt.set_text(pid if not math.isfinite(ppose[3]) else f"{pid} {ppose[3]:.1f} m/s")
        k = int(np.searchsorted(plan_t, t, side="right")) - 1
        if k >= 0:
            plan_line.set_data(ep.plans[k][1], ep.plans[k][2])
        hit = ep.collision is not None and t >= t_end - 1e-9
        if hit:
            crash.set_offsets([[float(ep.collision["x"]), float(ep.collision["y"])]])
        ax.set_xlim(ex - span / 2, ex + span / 2)
        ax.set_ylim(ey + span * 0.3, ey - span * 0.3)
        text = f"{ep.scenario}   t = {t:5.2f} s   ego {pose[3]:.1f} m/s"
        if hit:
            text += f"   COLLISION with {ep.collision.get('participant')} at {t_end:.2f} s"
        header.set_text(text)
        header.set_color(CRASH_COLOR if hit else "black")
        fig.canvas.draw()
        frames.append(np.asarray(fig.canvas.buffer_rgba())[:, :, :3].copy())
    plt.close(fig)
    try:
        with atomic_path(path) as tmp:
            imageio.mimsave(tmp, frames, fps=fps, macro_block_size=1)
        out = path
    except Exception:  # no ffmpeg: a GIF
        out = path.with_suffix(".gif")
        with atomic_path(out) as tmp:
            imageio.mimsave(tmp, frames, duration=1.0 / fps)
    if frames:  # the picture a page shows before the video plays: the collision, else the start
        # (written after the video: a kill while the video is written leaves neither picture)
        with atomic_path(poster_path(path)) as tmp:
            imageio.imwrite(tmp, frames[-1] if ep.collision else frames[0], format="png")
    return out


def poster_path(video: Path | str) -> Path:
    """The poster frame (PNG) of a video: ``video.mp4`` -> ``video_poster.png`` beside it."""
    video = Path(video)
    return video.with_name(f"{video.stem}_poster.png")


def ensure_poster(video: Path | str) -> Path | None:
    """The poster frame of ``video``, taken from the video's last frame when it has none yet (a
    video drawn before posters were); None when the video cannot be read."""
    import imageio.v2 as imageio

    poster = poster_path(video)
    if poster.exists():
        return poster
    try:
        frames = imageio.mimread(video, memtest=False)
    except Exception:  # no reader for it (no ffmpeg), or a damaged file
        return None
    if not frames:
        return None
    with atomic_path(poster) as tmp:
        imageio.imwrite(tmp, frames[-1], format="png")
    return poster


# -- what deft-gym render does ------------------------------------------------------------------------
def find_logs(path: Path | str) -> list[Path]:
    """The logs a render input names: a log, the log beside an ``episode.json``, or every log
    under a folder (sorted). ValueError when there is none."""
    path = Path(path)
    if path.is_file() and path.suffix == ".mcap":
        return [path]
    if path.is_file() and path.name.endswith(".json"):
        log = path.with_name("episode.mcap")
        if not log.exists():
            raise ValueError(f"{path}: no episode.mcap beside it")
        return [log]
    if path.is_dir():
        logs = sorted(p for p in path.rglob("*.mcap") if p.is_file())
        if not logs:
            raise ValueError(f"{path}: no .mcap logs under it")
        return logs
    raise ValueError(f"{path}: not an episode log (.mcap), an episode.json or a folder")


def picture_paths(log: Path, out: Path | None = None, root: Path | None = None) -> tuple[Path, Path]:
    """Where the plot and the video of ``log`` go: beside it (``plot.png``, ``video.mp4`` for an
    ``episode.mcap``, ``<stem>.png``/``.mp4`` otherwise), or under ``out`` mirroring ``root``."""
    stem = "" if log.name == "episode.mcap" else log.stem
    base = log.parent if out is None else out / (log.parent.relative_to(root) if root and root.is_dir() else Path())
    if stem:
        return base / f"{stem}.png", base / f"{stem}.mp4"
    return base / "plot.png", base / "video.mp4"


def render_log(log: Path, out: Path | None = None, root: Path | None = None, video: bool = True,
               only_failures: bool = False) -> dict[str, Any] | None:
    """Plot (and video) of one log; what was written, or None when ``only_failures`` and the
    episode did not fail."""
    ep = load_episode(log)
    verdict = log.with_name("episode.json")
    if verdict.exists():
        with contextlib.suppress(ValueError):
            ep.verdict = json.loads(verdict.read_text())
    if only_failures and not ep.failure:
        return None
    plot, vid = picture_paths(log, out, root)
    done: dict[str, Any] = {"log": str(log), "failure": ep.failure, "title": ep.title()}
    done["video"] = str(save_video(ep, vid)) if video else None  # the plot last: it says both are done
    done["plot"] = str(save_plot(ep, plot))
    return done


def render_failures(root: Path | str, video: bool = True, progress: Any = None) -> list[dict[str, Any]]:
    """Pictures of every failing episode under ``root`` that has none yet (the hook of training,
    evaluation, stress campaigns and extraction); ``progress(done, total)`` reports."""
    root = Path(root)
    logs = sorted(p for p in root.rglob("*.mcap") if p.is_file()) if root.is_dir() else []
    out = []
    for i, log in enumerate(logs):
        plot, _ = picture_paths(log)
        if not plot.exists():
            try:
                done = render_log(log, video=video, only_failures=True)
            except ValueError:
                done = None
            if done:
                out.append(done)
        if progress is not None:
            progress(i + 1, len(logs))
    return out
