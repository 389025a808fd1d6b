// The key's sessions, refreshed every two seconds.
import { getJson } from "./api.js";

const REFRESH_MS = 2000;

function escapeHtml(text) {
  return String(text).replace(/[&<>"']/g, (c) => `&#${c.charCodeAt(0)};`);
}

export function ago(seconds) {
  if (seconds === null || seconds === undefined) return "—";
  if (seconds < 1.5) return "just now";
  if (seconds < 90) return `${Math.round(seconds)} s ago`;
  if (seconds < 5400) return `${Math.round(seconds / 60)} min ago`;
  return `${Math.round(seconds / 3600)} h ago`;
}

function row(session, serverTime) {
  const name = session.name || session.id.slice(0, 8);
  const fps = session.frames_per_s === null ? "—" : session.frames_per_s.toFixed(1);
  const last = session.last_update === null ? null : serverTime - session.last_update;
  const status = session.last_status
    ? `<span class="badge ${session.last_status}">${session.last_status}</span>` : "";
  return `<tr data-id="${session.id}">
    <td><a href="/sessions/${session.id}">${escapeHtml(name)}</a></td>
    <td><span class="badge ${session.activity}">${session.activity}</span> ${status}</td>
    <td class="num">${session.frame_count}</td>
    <td class="num">${fps}</td>
    <td title="newest pose stored by this server">${ago(last)}</td>
    <td class="muted">${new Date(session.created_at).toLocaleString()}</td>
  </tr>`;
}

export function showSessionList({ app, crumb, say, failed }) {
  crumb.textContent = "sessions";
  document.title = "swarmvo · sessions";
  let timer = null;
  let stopped = false;

  async function refresh() {
    try {
      const answer = await getJson("/v1/live/sessions");
      if (stopped) return;
      say("");
      const rows = answer.sessions.map((s) => row(s, answer.server_time)).reverse();
      app.innerHTML = `<h1>Sessions <span class="muted">(${answer.sessions.length})</span></h1>
        ${rows.length ? `<table id="sessions"><thead><tr><th>name</th><th>status</th>
          <th class="num">frames</th><th class="num">frames/s</th><th>last update</th>
          <th>created</th></tr></thead><tbody>${rows.join("")}</tbody></table>`
        : `<p class="muted">No sessions for this key yet.</p>`}`;
      timer = setTimeout(refresh, REFRESH_MS);
    } catch (error) {
      if (stopped) return;
      failed(error);
      if (error.status !== 401) timer = setTimeout(refresh, REFRESH_MS);
    }
  }

  refresh();
  return () => {
    stopped = true;
    clearTimeout(timer);
  };
}
