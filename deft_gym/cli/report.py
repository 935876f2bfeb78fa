"""One HTML page for a run folder: headline numbers, tables, curves, a card per failure.

    deft-gym report runs/demo                      # -> runs/demo/report.html
    deft-gym report runs/adversary/main            # a training run
    deft-gym report runs/adversary/eval            # an evaluation
    deft-gym report runs/stress/off                # a robustness campaign
    deft-gym report runs/lt_tests                  # an extraction (deft-gym extract)

The folder and its sub-folders are recognised by what they hold: the demo (``demo.json``), a
run of reruns (``deft-gym run``), an extraction, a training run, an evaluation, a stress
campaign. Each gets a section: its headline numbers, its tables, its plots (training curves
from ``progress.jsonl``; the evaluation's cumulative-failure and per-scenario plots), and a card
per failure with its picture and video (drawn now when missing), the command that replays it
and the pytest command of its extracted test. Plots are embedded in the page (data URIs);
videos and links point at files in the run folder, relative to the page, so the page is
self-contained within its folder (no network, no scripts).
"""

from __future__ import annotations

import base64
import html
import json
import shlex
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from deft_gym.cli import common

MAX_CARDS = 24  # failure cards per section (the rest are counted)
ORDER = ["flaky", "reruns", "reruns_tests", "train", "eval"]  # the demo's folders in the order of its story
STYLE = """
body{font-family:system-ui,-apple-system,Segoe UI,Roboto,sans-serif;margin:0;background:#f6f7f9;color:#1d2733}
header{background:#15324d;color:#fff;padding:18px 28px}header h1{margin:0 0 4px;font-size:22px}
header p{margin:0;opacity:.8;font-size:13px}main{padding:8px 28px 40px;max-width:1280px}
section{background:#fff;border-radius:8px;padding:14px 20px;margin:18px 0;box-shadow:0 1px 3px #0002;overflow-x:auto}
h2{font-size:18px;margin:4px 0 10px}h3{font-size:15px;margin:14px 0 6px}
.kpis{display:flex;flex-wrap:wrap;gap:10px;margin:8px 0}.kpi{background:#eef3f8;border-radius:6px;padding:8px 12px;
min-width:120px}.kpi b{display:block;font-size:20px}.kpi span{font-size:12px;color:#4a5a6a}
table{border-collapse:collapse;font-size:13px;margin:6px 0}td,th{border-bottom:1px solid #dde3ea;padding:3px 9px;
text-align:right}th{background:#f0f3f6}td:first-child,th:first-child{text-align:left}
.cards{display:grid;grid-template-columns:repeat(auto-fill,minmax(380px,1fr));gap:14px}
.card{border:1px solid #dde3ea;border-radius:6px;padding:10px;background:#fcfdfe}.card img{width:100%}
.card video{width:100%;margin-top:6px;background:#fff}code,pre{background:#eef1f4;border-radius:4px;font-size:12px}
pre{padding:6px 8px;white-space:pre-wrap;word-break:break-all;margin:4px 0}.bad{color:#c0392b}.good{color:#1e8449}
.note{font-size:13px;color:#4a5a6a}img.plot{max-width:100%;border:1px solid #eee}
"""


@dataclass
class Page:
    """The page being built: its folder (links are relative to it) and its parts."""

    root: Path
    out: Path
    draw: bool = True
    parts: list[str] = field(default_factory=list)
    kpis: list[tuple[str, str]] = field(default_factory=list)

    def rel(self, path: Path | str) -> str:
        """A link to ``path`` relative to the page."""
        p = Path(path).resolve()
        try:
            return p.relative_to(self.out.parent.resolve()).as_posix()
        except ValueError:
            import os

            return Path(os.path.relpath(p, self.out.parent.resolve())).as_posix()


# -- small HTML helpers ---------------------------------------------------------------------------
def esc(x: Any) -> str:
    return html.escape(str(x), quote=True)


