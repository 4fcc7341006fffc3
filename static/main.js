// scandiff dashboard: sign in, sites, per-site timelines and jobs, job results, 3D view links.
// Plain ES modules, no framework and nothing from a CDN. Every request goes to this service
// with the HttpOnly session cookie (the page never holds the token after signing in).
// This module routes the hash (#/, #/sites/<id>, #/jobs/<id>, #/inbox[/<site id>],
// #/webhooks[/<id>]) to its view; a new page opens at its top.

import { ApiError, describeError } from "./api.js";
import { h } from "./dom.js";
import { renderInbox } from "./inbox.js";
import { renderJob } from "./job.js";
import { app, currentRender, showBanner, startRender } from "./page.js";
import { ensureSignedIn, handleFailure, startSessions } from "./session.js";
import { renderSite } from "./site.js";
import { renderSites } from "./sites.js";
import { renderWebhooks } from "./webhooks.js";

async function route() {
  startRender();
  const generation = currentRender();
  showBanner("");
  if (!(await ensureSignedIn())) return;
  const hash = location.hash.replace(/^#/, "") || "/";
  const siteMatch = hash.match(/^\/sites\/([^/]+)$/);
  const jobMatch = hash.match(/^\/jobs\/([^/]+)$/);
  const webhooksMatch = hash.match(/^\/webhooks(?:\/([^/]+))?$/);
  const inboxMatch = hash.match(/^\/inbox(?:\/([^/]+))?$/);
  try {
    if (siteMatch) await renderSite(decodeURIComponent(siteMatch[1]));
    else if (jobMatch) await renderJob(decodeURIComponent(jobMatch[1]));
    else if (inboxMatch) await renderInbox(inboxMatch[1] ? decodeURIComponent(inboxMatch[1]) : null);
    else if (webhooksMatch) await renderWebhooks(webhooksMatch[1] ? decodeURIComponent(webhooksMatch[1]) : null);
    else await renderSites();
    if (generation === currentRender()) window.scrollTo(0, 0); // not the last page's scroll
  } catch (failure) {
    if (failure instanceof ApiError && failure.status === 404) {
      app.replaceChildren(h("section", { class: "card" }, h("h1", {}, "Not found"),
        h("p", {}, describeError(failure)), h("p", {}, h("a", { href: "#/" }, "Back to the sites"))));
      return;
    }
    await handleFailure(failure, "Loading this page");
  }
}

startSessions(route);
window.addEventListener("hashchange", route);
route();
