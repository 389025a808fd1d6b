"""The live web view: its watcher channel and pages in-process, then the page in a real browser.

- ``/docs`` and the view load nothing from outside the service (no CDN);
- the watcher channel authenticates with its first message, sends the stored poses as columns,
  then follows new ones; it is read-only and refuses bad keys and unknown sessions with a reason;
- in headless Chromium (Debian's ``chromium``, driven over the DevTools protocol) the page of a
  session that a real server is processing draws as many poses as the server stored, its status
  and plots follow the stream, a finished run shows its summary, a bad key gets a message, and
  the key never reaches the server's log even at debug level.
"""

from __future__ import annotations

import asyncio
import json
import re
import subprocess
import sys
import threading
from html.parser import HTMLParser
from pathlib import Path

import numpy as np
import pytest
from fastapi.testclient import TestClient
from starlette.websockets import WebSocketDisconnect
from test_service_server import KEY, PROJECT_ROOT, Server
from test_service_units import KEY_A, KEY_B, A, FakeFactory, new_session, send, settings_for

from service.app import create_app
from service.redact import MASK, SecretFilter
from service.web import watch as watch_module
from service.web.browser import Browser, find_chromium
from service.web.pages import STATIC_DIR
from service.web.watch_messages import WATCH_SERVER_MESSAGE

# ----------------------------------------------------------------------------- in-process


@pytest.fixture
def client(tmp_path: Path):
    with TestClient(create_app(settings_for(tmp_path), FakeFactory())) as test_client:
        yield test_client


class _Links(HTMLParser):
    """Every URL an HTML page makes the browser load (src and href attributes)."""

    def __init__(self) -> None:
        super().__init__()
        self.urls: list[str] = []

    def handle_starttag(self, tag: str, attrs: list[tuple[str, str | None]]) -> None:
        self.urls += [value for name, value in attrs if name in ("src", "href") and value]


def _links(html: str) -> list[str]:
    parser = _Links()
    parser.feed(html)
    return parser.urls


def test_docs_and_pages_load_nothing_from_outside(client: TestClient) -> None:
    docs = client.get("/docs")
    assert docs.status_code == 200 and "swagger-ui" in docs.text
    urls = _links(docs.text) + re.findall(r"url: '([^']+)'", docs.text)
    assert urls, "the docs page should reference its script, style and schema"
    for url in urls:
        assert url.startswith("/") and not url.startswith("//"), url
        assert client.get(url).status_code == 200, url
    assert "://" not in docs.text.replace("http://www.w3.org", "")
    assert client.get("/redoc").status_code == 404  # ReDoc would need a CDN
    for page in ("/", "/sessions/0123456789abcdef0123456789abcdef"):
        html = client.get(page)
        assert html.status_code == 200 and html.headers["content-type"].startswith("text/html")
        for url in _links(html.text):
            assert url.startswith("/") or url.startswith("data:"), url
            if url.startswith("/"):
                assert client.get(url).status_code == 200, url
    # The view's own scripts fetch only relative paths of this service.
    for path in STATIC_DIR.iterdir():
        text = path.read_text()
        assert not re.search(r"https?://", text), f"{path.name} names an external URL"
        assert client.get(f"/web/static/{path.name}").status_code == 200


def _watch_messages(ws, until: str) -> list[dict]:
    messages = []
    while not messages or messages[-1]["type"] != until:
        messages.append(ws.receive_json())
        WATCH_SERVER_MESSAGE.validate_python(messages[-1])  # one of the server's messages
    return messages