def kpis(items: list[tuple[str, Any]]) -> str:
    return '<div class="kpis">' + "".join(f'<div class="kpi"><b>{esc(v)}</b><span>{esc(k)}</span></div>'
                                          for k, v in items) + "</div>"


def table(head: list[str], rows: list[list[Any]]) -> str:
    h = "".join(f"<th>{esc(c)}</th>" for c in head)
    body = "".join("<tr>" + "".join(f"<td>{esc(c)}</td>" for c in r) + "</tr>" for r in rows)
    return f"<table><thead><tr>{h}</tr></thead><tbody>{body}</tbody></table>"


def img_data(path: Path, alt: str, cls: str = "plot") -> str:
    """An image embedded as a data URI (the page needs no file for it)."""
    data = base64.b64encode(Path(path).read_bytes()).decode()
    return f'<img class="{cls}" alt="{esc(alt)}" src="data:image/png;base64,{data}">'


def fig_data(fig: Any, alt: str) -> str:
    import io

    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=100, bbox_inches="tight")
    import matplotlib.pyplot as plt

    plt.close(fig)
    return f'<img class="plot" alt="{esc(alt)}" src="data:image/png;base64,{base64.b64encode(buf.getvalue()).decode()}">'


def cmd(words: list[str]) -> str:
    return f"<pre>{esc(' '.join(shlex.quote(str(w)) for w in words))}</pre>"


def markdown(text: str) -> str:
    """The little markdown the project's reports use: headings, tables, paragraphs."""
    out, rows = [], []

    def flush() -> None:
        if rows:
            cells = [[c.strip() for c in r.strip().strip("|").split("|")] for r in rows
                     if not set(r.replace("|", "").strip()) <= set("-: ")]
            if cells:
                out.append(table(cells[0], cells[1:]))
            rows.clear()

    for line in text.splitlines():
        if line.strip() in ("<details>", "</details>") or line.strip().startswith("<details><summary>"):
            flush()
            out.append(line.strip())  # the collapsible blocks of the project's own reports
            continue
        if line.lstrip().startswith("|"):
            rows.append(line)
            continue
        flush()
        if line.startswith("#"):
            level = min(len(line) - len(line.lstrip("#")) + 1, 4)
            out.append(f"<h{level}>{esc(line.lstrip('#').strip())}</h{level}>")
        elif line.strip():
            out.append(f'<p class="note">{esc(line.replace("**", ""))}</p>')
    flush()
    return "\n".join(out)


def read_json(path: Path) -> Any:
    try:
        return json.loads(path.read_text())
    except (OSError, ValueError):
        return None


# -- failure cards ---------------------------------------------------------------------------------
def card(page: Page, title: str, log: Path | None, replay: list[str] | None, test: Path | None,
         note: str = "", pictures: Path | None = None, collision: bool = True) -> str:
    """One failure: its picture and video (drawn when missing), replay and pytest commands."""
    parts = [f"<h3>{esc(title)}</h3>"]
    if note:
        parts.append(f'<p class="note">{esc(note)}</p>')
    plot = video = None
    if log is not None and log.exists():
        from deft_gym.viz.episode import picture_paths

        plot, video = picture_paths(log) if pictures is None else (pictures / "plot.png", pictures / "video.mp4")
        if page.draw and not plot.exists():
            try:
                from deft_gym.viz.episode import load_episode, save_plot, save_video

                ep = load_episode(log)
                video = save_video(ep, video)  # the plot last: it says both are done
                save_plot(ep, plot)
            except ValueError as err:
                parts.append(f'<p class="note">no picture: {esc(err)}</p>')
    if plot is not None and plot.exists():
        parts.append(img_data(plot, f"plot of {title}"))
    if video is not None and not video.exists() and video.with_suffix(".gif").exists():
        video = video.with_suffix(".gif")
    if video is not None and video.exists():
        if video.suffix == ".gif":
            parts.append(f'<a href="{esc(page.rel(video))}">animation (GIF)</a>')
        else:
            from deft_gym.viz.episode import ensure_poster

            poster = ensure_poster(video) if page.draw else None
            poster = poster if poster is not None and poster.exists() else None
            attr = f' poster="{esc(page.rel(poster))}"' if poster else ""
            parts.append(f'<video controls preload="metadata"{attr} src="{esc(page.rel(video))}"></video>'
                         f'<p class="note"><a href="{esc(page.rel(video))}">video</a>'
                         + (f' · <a href="{esc(page.rel(log))}">log (MCAP, opens in Foxglove)</a>' if log else "")
                         + "</p>")
    if log is not None:
        parts.append(export_links(page, log))
    if replay:
        parts.append('<p class="note">replay the system-level run:</p>' + cmd(replay))
    if test is not None:
        what = ("run its planning-module test (fails while the planner still plans the collision):" if collision
                else "run its planning-module tests (they replay every frame of this episode):")
        parts.append(f'<p class="note">{what}</p>' + cmd(["pytest", "-q", common.shown(test)]))
    return '<div class="card">' + "".join(parts) + "</div>"


