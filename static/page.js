// The page's shared parts: the main area, the banner, the breadcrumbs, and which render is current
// (a render started later wins; polling belongs to the current render only).

import { h } from "./dom.js";

const POLL_MS = 1500;

export const app = document.getElementById("app");
const banner = document.getElementById("banner");
const crumbs = document.getElementById("crumbs");
let pollTimer = null;
let renderGeneration = 0;

export function showBanner(message, kind = "error") {
  if (!message) {
    banner.hidden = true;
    banner.textContent = "";
    return;
  }
  banner.className = `banner banner-${kind}`;
  banner.textContent = message;
  banner.hidden = false;
}

export function setCrumbs(...parts) {
  crumbs.replaceChildren(...parts.flatMap((part, index) => (index ? [h("span", { class: "crumb-sep" }, "›"), part] : [part])));
}

function stopPolling() {
  if (pollTimer !== null) clearTimeout(pollTimer);
  pollTimer = null;
}

/** Start a new render: earlier renders and their polling are now stale. */
export function startRender() {
  renderGeneration += 1;
  stopPolling();
}

/** The current render; a render that awaited compares it with the one it started in. */
export function currentRender() {
  return renderGeneration;
}

export function schedulePoll(callback) {
  stopPolling();
  const generation = renderGeneration;
  pollTimer = setTimeout(() => {
    if (generation === renderGeneration) callback();
  }, POLL_MS);
}
