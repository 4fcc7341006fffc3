// Signing in and out: the page trades a pasted token for a session cookie and forgets the token.

import { ApiError, api, describeError } from "./api.js";
import { h } from "./dom.js";
import { app, setCrumbs, showBanner, startRender } from "./page.js";

let me = null;
let onSignedIn = () => {};

function renderWho() {
  const who = document.getElementById("who");
  if (!me) {
    who.hidden = true;
    return;
  }
  document.getElementById("who-text").textContent = `${me.organisation || me.organisation_id} · ${me.role}`;
  who.hidden = false;
}

function renderSignIn(message = "") {
  startRender();
  renderWho();
  setCrumbs();
  showBanner(message ? message : "", "error");
  const error = h("p", { class: "form-error", id: "sign-in-error", role: "alert" });
  const input = h("input", { id: "token", name: "token", type: "password", autocomplete: "off", required: true, placeholder: "sdt_…", size: 48 });
  const form = h("form", { id: "sign-in-form", class: "card sign-in" },
    h("h1", {}, "Sign in"),
    h("p", { class: "muted" }, "Paste an API token: the one ", h("code", {}, "make run"), " printed, or one from ",
      h("code", {}, "scandiff token create"), ". The page trades it for a session cookie and forgets it."),
    h("label", { for: "token" }, "Token"),
    input,
    h("div", { class: "actions" }, h("button", { type: "submit", id: "sign-in-button", class: "primary" }, "Sign in")),
    error);
  form.addEventListener("submit", async (event) => {
    event.preventDefault();
    error.textContent = "";
    const token = input.value.trim();
    if (!token) {
      error.textContent = "Enter a token.";
      return;
    }
    try {
      me = await api("session", { method: "POST", body: { token } });
      input.value = "";
      showBanner("");
      renderWho();
      onSignedIn();
    } catch (failure) {
      error.textContent = failure instanceof ApiError && failure.status === 401
        ? "This token is not valid: it is unknown, or it was revoked. Check for a missing character."
        : describeError(failure);
    }
  });
  app.replaceChildren(form);
  input.focus();
}

/** Whether the signed-in token may change things (writer or admin; a reader only reads). */
export function canWrite() {
  return Boolean(me) && me.role !== "reader";
}

/** Wire the sign-out button; `afterSignIn()` runs when the sign-in form has opened a session. */
export function startSessions(afterSignIn) {
  onSignedIn = afterSignIn;
  document.getElementById("sign-out").addEventListener("click", async () => {
    try {
      await api("session", { method: "DELETE" });
    } catch {
      // Signing out locally is enough if the server is gone.
    }
    me = null;
    location.hash = "#/";
    renderSignIn("You are signed out.");
    showBanner("You are signed out.", "info");
  });
}

/** Whether a session is open (asking the service once); shows the sign-in form or the error if not. */
export async function ensureSignedIn() {
  if (!me) {
    try {
      me = await api("session");
    } catch (failure) {
      if (failure instanceof ApiError && failure.status === 401) {
        renderSignIn(failure.code === "session_ended" ? `Please sign in again: ${failure.detail}.` : "");
        return false;
      }
      showBanner(describeError(failure));
      return false;
    }
  }
  renderWho();
  return true;
}

/** Show a failure of `where`: an ended session goes back to the sign-in form, anything else to the banner. */
export async function handleFailure(error, where) {
  if (error instanceof ApiError && error.status === 401) {
    me = null;
    renderSignIn(describeError(error));
    return;
  }
  showBanner(`${where}: ${describeError(error)}`);
}