def export_links(page: Page, log: Path) -> str:
    """Links to the failure's exports beside its log (``deft-gym export``), or the command that
    writes them."""
    from deft_gym.export.failures import existing_exports

    names = {"xosc": "OpenSCENARIO", "xodr": "OpenDRIVE", "commonroad": "CommonRoad"}
    have = existing_exports(log)
    if not have:
        return '<p class="note">export it (OpenSCENARIO, CommonRoad):</p>' + cmd(["deft-gym", "export", common.shown(log)])
    links = " · ".join(f'<a href="{esc(page.rel(p))}">{names[k]} ({esc(p.name)})</a>' for k, p in have.items())
    return f'<p class="note">exported: {links}</p>'


def cards(items: list[str], total: int) -> str:
    more = f'<p class="note">{total - len(items)} more not shown.</p>' if total > len(items) else ""
    return '<div class="cards">' + "".join(items) + "</div>" + more


def _tests_in(folder: Path) -> Path | None:
    found = sorted(folder.glob("test_*.py")) if folder.is_dir() else []
    return found[0] if found else None


# -- the kinds of run folder -----------------------------------------------------------------------
def kind_of(folder: Path) -> str | None:
    """What a folder holds (None: nothing this report knows)."""
    if (folder / "demo.json").exists():
        return "demo"
    if (folder / "records.jsonl").exists() and (folder / "eval_config.json").exists():
        return "evaluation"
    if (folder / "config.yaml").exists() and list(folder.glob("episodes-*.jsonl")):
        return "training"
    s = read_json(folder / "summary.json")
    if isinstance(s, dict):
        if "reruns" in s and "scenario" in s:
            return "run"
        if str(s.get("format", "")).startswith("deft_gym.extraction-batch") or "frames_path" in s:
            return "extraction"
        if "crashes" in s and "hangs" in s:
            return "stress"
    return None


