// The review inbox: the organisation's succeeded jobs that await a verdict, newest first, with
// counts per site, reviewed by keyboard alone: j/k or the arrows move, v or Enter opens the 3D
// view, c confirms, f marks a false alarm, r (twice) makes the scan the site's reference.
// Routes: #/inbox (every site) and #/inbox/<site id> (one site). Reads GET /api/v1/jobs and
// GET /api/v1/jobs/awaiting-review/counts; writes with POST /api/v1/jobs/{id}/verdict.

import { ApiError, api, describeError, itemsOf } from "./api.js";
import { decisionBadge, formatDate, h } from "./dom.js";
import { warningBadge } from "./explain.js";
import { app, currentRender, setCrumbs } from "./page.js";
import { canWrite, handleFailure } from "./session.js";
import { VERDICT_NAMES } from "./timeline.js";

const PAGE = 50;
const KEYS = [
  ["j / ↓", "next job"],
  ["k / ↑", "previous job"],
  ["v / Enter", "open the 3D view"],
  ["o", "open the job page"],
  ["c", "confirm the decision"],
  ["f", "false alarm"],
  ["r, r", "new reference (press r twice)"],
];
const VERDICT_KEYS = { c: "confirmed", f: "false_alarm" };

// The inbox on screen: its rows (one per job), the focused one, the site names, its state.
let inbox = null;

function jobQuery(siteId, cursor) {
  const query = new URLSearchParams({ status: "succeeded", verdict: "none", limit: String(PAGE) });
  if (siteId) query.set("site_id", siteId);
  if (cursor) query.set("cursor", cursor);
  return `jobs?${query}`;
}

function countsList(counts, siteId) {
  const entries = [h("li", {}, h("a", { href: "#/inbox", class: siteId ? "" : "current", id: "inbox-all" },
    `All sites (${counts.total})`))];
  for (const site of counts.sites) {
    entries.push(h("li", { dataset: { siteId: site.site_id, count: String(site.count) } },
      h("a", { href: `#/inbox/${site.site_id}`, class: site.site_id === siteId ? "current" : "" },
        `${site.site_name || site.site_id.slice(0, 8)} (${site.count})`)));
  }
  return h("ul", { class: "inbox-counts", id: "inbox-counts" }, entries);
}

function legend() {
  return h("dl", { class: "key-legend", id: "inbox-keys", "aria-label": "Keyboard shortcuts" },
    KEYS.flatMap(([keys, meaning]) => [h("dt", {}, h("kbd", {}, keys)), h("dd", {}, meaning)]));
}

function jobRow(job, siteNames) {
  const explanation = job.explanation && job.explanation.text ? job.explanation.text : "";
  const row = h("li", { class: "inbox-row", tabindex: "-1", role: "option", "aria-selected": "false", dataset: { jobId: job.id, siteId: job.site_id } },
    h("div", { class: "inbox-row-head" },
      h("span", { class: "inbox-site" }, siteNames.get(job.site_id) || job.site_id.slice(0, 8)),
      h("span", { class: "muted" }, formatDate(job.created_at)),
      decisionBadge(job), warningBadge(job),
      h("span", { class: "muted" }, `${job.n_regions ?? 0} regions · ${job.method} · ${job.variant}`),
      h("span", { class: "inbox-verdict", "aria-live": "polite" })),
    h("div", { class: "inbox-files" }, h("a", { href: `#/jobs/${job.id}`, tabindex: "-1" }, job.scan_filename || job.id.slice(0, 8)),
      h("span", { class: "muted" }, ` vs ${job.reference_filename || "?"}`)),
    explanation ? h("p", { class: "inbox-why muted" }, explanation) : null);
  row.addEventListener("click", (event) => {
    if (event.target.closest("a")) return;
    focusRow(inbox.rows.indexOf(row));
  });
  return row;
}

function focusRow(index) {
  if (!inbox || !inbox.rows.length) return;
  const bounded = Math.max(0, Math.min(inbox.rows.length - 1, index));
  inbox.rows.forEach((row, position) => {
    row.classList.toggle("focused", position === bounded);
    row.setAttribute("aria-selected", String(position === bounded));
  });
  inbox.focused = bounded;
  inbox.armedReference = null;
  inbox.status.textContent = "";
  const row = inbox.rows[bounded];
  row.focus({ preventScroll: true });
  row.scrollIntoView({ block: "nearest" });
}

function setRowVerdict(row, verdict, state) {
  row.dataset.verdict = verdict;
  row.dataset.verdictState = state;
  row.classList.toggle("reviewed", state === "saved");
  const label = row.querySelector(".inbox-verdict");
  const name = VERDICT_NAMES[verdict] || verdict;
  label.className = `inbox-verdict badge ${state === "failed" ? "badge-bad" : state === "saved" ? "badge-ok" : "badge-wait"}`;
  label.textContent = state === "saved" ? name : state === "failed" ? `${name}: not saved` : `${name}…`;
}

