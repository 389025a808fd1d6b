// The page: asks for the API key when needed, then shows the sessions list or one session.
import { ApiError, forgetKey, storeKey, storedKey } from "./api.js";
import { showSessionList } from "./list.js";
import { showSession } from "./session.js";

const app = document.getElementById("app");
const notice = document.getElementById("notice");
const crumb = document.getElementById("crumb");
const changeKey = document.getElementById("change-key");
let stopCurrent = () => {};

export function say(text) {
  notice.textContent = text;
  notice.hidden = !text;
}

function askForKey(reason) {
  stopCurrent();
  crumb.textContent = "";
  say(reason);
  app.innerHTML = `
    <form class="key panel" autocomplete="off">
      <h1>API key</h1>
      <p class="muted">The key is kept in this tab only (session storage) and sent to this
      service as a bearer header.</p>
      <input id="key" type="password" placeholder="API key" required autofocus>
      <button type="submit">Show my sessions</button>
    </form>`;
  app.querySelector("form").addEventListener("submit", (event) => {
    event.preventDefault();
    storeKey(app.querySelector("#key").value.trim());
    say("");
    route();
  });
}

// A refused key or an unreachable service ends the current view with a message, never blank.
function failed(error) {
  if (error instanceof ApiError && error.status === 401) {
    const hadKey = storedKey() !== null;
    forgetKey();
    askForKey(hadKey ? `The API key was refused: ${error.message}`
                     : "This service needs an API key.");
    return;
  }
  say(error.message || String(error));
}

function route() {
  stopCurrent();
  changeKey.hidden = storedKey() === null;
  const match = location.pathname.match(/^\/sessions\/([^/]+)\/?$/);
  const context = { app, crumb, say, failed };
  stopCurrent = match ? showSession(decodeURIComponent(match[1]), context)
                      : showSessionList(context);
}

changeKey.addEventListener("click", () => {
  forgetKey();
  askForKey("");
});

window.addEventListener("error", (event) => say(`page error: ${event.message}`));
window.addEventListener("unhandledrejection", (event) => failed(event.reason));
route();