def section_run(page: Page, folder: Path, s: dict[str, Any]) -> str:
    reruns = s["reruns"]
    coll = [r for r in reruns if r.get("collision")]
    agg = s.get("metrics") or {}
    head = kpis([("reruns", len(reruns)), ("collided", f"{len(coll)} of {len(reruns)}"),
                 ("sim speed", f"{s.get('sim_speed') or 0:.0f}x real time")]
                + ([("mean driving score", f"{agg['mean_score']:.3f}")] if agg.get("mean_score") is not None else []))
    from deft_gym.cli.run import compared

    rows = [[r["rerun"], r["outcome"], (r.get("collision_detail") or {}).get("participant", ""),
             r["jitter_seed"], f"{r['sim_time']:.1f}",
             compared(r, reruns[0]) or f"{r['divergence']['identical']} of {r['divergence']['paired']}",
             *quality(r.get("metrics"))]
            for r in reruns]
    body = table(["rerun", "outcome", "hit", "jitter seed", "sim s", "plans identical to rerun 0", "score",
                  "violations (docs/metrics.md)"], rows)
    body += ('<p class="note">Plans are compared with rerun 0\'s only for reruns with its outcome; a rerun with '
             "another outcome drove elsewhere once they parted.</p>")
    items = []
    for r in coll[:MAX_CARDS]:
        log = Path(r["log"]) if r.get("log") else folder / str(r["rerun"]) / "episode.mcap"
        c = r["collision_detail"]
        scen = _scenario_arg(s.get("scenario_file"), s["scenario"])
        replay = ["deft-gym", "run", scen, "--reruns", "1", "--jitter-seed",
                  str(r["jitter_seed"]), "--out", f"runs/replay/{s['scenario']}-{r['jitter_seed']}"]
        test = None
        for cand in (folder.parent / f"{folder.name}_tests" / str(r["rerun"]), folder / str(r["rerun"]) / "deft"):
            test = test or _tests_in(cand)
        score = quality(r.get("metrics"))
        items.append(card(page, f"rerun {r['rerun']}: collision with {c['participant']} at {c['time']:.2f} s"
                          + (f"; score {score[0]}, {score[1]}" if r.get("metrics") else ""), log, replay, test))
    return (f"<h2>System-level reruns: {esc(s['scenario'])}</h2>{head}"
            f'<p class="note">The same scenario rerun; only the module timing (jitter) differs, so the outcome '
            f"may too.</p>{body}" + (cards(items, len(coll)) if items else ""))


def section_suite(doc: dict[str, Any]) -> str:
    """A suite's table (``deft-gym run`` with several scenarios): one row per scenario."""
    rows = doc.get("scenarios") or []
    failing = sum(bool(r.get("failing")) for r in rows)
    head = kpis([("scenarios", len(rows)), ("reruns each", doc.get("reruns", "?")),
                 ("failed in every rerun", f"{failing} of {len(rows)}")])
    body = table(["scenario", "outcomes", "violated in every rerun", "in some reruns", "comfort", "mean score"],
                 [[r.get("scenario"), ", ".join(r.get("outcomes") or []), ", ".join(r.get("confirmed") or []),
                   ", ".join(r.get("some_reruns") or []), "every rerun" if r.get("comfort_every_rerun") else "",
                   "-" if r.get("mean_score") is None else f"{r['mean_score']:.3f}"] for r in rows])
    return (f"<h2>Suite: {len(rows)} scenarios</h2>{head}"
            '<p class="note">Each scenario unmutated; a metric violated in every rerun is the planner\'s own '
            "failure, confirmed across jitter seeds (docs/metrics.md). Each scenario's reruns follow.</p>" + body)


def _scenario_arg(path: str | None, name: str) -> str:
    """How a replay command names a scenario file: ``configs/...`` for a shipped one (found from
    any folder), else its path as shown to users; the scenario's name without a file."""
    from deft_gym.config import CONFIG_DIR

    if not path or not Path(path).exists():
        return name
    try:
        return "configs/" + Path(path).resolve().relative_to(CONFIG_DIR.resolve()).as_posix()
    except ValueError:
        return common.shown(path)


def quality(m: dict[str, Any] | None) -> list[str]:
    """An episode's driving-quality cells: its score and the metrics it violated (docs/metrics.md)."""
    if not m:
        return ["-", "-"]
    return [f"{m['score']:.3f}", ", ".join(m.get("violations") or []) or "none"]


