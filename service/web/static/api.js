// The API key and the calls made with it. The key lives in sessionStorage only: it is sent as
// a bearer header (REST) or in the first WebSocket message, never in a URL.
const KEY_NAME = "swarmvo.key";

export class ApiError extends Error {
  constructor(status, detail) {
    super(detail);
    this.status = status;
  }
}

export function storedKey() {
  return sessionStorage.getItem(KEY_NAME);
}

export function storeKey(key) {
  sessionStorage.setItem(KEY_NAME, key);
}

export function forgetKey() {
  sessionStorage.removeItem(KEY_NAME);
}

function headers() {
  const key = storedKey();
  return key ? { Authorization: `Bearer ${key}` } : {};
}

async function detailOf(response) {
  try {
    const body = await response.json();
    if (typeof body.detail === "string") return body.detail;
  } catch (_) { /* not JSON */ }
  return `${response.status} ${response.statusText}`;
}

export async function getJson(path) {
  let response;
  try {
    response = await fetch(path, { headers: headers(), cache: "no-store" });
  } catch (error) {
    throw new ApiError(0, `the service cannot be reached (${error.message})`);
  }
  if (!response.ok) throw new ApiError(response.status, await detailOf(response));
  return response.json();
}

// A download needs the bearer header, so a plain link cannot do it: fetch, then save the blob.
export async function download(path, filename) {
  const response = await fetch(path, { headers: headers() });
  if (!response.ok) throw new ApiError(response.status, await detailOf(response));
  const url = URL.createObjectURL(await response.blob());
  const link = document.createElement("a");
  link.href = url;
  link.download = filename;
  document.body.append(link);
  link.click();
  link.remove();
  setTimeout(() => URL.revokeObjectURL(url), 10000);
}

// The watcher channel: authenticate with the first message (and say from which frame on the
// poses are wanted), then hand each message on.
export function watch(sessionId, since, onMessage, onClose) {
  const scheme = location.protocol === "https:" ? "wss" : "ws";
  const socket = new WebSocket(`${scheme}://${location.host}/v1/sessions/${sessionId}/watch`);
  socket.onopen = () => socket.send(JSON.stringify({ type: "auth", token: storedKey() || "", since }));
  socket.onmessage = (event) => onMessage(JSON.parse(event.data));
  socket.onclose = (event) => onClose(event);
  return socket;
}