def test_watch_channel_sends_backlog_then_follows(
    client: TestClient, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setattr(watch_module, "CHUNK", 2)  # a backlog of 3 poses comes in two parts
    sid = new_session(client, name="rover")
    for t in (10, 20, 30):
        assert send(client, sid, t).status_code == 200
    stored = client.get(f"/v1/sessions/{sid}/trajectory", headers=A).json()["poses"]
    with client.websocket_connect(f"/v1/sessions/{sid}/watch") as ws:
        ws.send_text(json.dumps({"type": "auth", "token": KEY_A}))
        messages = _watch_messages(ws, "synced")
        assert [m["type"] for m in messages] == ["hello", "world", "poses", "poses", "synced"]
        hello, world, first, second, synced = messages
        assert first["index"] == [0, 1] and second["index"] == [2]
        poses = {key: first[key] + second[key] for key in first if isinstance(first[key], list)}
        poses["status"] = first["status"] + second["status"]
        assert hello["name"] == "rover" and synced["frame_count"] == 3
        # The fake odometry starts at the identity: the world is the first camera, y down.
        assert world["up"] == "-y"
        assert poses["index"] == [0, 1, 2] and poses["status"] == "ooo"
        expected = [np.array(p["pose"])[:3, 3] for p in stored]
        np.testing.assert_allclose(np.reshape(poses["position"], (-1, 3)), expected, atol=1e-4)
        np.testing.assert_allclose(np.reshape(poses["frontend_position"], (-1, 3)), expected,
                                   atol=1e-4)
        assert ws.receive_json()["type"] == "state"
        # New frames arrive without asking.
        for t in (40, 50):
            assert send(client, sid, t).status_code == 200
        received: list[int] = []
        while len(received) < 2:
            message = ws.receive_json()
            if message["type"] == "poses":
                received += message["index"]
            elif message["type"] == "state":
                assert message["activity"] == "live" and message["frame_count"] >= 3
        assert received == [3, 4]
        ws.send_text(json.dumps({"type": "frame", "timestamp_ns": 60}))
        reply = ws.receive_json()
        while reply["type"] == "state":
            reply = ws.receive_json()
        assert reply["type"] == "error" and "read-only" in reply["detail"]
    # A watcher that reconnects asks for what it has not seen; the world comes first again.
    with client.websocket_connect(f"/v1/sessions/{sid}/watch") as ws:
        ws.send_text(json.dumps({"type": "auth", "token": KEY_A, "since": 3}))
        messages = _watch_messages(ws, "synced")
        assert [m["type"] for m in messages] == ["hello", "world", "poses", "synced"]
        assert messages[2]["index"] == [3, 4]
        np.testing.assert_allclose(np.reshape(messages[2]["position"], (-1, 3))[:, 0],
                                   [0.03, 0.04], atol=1e-4)  # the fake moves 1 cm per frame


@pytest.mark.parametrize(
    ("first", "status", "code", "words"),
    [
        ({"type": "auth", "token": "wrong"}, 401, 4401, "unknown API key"),
        ({"type": "auth"}, 401, 4401, "missing API key"),
        ({"type": "auth", "token": KEY_B}, 404, 4404, "unknown session"),
        ({"type": "hello"}, 400, 4400, "first message"),
        ({"type": "auth", "token": KEY_A, "since": -1}, 400, 4400, "since"),
        ({"type": "auth", "token": KEY_A, "since": "3"}, 400, 4400, "since"),
        ({"type": "auth", "token": 5}, 400, 4400, "token"),
        ("not json", 400, 4400, "JSON"),
    ],
)
def test_watch_channel_refuses_with_a_reason(
    client: TestClient, first: dict | str, status: int, code: int, words: str
) -> None:
    sid = new_session(client)
    with client.websocket_connect(f"/v1/sessions/{sid}/watch") as ws:
        ws.send_text(first if isinstance(first, str) else json.dumps(first))
        error = ws.receive_json()
        WATCH_SERVER_MESSAGE.validate_python(error)
        assert error["type"] == "error" and error["status"] == status
        assert words in error["detail"]
        with pytest.raises(WebSocketDisconnect) as closed:
            ws.receive_json()
        assert closed.value.code == code


def test_live_sessions_list(client: TestClient) -> None:
    assert client.get("/v1/live/sessions").status_code == 401
    mine, theirs = new_session(client, name="mine"), new_session(client, headers={
        "Authorization": f"Bearer {KEY_B}"})
    for t in (10, 20, 30):
        assert send(client, mine, t).status_code == 200
    answer = client.get("/v1/live/sessions", headers=A).json()
    assert [s["id"] for s in answer["sessions"]] == [mine] and theirs != mine
    row = answer["sessions"][0]
    assert row["name"] == "mine" and row["frame_count"] == 3 and row["last_status"] == "ok"
    assert row["activity"] == "live" and row["frames_per_s"] > 0
    assert 0 <= answer["server_time"] - row["last_update"] < 60


def test_keys_are_redacted_from_log_records() -> None:
    secret_filter = SecretFilter(["k3y-secret"])
    lines = {
        "< authorization: Bearer abc.def": "< authorization: Bearer " + MASK,
        """< TEXT '{"type":"auth","token":"xyz","since":0}'""":
            """< TEXT '{"type":"auth","token":"MASK","since":0}'""".replace("MASK", MASK),
        "GET /v1/sessions/1/stream?token=abc&x=1": f"GET /v1/sessions/1/stream?token={MASK}&x=1",
        "key k3y-secret in plain text": f"key {MASK} in plain text",
        "nothing to hide": "nothing to hide",
    }
    for line, expected in lines.items():
        assert secret_filter.redact(line) == expected


# ----------------------------------------------------------------------------- browser

FRAMES = 24


@pytest.fixture(scope="module")
def chromium() -> str:
    path = find_chromium()
    if path is None:
        pytest.skip("no Chromium found (Debian: apt-get install chromium; .ci/run installs it)")
    return path


@pytest.fixture(scope="module")
def rendered(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A short rendered flight with a few broken frames (so degraded frames get marked)."""
    folder = tmp_path_factory.mktemp("web") / "rendered"
    subprocess.run(
        [sys.executable, "-m", "estimator.cli.main", "synth", str(folder), "--frames", str(FRAMES),
         "--length-m", "1.5", "--seed", "2", "--broken-fraction", "0.1", "--quiet"],
        cwd=PROJECT_ROOT, check=True, timeout=300,
    )
    return folder


def _stats(browser: Browser) -> dict:
    return json.loads(browser.evaluate(
        "JSON.stringify(window.swarmvoView ? window.swarmvoView.stats : {})"))


def _stream_in_background(url: str, dataset: Path, session) -> threading.Thread:
    from swarmvo_client.datasets import open_local_sequence
    from swarmvo_client.replay import replay_ws

    sequence = open_local_sequence(dataset)
    thread = threading.Thread(
        target=lambda: asyncio.run(
            replay_ws(url, KEY, session, sequence, progress=False, window=2)
        ),
        daemon=True,
    )
    thread.start()
    return thread


@pytest.mark.slow
def test_page_follows_a_live_session_in_chromium(
    chromium: str, rendered: Path, tmp_path: Path
) -> None:
    from swarmvo_client import Client
    from swarmvo_client.datasets import open_local_sequence
    from swarmvo_client.replay import create_session_for

    screenshots = tmp_path / "screenshots"
    server = Server(tmp_path / "data", tmp_path / "server.log", "--log-level", "debug")
    try:
        with Client(server.url, KEY) as api:
            session = create_session_for(
                api, open_local_sequence(rendered), {"seed": 3}, name="rendered flight"
            )
        with Browser(chromium) as browser:
            # The key is asked for once, then the sessions list shows the new session.
            browser.navigate(f"{server.url}/")
            browser.wait_for("!!document.querySelector('form.key')", what="the key form")
            browser.evaluate(f"document.querySelector('#key').value = {json.dumps(KEY)};"
                             "document.querySelector('form.key button').click()")
            row = browser.wait_for(
                f"document.querySelector('tr[data-id=\"{session.id}\"]')?.innerText",
                what="the session in the list")
            assert "rendered flight" in row and "idle" in row

            browser.navigate(f"{server.url}/sessions/{session.id}")
            browser.wait_for("window.swarmvoView?.stats.synced", what="the watcher")
            assert _stats(browser)["poses"] == 0
            streamer = _stream_in_background(server.url, rendered, session)
            seen = set()
            while streamer.is_alive():  # the page follows while frames are processed
                stats = _stats(browser)
                seen.add(stats["poses"])
                if stats["poses"] >= FRAMES // 2 and not (screenshots / "live.png").exists():
                    browser.wait_for("window.swarmvoView.stats.activity === 'live'")
                    browser.screenshot(screenshots / "live.png")
                streamer.join(0.05)
            with Client(server.url, KEY) as api:
                stored = api.trajectory(session.id)
                smoothed = api.smoothed(session.id)
            assert len(stored) == FRAMES and smoothed
            # The final smoothed poses reach the page after the last frame's answer: wait for
            # them too, then check every count.
            stats = json.loads(browser.wait_for(
                f"window.swarmvoView.stats.drawn === {FRAMES} && "
                f"window.swarmvoView.stats.serverFrames === {FRAMES} && "
                f"window.swarmvoView.stats.smoothed === {len(smoothed)} && "
                "JSON.stringify(window.swarmvoView.stats)", what="every pose drawn"))
            assert len({n for n in seen if 0 < n < FRAMES}) >= 2, f"no live updates: {seen}"
            assert stats["poses"] == stats["serverFrames"] == FRAMES
            assert stats["world"] == "z"  # the rendered flight has an IMU: z up
            # The smoother's final poses are drawn too, every one the server has handed out.
            assert stats["smoothed"] == len(smoothed)
            assert browser.evaluate("window.swarmvoView.views[0].drawnSmoothed") == len(smoothed)
            last_smoothed = browser.evaluate(
                "Array.from(window.swarmvoView.smoothed.position.subarray("
                "3 * (window.swarmvoView.smoothed.n - 1), 3 * window.swarmvoView.smoothed.n))")
            np.testing.assert_allclose(last_smoothed, smoothed[-1][1][:3, 3], atol=1e-4)
            # The path is really on the canvas, and the plots got every frame.
            painted = browser.evaluate(
                "(() => { const c = document.querySelector('#top');"
                "const d = c.getContext('2d').getImageData(0, 0, c.width, c.height).data;"
                "let n = 0; for (let i = 0; i < d.length; i += 4)"
                " n += d[i] < 80 && d[i + 1] < 120 && d[i + 2] > 200; return n; })()")
            assert painted > 50, "no trajectory pixels on the top view"
            plots = browser.evaluate("JSON.stringify(Object.fromEntries(Object.entries("
                                     "window.swarmvoView.plots).map(([k, p]) => [k, p.count])))")
            counts = json.loads(plots)
            assert counts["inliers"] == counts["latency"] == FRAMES and counts["fps"] >= 1
            statuses = [p.status for p in stored]
            marked = browser.evaluate("window.swarmvoView.buffer.count(1) + "
                                      "window.swarmvoView.buffer.count(2)")
            assert marked == sum(s != "ok" for s in statuses)
            facts = browser.evaluate("document.querySelector('#f-status').innerText")
            assert facts == stored[-1].status
            # Finished: the summary replaces the live facts.
            browser.wait_for("window.swarmvoView.stats.activity === 'idle' && "
                             "!document.querySelector('#summary').hidden", timeout=20,
                             what="the finished run's summary")
            summary = browser.evaluate("document.querySelector('#summary').innerText")
            assert f"frames\n{FRAMES}" in summary.replace("\t", "\n")
            browser.screenshot(screenshots / "finished.png")
            assert not browser.exceptions(), browser.exceptions()
            origins = {re.match(r"^[a-z]+:(//[^/]+)?", u).group(0)
                       for u in browser.requested_urls()}
            assert origins <= {server.url, "data:"}, origins

            # A refused key says so instead of showing an empty page.
            browser.evaluate("sessionStorage.setItem('swarmvo.key', 'not-a-key')")
            browser.navigate(f"{server.url}/sessions/{session.id}")
            notice = browser.wait_for(
                "!document.querySelector('#notice').hidden && "
                "document.querySelector('#notice').innerText", what="the bad-key message")
            assert "refused" in notice and "unknown API key" in notice
            assert browser.evaluate("!!document.querySelector('form.key')")
    finally:
        server.stop()
    log = (tmp_path / "server.log").read_text()
    assert "/watch" in log and "GET /v1/live/sessions" in log  # debug: requests are logged
    assert KEY not in log, "the API key reached the server log"
    assert "Traceback" not in log