def section_extraction(page: Page, folder: Path, s: dict[str, Any]) -> str:
    eps = s.get("episodes_list") or [s]
    frames = s.get("frames", 0)
    rep = (s.get("reproduced") or {}).get("0", s.get("reproduced_at_theta"))
    head = kpis([("logs", len(eps)), ("planning frames", frames),
                 ("reproduced bit-exactly", f"{100 * rep / frames:.1f} %" if frames and rep is not None else "-"),
                 ("failure tests (P_faulty)", sum(1 for e in eps if e.get("faulty_trajectory")))])
    rows = []
    items = []
    for e in eps:
        test = Path(e["test_path"]) if e.get("test_path") else None
        f = e.get("faulty_trajectory")
        rows.append([Path(e.get("log") or "?").parent.name, e.get("scenario", "?"), e.get("frames", 0),
                     f"frame {f['index']} t={f['time']:.2f} s" if f else "-", test.name if test else "-"])
        if f and len(items) < MAX_CARDS and test is not None:
            log = Path(e["log"]) if e.get("log") else None
            replay = replay_command(test.parent, None, log) if log is not None else None
            items.append(card(page, f"{e.get('scenario')}: P_faulty at frame {f['index']} (t={f['time']:.2f} s)",
                              log, replay, test, pictures=test.parent))
    return (f"<h2>Extracted planning-module tests (DeFT)</h2>{head}"
            f'<p class="note">Every planning output of each log replayed through the planner from the frames '
            f"it was planned from; run them all with:</p>{cmd(['pytest', '-q', common.shown(folder)])}"
            + table(["log", "scenario", "frames", "P_faulty", "test module"], rows) + (cards(items, len(items)) if items else ""))


def _curves(progress: list[dict[str, Any]]) -> str:
    """Cumulative counts over env steps, from the start of training (0) to its last record."""
    if progress and progress[0].get("timesteps", 0) > 0:
        progress = [{"timesteps": 0}, *progress]
    if len(progress) < 2:
        return '<p class="note">(too few progress records for training curves)</p>'
    from deft_gym.viz.episode import _pyplot

    plt = _pyplot()
    fig, ax = plt.subplots(figsize=(7.5, 3.2))
    x = [p.get("timesteps", 0) for p in progress]
    for key, label in (("collision", "collisions"), ("nods", "non-optimal decisions"), ("episodes", "episodes")):
        ax.plot(x, [p.get(key, 0) for p in progress], label=label, lw=2 if key != "episodes" else 1,
                ls="-" if key != "episodes" else ":")
    ax.set_xlabel("env steps")
    ax.set_ylabel("cumulative count")
    ax.grid(alpha=0.3)
    ax.legend(loc="upper left", bbox_to_anchor=(1.01, 1.0), frameon=False)
    return fig_data(fig, "training curves")


def _episode_cards(page: Page, episodes: list[Path]) -> list[str]:
    items = []
    for d in episodes[:MAX_CARDS]:
        v = read_json(d / "episode.json") or {}
        replay = replay_command(d, v, d / "episode.mcap")
        what = v.get("failure") or v.get("oracle_signature") or "failure"
        title = f"{v.get('scenario', d.name)}: {what}" + (f" (IoU {v['iou']:.2f})" if isinstance(v.get("iou"), float)
                                                         and what == "nods" else "")
        if isinstance(v.get("metrics"), dict):
            score, violated = quality(v["metrics"])
            title += f"; score {score}, {violated}"
        items.append(card(page, title, d / "episode.mcap", replay, _tests_in(d / "extracted"), note=d.name,
                          collision=what == "collision"))
    return items


def replay_command(d: Path, v: dict[str, Any] | None = None, log: Path | None = None) -> list[str] | None:
    """The command that replays a failing episode: ``deft-gym run d/replay_scenario.yaml`` with
    its jitter seed. The file is written when missing (:func:`deft_gym.search.episode.write_replay`)
    from the scenario of the episode's verdict ``v`` (``episode.json``), else from its ``log``'s
    metadata; None when neither holds one."""
    from deft_gym.search.episode import load_replay, read_replay, replay_of_log, write_replay

    scen = d / "replay_scenario.yaml"
    eq = load_replay(scen) if scen.exists() else None
    if eq is None:
        eq = read_replay((v or {}).get("scenario_equivalent"), (v or {}).get("jitter_seed"))
        if eq is None and log is not None and log.exists():
            eq = replay_of_log(log)
        if eq is None:
            return None
        write_replay(scen, eq)
    import re

    name = re.sub(r"[^A-Za-z0-9._-]+", "_", str(eq["scenario"].get("name") or d.name))
    return ["deft-gym", "run", common.shown(scen), "--reruns", "1", "--jitter-seed", str(eq["jitter_seed"]),
            "--out", f"runs/replay/{name}-{eq['jitter_seed']}"]


