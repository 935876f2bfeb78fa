"""Foxglove-ready logs (epoch log times, the scene topics read back with the mcap library and
validated against their schemas, non-finite floats as plain JSON), the pictures drawn from a log,
the HTML report's structure and links, and generated test modules that any set of extraction
folders collects (``pytest A B``), with strict xfail failure oracles on request."""

from __future__ import annotations

import base64
import json
import subprocess
import sys
from html.parser import HTMLParser
from pathlib import Path

import jsonschema
import pytest
from mcap.reader import make_reader

from deft_gym.bus.codec import decode, encode
from deft_gym.bus.messages import NS_PER_S, SCENE_MAP_TOPIC, SCENE_TOPIC, TF_TOPIC, VIEWER_TOPICS
from deft_gym.config import CONFIG_DIR
from deft_gym.record.scene import frame_transform_schema, scene_update_schema

ROOT = Path(__file__).resolve().parents[2]
FLAKY = CONFIG_DIR / "scenarios" / "handwritten" / "stopped_bus.yaml"  # the demo's: collides with jitter seed 1002, not with 1003


@pytest.fixture(scope="module")
def runs(tmp_path_factory) -> Path:
    """``deft-gym run`` of the demo's flaky scenario, 2 reruns (rerun 0 collides), pictures of all."""
    from deft_gym.cli.run import main

    out = tmp_path_factory.mktemp("scene") / "flaky"
    assert main([str(FLAKY), "--reruns", "2", "--jitter-seed", "1002", "--out", str(out), "--render", "all",
                 "--quiet"]) == 0
    return out


def _read(log: Path) -> tuple[dict, list]:
    with open(log, "rb") as f:
        reader = make_reader(f)
        meta = {m.name: dict(m.metadata) for m in reader.iter_metadata()}
    with open(log, "rb") as f:
        msgs = [(sch, ch, m) for sch, ch, m in make_reader(f).iter_messages()]
    return meta, msgs


def test_log_times_are_epoch_times_and_readers_get_sim_time_back(runs: Path) -> None:
    from extract.logs import read_log

    log = runs / "0" / "episode.mcap"
    meta, msgs = _read(log)
    start = int(meta["deft_gym.episode"]["log_start_ns"])
    assert start > 1_600_000_000 * NS_PER_S  # a real date, not 1970
    assert all(start <= m.log_time < start + 60 * NS_PER_S for _, _, m in msgs)
    elog = read_log(log, ["/apollo/planning"])
    truth = [json.loads(x) for x in (runs / "0" / "truth.jsonl").read_text().splitlines()]
    assert elog.topics["/apollo/planning"].publish_ns.tolist() == [t["publish_ns"] for t in truth]


