// One session: its trajectory from above and from the side, live over the watcher channel,
// small time plots, and for a finished run its summary and downloads.
import { ApiError, download, watch } from "./api.js";
import { PathBuffer, PoseBuffer, STATUS_NAMES, TimePlot, TrajectoryView } from "./draw.js";
import { ago } from "./list.js";

const RECONNECT_MS = 2000;

function template(id) {
  return `
  <div class="session">
    <div class="views">
      <div class="panel"><h2>From above</h2><canvas id="top" class="view"></canvas>
        <div class="legend"><span><i style="background:#2563eb"></i>pose (real time)</span>
          <span><i style="background:#16a34a"></i>smoothed (final)</span>
          <span><i style="background:#9aa3b2"></i>vision only</span>
          <span><i style="background:#e08a00;height:8px;width:8px;border-radius:4px"></i>degraded</span>
          <span><i style="background:#d62828;height:8px;width:8px;border-radius:4px"></i>lost</span>
        </div></div>
      <div class="panel"><h2>From the side</h2><canvas id="side" class="view"></canvas>
        <div class="legend"><span id="world-note"></span></div></div>
    </div>
    <div class="side">
      <div class="panel"><h2>Now</h2><dl class="facts">
        <dt>session</dt><dd id="f-activity">—</dd>
        <dt>status</dt><dd id="f-status">—</dd>
        <dt>frames</dt><dd id="f-frames">0</dd>
        <dt>frames/s</dt><dd id="f-fps">—</dd>
        <dt>last update</dt><dd id="f-last">—</dd>
        <dt>inliers</dt><dd id="f-inliers">—</dd>
        <dt>latency</dt><dd id="f-latency">—</dd>
      </dl><p class="message" id="f-message"></p></div>
      <div class="panel" id="summary" hidden><h2>Run</h2><dl class="facts" id="summary-facts">
      </dl></div>
      <div class="panel"><h2>Trajectory</h2><div class="downloads">
        <button type="button" data-format="tum">TUM</button>
        <button type="button" data-format="kitti">KITTI</button>
        <button type="button" data-format="json">odometry JSON</button>
      </div></div>
    </div>
    <div class="plots">
      <div class="panel"><canvas id="p-inliers" class="plot"></canvas></div>
      <div class="panel"><canvas id="p-latency" class="plot"></canvas></div>
      <div class="panel"><canvas id="p-fps" class="plot"></canvas></div>
    </div>
  </div>
  <p class="muted">Session <code>${id}</code>. Real time: each frame's pose as answered (fused
  when the session has an IMU). Smoothed: the back end's final estimate of a frame once it leaves
  the smoother's window (kept by the live session only, not stored).</p>`;
}

function median(values) {
  if (!values.length) return NaN;
  const sorted = Float64Array.from(values).sort();
  return sorted[Math.floor(sorted.length / 2)];
}

function pathLength(b) {
  let total = 0;
  for (let i = 1; i < b.n; i++) {
    const d = [0, 1, 2].map((a) => b.position[3 * i + a] - b.position[3 * (i - 1) + a]);
    total += Math.hypot(...d);
  }
  return total;
}