def section_training(page: Page, folder: Path) -> str:
    s = read_json(folder / "summary.json") or {}
    from deft_gym.files import read_jsonl

    progress = read_jsonl(folder / "progress.jsonl") if (folder / "progress.jsonl").exists() else []
    eps = sorted(p.parent for p in (folder / "episodes").glob("*/episode.json"))
    fails = [d for d in eps if any((read_json(d / "episode.json") or {}).get(k)
                                   for k in ("failure", "oracle_signature"))]  # incl. a metric oracle's findings
    head = kpis([("env steps", f"{s.get('timesteps', 0):,}"), ("episodes", s.get("episodes", "-")),
                 ("collisions", s.get("collisions", "-")), ("NoDS", s.get("nods", "-")),
                 ("valid mutations", f"{100 * s['validity']:.1f} %" if "validity" in s else "-"),
                 ("training time", f"{s.get('train_seconds', 0):.0f} s")])
    per = s.get("per_scenario") or {}
    rows = [[k, v.get("episodes", 0), v.get("collision", 0), v.get("nods", 0), v.get("valid", 0)]
            for k, v in sorted(per.items())]
    last = progress[-1] if progress else {}
    if s.get("timesteps", 0) > last.get("timesteps", 0):  # a run from before progress.jsonl got its last line
        progress = [*progress, {"timesteps": s["timesteps"], "collision": s.get("collisions", last.get("collision", 0)),
                                "nods": s.get("nods", last.get("nods", 0)),
                                "episodes": s.get("episodes", last.get("episodes", 0))}]
    return (f"<h2>Adversary training: {esc(folder.name)}</h2>{head}<h3>Training curves</h3>{_curves(progress)}"
            f'<p class="note">Live curves: {esc("tensorboard --logdir " + common.shown(folder / "tb"))}</p>'
            + table(["scenario", "episodes", "collisions", "NoDS", "valid"], rows)
            + (f"<h3>Failing episodes ({len(fails)})</h3>" + cards(_episode_cards(page, fails), len(fails))
               if fails else ""))


def section_evaluation(page: Page, folder: Path) -> str:
    s = read_json(folder / "summary.json") or {}
    parts = [f"<h2>Adversary evaluation: {esc(folder.name)}</h2>"]
    cfg = read_json(folder / "eval_config.json") or {}
    parts.append(kpis([("methods", ", ".join(cfg.get("methods", []))), ("budget per scenario", cfg.get("budget", "-")),
                       ("scenarios", len(cfg.get("scenarios", [])) + len(cfg.get("held_out", []))),
                       ("wall time", f"{s.get('wall_seconds', 0):.0f} s")]))
    # the headline: distinct root causes per method (first placement rule), raw failures beside
    heads = []
    for m, ps in (s.get("groups") or {}).items():
        cell = next(iter(ps.values()), {}).get("all") or {}
        rc, fl = (cell.get("root_causes") or {}).get("mean"), (cell.get("failures") or {}).get("mean")
        if rc is not None:
            heads.append((f"{m}: root causes", f"{rc:.1f} ({fl:.0f} failures)" if fl is not None else f"{rc:.1f}"))
        score = (cell.get("metric_score") or {}).get("mean")
        if score is not None:  # driving quality (docs/metrics.md): the mean score of its simulated scenarios
            heads.append((f"{m}: driving score", f"{score:.3f}"))
    if heads:
        parts.append(kpis(heads))
    found = folder / "findings" / "findings.md"
    if found.exists():
        pics = sorted(found.parent.glob("*.png"))[:MAX_CARDS]
        parts.append(f'<h3>Findings re-simulated and drawn ({esc(common.shown(found))})</h3>'
                     + "".join(img_data(p, p.stem) for p in pics))
    for png, alt in (("cumulative_failures.png", "cumulative failures per method"),
                     ("per_scenario.png", "failures per scenario")):
        if (folder / png).exists():
            parts.append(img_data(folder / png, alt))
    parts.append(evaluation_tables(s, folder))
    logs = sorted(p.parent for p in (folder / "logs").rglob("episode.json"))
    if logs:
        parts.append(f"<h3>Failing scenarios with logs ({len(logs)})</h3>" + cards(_episode_cards(page, logs), len(logs)))
    return "".join(parts)