def test_scene_topics_have_foxglove_schemas_and_draw_the_episode(runs: Path) -> None:
    meta, msgs = _read(runs / "0" / "episode.mcap")
    schemas = {ch.topic: (sch.name, sch.encoding, ch.message_encoding, dict(ch.metadata))
               for sch, ch, _ in msgs if ch.topic in VIEWER_TOPICS}
    assert schemas[SCENE_TOPIC][:3] == ("foxglove.SceneUpdate", "jsonschema", "json")
    assert schemas[SCENE_MAP_TOPIC][0] == "foxglove.SceneUpdate" and schemas[TF_TOPIC][0] == "foxglove.FrameTransform"
    assert all("role" not in s[3] for s in schemas.values())  # readers of bus messages skip them
    scene = [(m.log_time, json.loads(m.data)) for _, ch, m in msgs if ch.topic == SCENE_TOPIC]
    scene_schema = scene_update_schema()
    for _, payload in scene[:: max(1, len(scene) // 10)] + scene[-1:]:
        jsonschema.validate(payload, scene_schema)
    for _, ch, m in msgs:
        if ch.topic == TF_TOPIC:
            jsonschema.validate(json.loads(m.data), frame_transform_schema())
            break
    start = int(meta["deft_gym.episode"]["log_start_ns"])
    t, last = scene[-1]
    ent = {e["id"]: e for e in last["entities"]}
    ts = ent["ego"]["timestamp"]
    assert ts["sec"] * NS_PER_S + ts["nsec"] == t and t >= start
    participants = {p["id"] for p in json.loads(meta["deft_gym.episode"]["scenario"])["participants"]}
    assert {f"participant/{p}" for p in participants} <= set(ent)
    assert any(txt["text"].startswith("ego ") and txt["text"].endswith("m/s") for txt in ent["ego"]["texts"])
    assert "plan" in ent and len(ent["plan"]["lines"][0]["points"]) >= 2
    coll = json.loads(meta["deft_gym.outcome"]["collision"])
    assert "collision" in ent and f"collision with {coll['participant']}" in ent["collision"]["texts"][0]["text"]
    lanes = [json.loads(m.data) for _, ch, m in msgs if ch.topic == SCENE_MAP_TOPIC]
    jsonschema.validate(lanes[0], scene_schema)
    assert lanes[0]["entities"][0]["id"] == "lanes" and len(lanes[0]["entities"][0]["lines"]) > 10


def test_extraction_digests_and_the_offline_checker_read_the_log(runs: Path, tmp_path: Path) -> None:
    from deft_gym.cli.digest import run_digest
    from deft_gym.robustness.offline import check_log
    from extract import extract_episode

    res = extract_episode(runs / "0" / "episode.mcap", tmp_path / "x")
    assert res.summary["reproduced_at_theta"] == res.summary["frames"] > 0
    assert res.summary["truth_agreement"] > 0.9 and res.faulty is not None
    check_log(runs / "0" / "episode.mcap")  # reads and judges it (violations or none)
    a = run_digest(FLAKY, 1002)
    assert not set(VIEWER_TOPICS) & set(a)  # pictures are not behaviour
    assert a == run_digest(FLAKY, 1002)  # sim times, not epoch times: two runs agree


def test_non_finite_floats_are_plain_json() -> None:
    payload = {"v": float("nan"), "a": [float("inf"), -float("inf"), -0.0, 1.5], "null": None}
    data = encode(payload)

    def no_constants(name: str) -> None:
        raise AssertionError(f"JSON5 token {name} in {data!r}")

    plain = json.loads(data, parse_constant=no_constants)  # what Foxglove's JSON.parse reads
    assert plain["v"] == {"$float": "NaN"} and plain["a"][0] == {"$float": "Infinity"}
    back = decode(data)
    assert back["v"] != back["v"] and back["a"][:2] == [float("inf"), -float("inf")] and back["null"] is None
    assert decode(b'{"v":NaN,"w":-Infinity}')["w"] == -float("inf")  # logs written before


def test_plot_and_video_of_a_collision(runs: Path) -> None:
    import imageio.v2 as imageio

    from deft_gym.viz.episode import load_episode

    ep = load_episode(runs / "0" / "episode.mcap")
    assert ep.source == "scene" and ep.collision is not None and ep.failure == "collision"
    assert set(ep.participants) >= {ep.collision["participant"]}
    assert len({t.kind for t in ep.participants.values()}) >= 1 and ep.plans and ep.lanes
    plot = imageio.imread(runs / "0" / "plot.png")
    assert plot.shape[0] > 300 and plot.shape[1] > 500
    red = (plot[..., 0] > 200) & (plot[..., 1] < 60) & (plot[..., 2] < 60)
    assert red.sum() > 50  # the collision marker
    frames = imageio.mimread(runs / "0" / "video.mp4", memtest=False)
    assert len(frames) >= 10 and frames[0].shape[1] >= 600
    summary = json.loads((runs / "summary.json").read_text())
    assert summary["reruns"][0]["plot"].endswith("plot.png") and summary["reruns"][1]["video"].endswith("video.mp4")


def test_render_command_draws_a_folder(runs: Path, tmp_path: Path) -> None:
    from deft_gym.cli.render import main

    assert main([str(runs), "--out", str(tmp_path), "--only", "failures", "--no-video", "--quiet"]) == 0
    assert (tmp_path / "0" / "plot.png").exists() and not (tmp_path / "1").exists()


# -- generated test modules -----------------------------------------------------------------------------
@pytest.fixture(scope="module")
def extractions(runs: Path) -> tuple[Path, Path]:
    """Rerun 0 extracted into ``flaky_tests/0`` (plain) and into ``ci/0`` (strict xfail oracles)."""
    from deft_gym.cli.extract import main

    a, b = runs.parent / "flaky_tests" / "0", runs.parent / "ci" / "0"
    assert main([str(runs / "0" / "episode.mcap"), "--out", str(a), "--quiet"]) == 0
    assert main([str(runs / "0" / "episode.mcap"), "--out", str(b), "--xfail-failures", "--render", "none",
                 "--quiet"]) == 0
    return a, b


def test_module_names_are_unique_per_log_and_folders_collect_together(runs: Path, extractions, tmp_path) -> None:
    from extract import extract_episode

    a, strict = extractions
    other = extract_episode(runs / "1" / "episode.mcap", tmp_path / "other").test_path
    names = [next(a.glob("test_*.py")).name, other.name]
    assert names[0] != names[1] and all(n.startswith("test_stopped_bus_") for n in names)
    assert names[0].count("stopped_bus") == 1
    proc = subprocess.run([sys.executable, "-m", "pytest", "-q", "-p", "no:cacheprovider", "-o", "addopts=",
                           str(a), str(other.parent)], capture_output=True, text=True, cwd=tmp_path)
    assert "import file mismatch" not in proc.stdout + proc.stderr and " error" not in proc.stdout.splitlines()[-1]
    assert proc.returncode == 1 and " failed" in proc.stdout.splitlines()[-1]  # the collision's failure oracle
    proc = subprocess.run([sys.executable, "-m", "pytest", "-q", "-p", "no:cacheprovider", "-o", "addopts=",
                           str(strict)], capture_output=True, text=True, cwd=tmp_path)
    assert proc.returncode == 0 and "xfailed" in proc.stdout.splitlines()[-1], proc.stdout[-500:]
    assert "strict=True" in next(strict.glob("test_*.py")).read_text()


# -- the HTML report -----------------------------------------------------------------------------------
class _Page(HTMLParser):
    def __init__(self) -> None:
        super().__init__()
        self.tags: list[tuple[str, dict[str, str]]] = []
        self.text: list[str] = []

    def handle_starttag(self, tag: str, attrs: list) -> None:
        self.tags.append((tag, dict(attrs)))

    def handle_data(self, data: str) -> None:
        self.text.append(data)


def check_report(path: Path) -> _Page:
    """The report's structure: sections, embedded images that decode, links and videos that
    resolve to files, no scripts and nothing from the network."""
    page = _Page()
    page.feed(path.read_text())
    tags = page.tags
    assert any(t == "section" for t, _ in tags) and not any(t == "script" for t, _ in tags)
    for tag, a in tags:
        for key in ("src", "href", "poster"):
            ref = a.get(key)
            if ref is None:
                continue
            assert not ref.startswith(("http:", "https:", "//")), ref
            if ref.startswith("data:image/png;base64,"):
                assert base64.b64decode(ref.split(",", 1)[1])[:8] == b"\x89PNG\r\n\x1a\n"
            elif not ref.startswith("data:"):
                assert (path.parent / ref).exists(), f"<{tag} {key}={ref!r}> does not resolve"
    return page


def test_report_of_reruns_and_their_extraction(runs: Path, extractions) -> None:
    from deft_gym.cli.report import main

    assert main([str(runs.parent), "--quiet"]) == 0
    path = runs.parent / "report.html"
    page = check_report(path)
    classes = [a.get("class") for t, a in page.tags if t == "section"]
    assert "run" in classes and classes.count("extraction") == 2
    text = " ".join(page.text)
    assert "1 of 2" in text  # reruns that collided
    assert "deft-gym run" in text and "--jitter-seed 1002" in text  # replay the failing rerun
    assert "pytest -q" in text and "test_stopped_bus_" in text  # its extracted test
    imgs = [a for t, a in page.tags if t == "img"]
    assert len(imgs) >= 2 and all(a["src"].startswith("data:image/png") for a in imgs)
    videos = [a for t, a in page.tags if t == "video"]
    assert videos and all(a.get("poster", "").endswith("_poster.png") for a in videos)  # no black box before play
    pres = [x for x in page.text if x.startswith(("deft-gym ", "pytest "))]
    assert pres and not any(w.startswith(str(ROOT)) for x in pres for w in x.split()), pres  # no clone's path
    # the extracted log's card replays the log's episode (its replay_scenario.yaml), as printed
    import shlex

    from deft_gym.cli.run import main as run_main

    words = next(shlex.split(x) for x in pres if x.startswith("deft-gym run") and "replay_scenario.yaml" in x)
    args = words[2:]
    args[args.index("--out") + 1] = str(runs.parent / "replayed")
    assert run_main([*args, "--render", "none", "--quiet"]) == 0
    again = json.loads((runs.parent / "replayed" / "summary.json").read_text())["reruns"][0]
    first = json.loads((runs / "summary.json").read_text())["reruns"][0]
    assert (again["outcome"], again["sim_time"], again["collision_detail"]) == \
        (first["outcome"], first["sim_time"], first["collision_detail"])


def _chrome() -> object:
    """Headless Chromium through selenium (``make browser`` installs both); the test skips,
    saying what is missing, where they are not installed."""
    import shutil

    try:
        from selenium import webdriver
    except ImportError:
        pytest.skip("selenium is not installed (make browser installs it with chromium and chromedriver)")
    binary = shutil.which("chromium") or shutil.which("chromium-browser")
    driver_path = shutil.which("chromedriver")
    if binary is None or driver_path is None:
        pytest.skip("chromium and chromedriver are not installed (make browser: apt-get install chromium "
                    "chromium-driver, as root)")
    opts = webdriver.ChromeOptions()
    for flag in ("--headless", "--no-sandbox", "--disable-gpu", "--disable-background-networking",
                 "--disable-component-update", "--disable-sync", "--no-first-run", "--allow-file-access-from-files",
                 "--autoplay-policy=no-user-gesture-required", "--window-size=1300,2000"):
        opts.add_argument(flag)
    opts.binary_location = binary
    opts.set_capability("goog:loggingPrefs", {"browser": "ALL"})
    return webdriver.Chrome(options=opts, service=webdriver.ChromeService(executable_path=driver_path))


@pytest.mark.slow
def test_report_loads_in_a_real_browser(runs: Path, extractions) -> None:
    """Chromium, headless (``make browser`` installs it and selenium): the page loads without
    console errors, every image decodes and every video's file is there."""
    from deft_gym.cli.report import write_report

    path = write_report(runs.parent)
    driver = _chrome()
    try:
        driver.get(path.resolve().as_uri())
        assert driver.title.startswith("DeFT-Gym report")
        images = driver.execute_script(
            "return Array.from(document.images).map(i => [i.complete, i.naturalWidth, i.alt]);")
        assert images and all(ok and w > 0 for ok, w, _ in images), images
        links = driver.execute_script("return Array.from(document.querySelectorAll('a[href], video[src]'))"
                                      ".map(e => e.href || e.src);")
        for url in links:
            assert url.startswith("file://") and Path(url.removeprefix("file://")).exists(), url
        errors = [e for e in driver.get_log("browser") if e["level"] == "SEVERE"]
        assert errors == [], errors
    finally:
        driver.quit()


# what the screenshot test asks the page: broken images, videos (poster, playable), cut table cells
_PAGE_STATE = """
const done = arguments[arguments.length - 1];
const videos = Array.from(document.querySelectorAll('video'));
const posters = videos.map(v => new Promise(ok => {
  if (!v.poster) { ok([v.src, false, 0]); return; }
  const img = new Image(); img.onload = () => ok([v.src, true, img.naturalWidth]);
  img.onerror = () => ok([v.src, true, 0]); img.src = v.poster; }));
const playable = videos.map(v => new Promise(ok => {
  const report = () => ok([v.src, v.readyState, isFinite(v.duration) ? v.duration : 0,
                           v.error ? v.error.code : null]);
  if (v.readyState >= 1 || v.error) { report(); return; }
  v.addEventListener('loadedmetadata', report); v.addEventListener('error', report);
  setTimeout(report, 8000); v.preload = 'metadata'; v.load(); }));
const cells = Array.from(document.querySelectorAll('td, th'))
  .filter(c => c.scrollWidth > c.clientWidth + 1 || c.textContent.includes('\u2026'))
  .map(c => c.textContent);
const images = Array.from(document.images).filter(i => !(i.complete && i.naturalWidth > 0)).map(i => i.alt);
Promise.all([Promise.all(posters), Promise.all(playable)]).then(([p, v]) =>
  done({posters: p, videos: v, cut: cells, broken: images, tables: document.querySelectorAll('table').length}));
"""


@pytest.mark.slow
def test_report_screenshot_in_a_real_browser(runs: Path, extractions, tmp_path: Path) -> None:
    """The report as a user sees it in Chromium: a screenshot is taken, and the test fails on a
    broken image, a video without a poster frame or that cannot play (no metadata, an error), or
    a table cell whose text is cut (wider than the cell, or an ellipsis)."""
    from deft_gym.cli.report import write_report

    path = write_report(runs.parent)
    driver = _chrome()
    try:
        driver.set_script_timeout(60)
        driver.get(path.resolve().as_uri())
        state = driver.execute_async_script(_PAGE_STATE)
        shot = tmp_path / "report.png"
        assert driver.save_screenshot(str(shot)) and shot.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    finally:
        driver.quit()
    assert state["broken"] == [], state["broken"]
    assert state["videos"], "the report of a collision has a video"
    assert all(has and width > 0 for _, has, width in state["posters"]), state["posters"]
    assert all(ready >= 1 and duration > 0 and err is None for _, ready, duration, err in state["videos"]), state["videos"]
    assert state["tables"] > 0 and state["cut"] == [], state["cut"]