export function showSession(id, { app, crumb, say, failed }) {
  app.innerHTML = template(id);
  crumb.innerHTML = `<a href="/">sessions</a> / <span id="crumb-name"></span>`;
  crumb.querySelector("#crumb-name").textContent = id.slice(0, 8);
  const $ = (selector) => app.querySelector(selector);
  const buffer = new PoseBuffer();
  const smoothed = new PathBuffer();
  const views = [
    new TrajectoryView($("#top"), buffer, [[0, 1], [2, 1]], ["x →", "z ↑ (forward)"], smoothed),
    new TrajectoryView($("#side"), buffer, [[2, 1], [1, -1]], ["z →", "−y ↑ (up)"], smoothed),
  ];
  const plots = {
    inliers: new TimePlot($("#p-inliers"), "inliers", "", { color: "#1f9d55" }),
    latency: new TimePlot($("#p-latency"), "latency (queue + odometry)", "ms",
                          { color: "#7c3aed", digits: 1 }),
    fps: new TimePlot($("#p-fps"), "frames/s", "", { window: 300, color: "#2563eb", digits: 1 }),
  };
  // What tests and benchmarks read: counts, timings and the page's own measurements.
  const stats = { poses: 0, serverFrames: null, synced: false, firstDrawMs: null,
                  fullDrawMs: null, updates: 0, lastUpdateMs: 0, drawMsTotal: 0, drawMsMax: 0,
                  states: 0, activity: null, error: null };
  window.swarmvoView = { stats, buffer, smoothed, views, plots };
  let socket = null;
  let stopped = false;
  let frame = null;
  let lastState = null;
  let wasLive = false;
  let retry = null;

  function render() {
    frame = null;
    const started = performance.now();
    const redraws = views[0].redraws;
    let changed = false;
    for (const view of views) changed = view.update() || changed;
    for (const plot of Object.values(plots)) plot.draw();
    stats.lastUpdateMs = performance.now() - started;
    if (changed) {
      stats.updates += 1;
      stats.drawMsTotal += stats.lastUpdateMs;
      stats.drawMsMax = Math.max(stats.drawMsMax, stats.lastUpdateMs);
    }
    stats.drawn = views[0].drawn;
    stats.vertices = views[0].vertices;
    stats.redraws = views[0].redraws;
    if (views[0].redraws !== redraws) stats.fullDrawMs = stats.lastUpdateMs;
    if (changed && stats.firstPathMs === undefined) stats.firstPathMs = performance.now();
    if (stats.synced && stats.firstDrawMs === null) stats.firstDrawMs = performance.now();
  }

  function schedule() {
    if (frame === null && !stopped) frame = requestAnimationFrame(render);
  }

  function showFacts() {
    const b = buffer;
    const i = b.n - 1;
    $("#f-frames").textContent = String(b.n);
    if (i >= 0) {
      const status = STATUS_NAMES[b.status[i]];
      $("#f-status").innerHTML = `<span class="badge ${status}">${status}</span>`;
      $("#f-inliers").textContent = String(b.inliers[i]);
      $("#f-latency").textContent = `${b.latency[i].toFixed(1)} ms`;
    }
    if (lastState) {
      const s = lastState;
      $("#f-activity").innerHTML = `<span class="badge ${s.activity}">${s.activity}</span>`;
      $("#f-fps").textContent = s.frames_per_s === null ? "—" : s.frames_per_s.toFixed(1);
      $("#f-last").textContent = s.last_update === null ? "—"
        : ago(s.server_time - s.last_update);
    }
  }

  function showSummary() {
    const b = buffer;
    const facts = $("#summary-facts");
    const latencies = Array.from(b.latency.subarray(0, b.n));
    const inliers = Array.from(b.inliers.subarray(0, b.n));
    const duration = b.n ? b.time[b.n - 1] : 0;
    const rows = [
      ["frames", b.n],
      ["duration", `${duration.toFixed(1)} s`],
      ["path length", `${pathLength(b).toFixed(2)} m`],
      ["ok / degraded / lost", `${b.count(0)} / ${b.count(1)} / ${b.count(2)}`],
      ["median inliers", median(inliers).toFixed(0)],
      ["median latency", `${median(latencies).toFixed(1)} ms`],
    ];
    facts.innerHTML = rows.map(([k, v]) => `<dt>${k}</dt><dd>${v}</dd>`).join("");
    $("#summary").hidden = b.n === 0;
  }

  function onMessage(message) {
    const started = performance.now();
    handle(message);
    stats.messageMs = (stats.messageMs ?? 0) + performance.now() - started;
  }

  function handle(message) {
    if (message.type === "hello") {
      stats.helloMs = performance.now();
      crumb.querySelector("#crumb-name").textContent = message.name || id.slice(0, 8);
      document.title = `swarmvo · ${message.name || id.slice(0, 8)}`;
      say("");
    } else if (message.type === "world") {
      views[0].setAxes(message.top, message.top_labels);
      views[1].setAxes(message.side, message.side_labels, message.side_across);
      $("#world-note").textContent = message.note;
      stats.world = message.up;
    } else if (message.type === "poses") {
      buffer.append(message);
      stats.poses = buffer.n;
      for (let k = 0; k < message.index.length; k++) {
        plots.inliers.push(message.inliers[k]);
        plots.latency.push(message.latency_ms[k]);
      }
      $("#f-message").textContent = message.message;
      showFacts();
      // While a backlog streams in, its first part is drawn at once and the rest when it is
      // complete: each part that leaves the view would otherwise cost a full redraw.
      if (stats.synced || !views[0].drawn) schedule();
    } else if (message.type === "smoothed") {
      smoothed.append(message.position);
      stats.smoothed = smoothed.n;
      if (stats.synced || !views[0].drawn) schedule();
    } else if (message.type === "synced") {
      stats.syncedMs = performance.now();
      stats.synced = true;
      stats.serverFrames = message.frame_count;
      schedule();
    } else if (message.type === "state") {
      lastState = message;
      stats.states += 1;
      stats.activity = message.activity;
      stats.serverFrames = message.frame_count;
      if (message.activity === "live") plots.fps.push(message.frames_per_s ?? 0);
      showFacts();
      if (message.activity === "idle" && wasLive) {
        // The run ended: fit the whole trajectory again, tightly.
        for (const view of views) view.setAxes(view.axes, view.labels, view.across);
      }
      wasLive = message.activity === "live";
      if (message.activity === "idle") showSummary(); else $("#summary").hidden = true;
      schedule();
    } else if (message.type === "error") {
      stats.error = message.detail;
      failed(new ApiError(message.status, message.detail));
    }
  }

  function connect() {
    // A reconnect resumes after the last pose received.
    const since = buffer.n ? buffer.index[buffer.n - 1] + 1 : 0;
    socket = watch(id, since, onMessage, (event) => {
      if (stopped || event.code === 4401 || event.code === 4404 || event.code === 4400) return;
      say(`connection to the service lost (code ${event.code}); reconnecting…`);
      retry = setTimeout(connect, RECONNECT_MS);
    });
  }
  connect();
  window.addEventListener("resize", schedule);

  app.querySelector(".downloads").addEventListener("click", (event) => {
    const format = event.target.dataset.format;
    if (!format) return;
    const extension = { tum: "tum.txt", kitti: "kitti.txt", json: "json" }[format];
    download(`/v1/sessions/${id}/trajectory?format=${format}`, `${id}.${extension}`)
      .catch(failed);
  });

  return () => {
    stopped = true;
    clearTimeout(retry);
    window.removeEventListener("resize", schedule);
    if (socket) socket.close();
  };
}