async function giveVerdict(verdict) {
  const row = inbox.rows[inbox.focused];
  if (!row) return;
  if (!canWrite()) {
    inbox.status.textContent = "Your token's role (reader) cannot give verdicts: sign in with a writer's token.";
    return;
  }
  const jobId = row.dataset.jobId;
  const wasWaiting = !row.dataset.verdict || row.dataset.verdictState === "failed";
  setRowVerdict(row, verdict, "saving");
  focusRow(inbox.focused + 1); // on to the next job while this one saves
  try {
    await api(`jobs/${jobId}/verdict`, { method: "POST", body: { verdict } });
    setRowVerdict(row, verdict, "saved");
    if (wasWaiting) changeCount(row.dataset.siteId, -1);
  } catch (failure) {
    if (failure instanceof ApiError && failure.status === 401) return handleFailure(failure, "Saving the verdict");
    setRowVerdict(row, verdict, "failed");
    inbox.status.textContent = `Not saved: ${describeError(failure)}`;
  }
}

function changeCount(siteId, delta) {
  inbox.counts.total += delta;
  const site = inbox.counts.sites.find((entry) => entry.site_id === siteId);
  if (site) site.count += delta;
  const countsNode = countsList(inbox.counts, inbox.siteId);
  inbox.countsNode.replaceWith(countsNode);
  inbox.countsNode = countsNode;
  inbox.title.textContent = `Review inbox (${inbox.counts.total} awaiting a verdict)`;
}

function onKey(event) {
  if (!inbox || !document.body.contains(inbox.list)) return;
  if (event.ctrlKey || event.metaKey || event.altKey) return;
  const target = event.target instanceof Element ? event.target : null;
  if (document.querySelector("dialog[open]")) return;
  if (target && target.closest("input, textarea, select, [contenteditable]")) return;
  const key = event.key;
  if (key === "Enter" && target && target.closest("a, button")) return; // their own action
  const row = inbox.rows[inbox.focused];
  if (key === "j" || key === "ArrowDown") focusRow(inbox.focused + 1);
  else if (key === "k" || key === "ArrowUp") focusRow(inbox.focused - 1);
  else if ((key === "v" || key === "Enter") && row) window.open(`/jobs/${row.dataset.jobId}/view`, "_blank", "noopener");
  else if (key === "o" && row) location.hash = `#/jobs/${row.dataset.jobId}`;
  else if (VERDICT_KEYS[key] && row) giveVerdict(VERDICT_KEYS[key]);
  else if (key === "r" && row) {
    if (inbox.armedReference === row.dataset.jobId) giveVerdict("new_reference");
    else {
      inbox.armedReference = row.dataset.jobId;
      inbox.status.textContent = "Press r again to make this job's scan the site's reference (any other key cancels).";
    }
    event.preventDefault();
    return;
  } else return;
  event.preventDefault();
}

document.addEventListener("keydown", onKey);

export async function renderInbox(siteId = null) {
  const generation = currentRender();
  const [counts, firstPage] = await Promise.all([api("jobs/awaiting-review/counts"), api(jobQuery(siteId, null))]);
  if (generation !== currentRender()) return;
  const siteNames = new Map(counts.sites.map((site) => [site.site_id, site.site_name]));
  const siteName = siteId ? siteNames.get(siteId) || "site" : null;
  setCrumbs(h("a", { href: "#/" }, "Sites"), h("a", { href: "#/inbox" }, "Review inbox"), ...(siteName ? [h("span", {}, siteName)] : []));

  const list = h("ol", { class: "inbox-list", id: "inbox-list", role: "listbox", "aria-label": "Jobs awaiting a verdict, newest first" });
  const more = h("button", { type: "button", id: "inbox-more", hidden: !firstPage.next_cursor }, "Load more");
  const status = h("p", { id: "inbox-status", role: "status", class: "muted" });
  const title = h("h1", { id: "inbox-title" }, `Review inbox (${counts.total} awaiting a verdict)`);
  const countsNode = countsList(counts, siteId);
  inbox = { rows: [], focused: 0, list, status, title, counts, countsNode, siteId, cursor: firstPage.next_cursor, armedReference: null };

  function append(jobs) {
    const rows = jobs.map((job) => jobRow(job, siteNames));
    inbox.rows.push(...rows);
    list.append(...rows);
  }
  append(itemsOf(firstPage));
  more.addEventListener("click", async () => {
    try {
      const page = await api(jobQuery(siteId, inbox.cursor));
      append(itemsOf(page));
      inbox.cursor = page.next_cursor;
      more.hidden = !inbox.cursor;
    } catch (failure) {
      await handleFailure(failure, "Loading more jobs");
    }
  });

  app.replaceChildren(
    h("section", { class: "card", id: "inbox" },
      title,
      h("p", { class: "muted" }, "Succeeded jobs without a verdict, newest first. Review them with the keys below; a verdict moves on to the next job."),
      countsNode,
      legend(),
      status,
      inbox.rows.length ? list : h("p", { class: "muted", id: "inbox-empty" }, "Nothing to review: every finished job has a verdict."),
      more));
  if (inbox.rows.length) focusRow(0);
}