def evaluation_tables(s: dict[str, Any], folder: Path) -> str:
    """One evaluation table (a row per method and placement: the headline measures, failures on
    seed, held-out and all scenarios) and one table of the root causes (method and placement
    columns); every other measure stays in ``table.md``, linked. An older summary that these
    cannot be built from: ``table.md`` as it is."""
    from agents.eval_report import METHOD_LABELS, headline_markdown

    md = folder / "table.md"
    link = (f'<p class="note">Every measure per group of scenarios, per scenario, the statistics and the targets: '
            f'<a href="{esc(md.name)}">{esc(common.shown(md))}</a></p>' if md.exists() else "")
    try:
        head = markdown(headline_markdown(s))
    except (KeyError, TypeError, AttributeError):
        return markdown(md.read_text()) if md.exists() else ""
    rows = []
    causes = ((s.get("findings") or {}).get("root_causes") or {})
    for m in [*s.get("methods", []), "all"]:
        for p, cs in (causes.get(m) or {}).items():
            for sig, c in sorted(cs.items(), key=lambda kv: (-kv[1]["failures"], kv[0]))[:MAX_CARDS]:
                rows.append(["all methods" if m == "all" else METHOD_LABELS.get(m, m), p, sig, c.get("band", "-"),
                             c.get("failures", 0), ", ".join(c.get("scenarios", [])[:3])])
    causes_html = ("<h3>Root causes</h3>" + table(["method", "placement", "root cause", "band", "failures",
                                                   "scenarios"], rows)) if rows else ""
    return f"<h3>Evaluation</h3>{head}{causes_html}{link}"


def section_stress(page: Page, folder: Path, s: dict[str, Any]) -> str:
    head = kpis([("tests", s.get("runs")), ("crashes", s.get("crashes")), ("hangs", s.get("hangs")),
                 ("runs with violations", s.get("runs_with_violations")),
                 ("hardening", "on" if s.get("hardening") else "off")])
    viol = table(["invariant", "runs"], [[k, v] for k, v in (s.get("violations") or {}).items()])
    items = []
    mins = s.get("minimised") or []
    for m in mins[:MAX_CARDS]:
        case = folder / m["case"] if m.get("case") else None
        log = folder / m["log"] if m.get("log") else None
        items.append(card(page, f"finding {m.get('signature')}", log,
                          ["deft-gym", "stress", "replay", common.shown(case)] if case else None, None,
                          note=f"minimised: {', '.join((m.get('dimensionality') or {}).get('fields', [])) or '-'}"))
    return (f"<h2>Robustness campaign (ASTAA): {esc(folder.name)}</h2>{head}{viol}"
            + (f"<h3>Minimised findings ({len(mins)})</h3>" + cards(items, len(mins)) if items else ""))


def section_demo(page: Page, folder: Path, d: dict[str, Any]) -> str:
    """The demo's story: flaky system reruns, a deterministic module test, the adversary."""
    flaky = d.get("flaky") or {}
    parts = ["<h2>The story: a flaky collision becomes a test that fails every time</h2>"]
    k, n = flaky.get("collided", 0), flaky.get("reruns", 0)
    fails, runs = flaky.get("test_failed", 0), flaky.get("test_runs", 0)
    parts.append(kpis([("system reruns that collided", f"{k} of {n}"),
                       ("extracted test failed", f"{fails} of {runs} runs"),
                       ("a system rerun simulates", f"{flaky.get('rerun_seconds', 0):.2f} s"),
                       ("the failure test runs", f"{flaky.get('test_seconds', 0):.3f} s")]))
    parts.append(f'<p class="note">{esc(flaky.get("story", ""))}</p>')
    adv = d.get("adversary") or {}
    if adv:
        parts.append(f'<p class="note">{esc(adv.get("story", ""))}</p>')
    return "".join(parts)


def build(root: Path, out: Path, draw: bool = True) -> Page:
    """The page for ``root`` and what it holds (sub-folders to depth 3)."""
    page = Page(root, out, draw)
    seen: list[tuple[str, Path]] = []

    def walk(folder: Path, depth: int) -> None:
        if (folder / "suite.json").is_file():  # a suite of runs: its table, then each run
            seen.append(("suite", folder))
        kind = kind_of(folder)
        if kind is not None:
            seen.append((kind, folder))
            if kind in ("evaluation", "training", "stress", "extraction"):
                return
        if depth < 3:
            subs = [p for p in folder.iterdir() if p.is_dir() and p.name not in ("tb", "checkpoints", "episodes", "logs")]
            for sub in sorted(subs, key=lambda p: (ORDER.index(p.name) if p.name in ORDER else len(ORDER), p.name)):
                walk(sub, depth + 1)

    walk(root, 0)
    for kind, folder in seen:
        s = read_json(folder / "summary.json") or {}
        if kind == "demo":
            html_part = section_demo(page, folder, read_json(folder / "demo.json") or {})
        elif kind == "suite":
            html_part = section_suite(read_json(folder / "suite.json") or {})
        elif kind == "run":
            html_part = section_run(page, folder, s)
        elif kind == "extraction":
            html_part = section_extraction(page, folder, s)
        elif kind == "training":
            html_part = section_training(page, folder)
        elif kind == "evaluation":
            html_part = section_evaluation(page, folder)
        else:
            html_part = section_stress(page, folder, s)
        page.parts.append(f'<section id="{esc(kind)}-{len(page.parts)}" class="{esc(kind)}">{html_part}</section>')
    return page


def render_html(page: Page, title: str) -> str:
    body = "\n".join(page.parts) or '<section><p class="note">Nothing in this folder that the report knows: a demo, ' \
                                   "reruns, an extraction, a training run, an evaluation or a stress campaign.</p></section>"
    when = time.strftime("%Y-%m-%d %H:%M")
    return (f'<!DOCTYPE html>\n<html lang="en"><head><meta charset="utf-8"><title>{esc(title)}</title>'
            f'<meta name="viewport" content="width=device-width, initial-scale=1">'
            f'<link rel="icon" href="data:,"><style>{STYLE}</style></head>'
            f"<body><header><h1>{esc(title)}</h1><p>{esc(common.shown(page.root))} · generated {when} by deft-gym "
            "report · the commands run from the project's folder in its virtual environment "
            "(<code>source .venv/bin/activate</code>)</p>"
            f"</header><main>{body}</main></body></html>\n")


def write_report(root: Path | str, out: Path | str | None = None, draw: bool = True) -> Path:
    """Write the report of ``root`` (default ``root/report.html``); returns its path."""
    from deft_gym.files import write_atomic

    root = Path(root)
    out = Path(out) if out else root / "report.html"
    page = build(root, out, draw)
    write_atomic(out, render_html(page, f"DeFT-Gym report: {root.name}"))
    return out


def build_parser() -> common.Parser:
    p = common.parser("report", "deft_gym.cli.report", __doc__)
    p.add_argument("dir", metavar="DIR", help="run folder (demo, reruns, extraction, training, evaluation, stress)")
    common.add_out(p, None, help="the HTML file (default: DIR/report.html)", folder=False)
    p.add_argument("--no-draw", action="store_true", help="do not draw missing pictures of failures")
    common.add_output_flags(p)
    return p


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    root = Path(args.dir)
    if not root.is_dir():
        return common.cli_error(f"DIR: {root}: no such folder")
    path = write_report(root, args.out, draw=not args.no_draw)
    print(f"report: {path}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
