// A site's schedules: their rhythm, source and recent runs, run now / delete, and a create form.

import { ApiError, api, describeError, itemsOf } from "./api.js";
import { formatDate, h } from "./dom.js";
import { handleFailure } from "./session.js";

const RECENT_RUNS = 5;
let section = { siteId: null, node: null, refresh: null };

function describeRhythm(schedule) {
  return schedule.cron ? `cron ${schedule.cron} (${schedule.timezone})` : `every ${schedule.interval_seconds} s`;
}

function describeSource(source) {
  if (source && source.directory) return `directory ${source.directory}`;
  if (source && source.url) return `URL ${source.url}`;
  return "uploads";
}

function runBadge(run) {
  const classes = { compared: "ok", failed: "bad", missed: "bad", running: "busy", skipped: "wait" };
  return h("span", { class: `badge badge-${classes[run.status] || "wait"}`, dataset: { status: run.status } }, run.status);
}

function runItem(run) {
  return h("li", { class: "schedule-run", dataset: { runId: run.id, status: run.status } },
    runBadge(run), " ", formatDate(run.period_start), run.kind === "manual" ? " (run now)" : "",
    run.job_id ? [" · ", h("a", { href: `#/jobs/${run.job_id}` }, "comparison")] : null,
    run.trend_job_id ? [" · ", h("a", { href: `#/jobs/${run.trend_job_id}` }, "trend")] : null,
    run.error ? h("span", { class: "error-cell" }, ` ${run.error}`) : null);
}

function scheduleRow(schedule, runs, refresh, message) {
  const act = async (what, request) => {
    message.textContent = "";
    message.className = "form-error";
    try {
      await request();
      await refresh();
    } catch (failure) {
      if (failure instanceof ApiError && failure.status === 401) return handleFailure(failure, what);
      message.textContent = `${what} failed: ${describeError(failure)}`;
      await refresh().catch(() => {});
    }
  };
  return h("tr", { dataset: { scheduleId: schedule.id } },
    h("td", {}, describeRhythm(schedule)),
    h("td", {}, describeSource(schedule.source)),
    h("td", {}, schedule.catch_up, schedule.compare_previous ? " · trend" : ""),
    h("td", {}, schedule.enabled ? formatDate(schedule.next_run_at) : "disabled",
      schedule.stale_since ? h("div", { class: "badge badge-bad" }, `stale since ${formatDate(schedule.stale_since)}`) : null),
    h("td", {}, runs.length ? h("ul", { class: "schedule-runs" }, runs.map(runItem)) : h("span", { class: "muted" }, "no run yet")),
    h("td", {},
      h("button", { type: "button", class: "run-now", onclick: () => act("Running the schedule", () => api(`schedules/${schedule.id}/run`, { method: "POST" })) }, "Run now"),
      " ",
      h("button", { type: "button", class: "delete-schedule", onclick: () => act("Deleting the schedule", () => api(`schedules/${schedule.id}`, { method: "DELETE" })) }, "Delete")));
}

function createForm(siteId, refresh) {
  const kind = h("select", { id: "schedule-kind" }, h("option", { value: "cron" }, "cron"), h("option", { value: "interval" }, "interval (s)"));
  const rhythm = h("input", { type: "text", id: "schedule-rhythm", value: "0 2 * * *", size: 14, title: "A cron expression (minute hour day month weekday) or a number of seconds" });
  const zone = h("input", { type: "text", id: "schedule-timezone", size: 16, value: Intl.DateTimeFormat().resolvedOptions().timeZone || "UTC" });
  const sourceKind = h("select", { id: "schedule-source-kind" }, ["uploads", "directory", "url"].map((value) => h("option", { value }, value)));
  const sourceValue = h("input", { type: "text", id: "schedule-source", placeholder: "directory path or https:// URL", size: 28 });
  const catchUp = h("select", { id: "schedule-catch-up" }, ["latest", "each", "none"].map((value) => h("option", { value }, `catch up: ${value}`)));
  const trend = h("input", { type: "checkbox", id: "schedule-trend" });
  const stale = h("input", { type: "number", id: "schedule-stale", min: 1, placeholder: "stale after (s)", size: 10 });
  const error = h("p", { class: "form-error", id: "schedule-error", role: "alert" });
  const button = h("button", { type: "button", id: "create-schedule", class: "primary" }, "Add schedule");
  button.addEventListener("click", async () => {
    error.textContent = "";
    const body = { timezone: zone.value.trim(), catch_up: catchUp.value, compare_previous: trend.checked };
    if (kind.value === "cron") body.cron = rhythm.value.trim();
    else body.interval_seconds = Number(rhythm.value);
    if (sourceKind.value === "directory") body.source = { directory: sourceValue.value.trim() };
    else if (sourceKind.value === "url") body.source = { url: sourceValue.value.trim() };
    if (stale.value) body.stale_after_seconds = Number(stale.value);
    button.disabled = true;
    try {
      await api(`sites/${siteId}/schedules`, { method: "POST", body });
      await refresh();
    } catch (failure) {
      if (failure instanceof ApiError && failure.status === 401) return handleFailure(failure, "Adding a schedule");
      error.textContent = `The schedule was not added: ${describeError(failure)}`;
    } finally {
      button.disabled = false;
    }
  });
  return h("div", { class: "schedule-form" },
    h("div", { class: "upload-row" }, kind, rhythm, zone, sourceKind, sourceValue, catchUp,
      h("label", {}, trend, " also compare with the previous scan"), stale, button),
    error);
}

function buildSection(site) {
  const list = h("div", { id: "schedules-list" }, h("p", { class: "muted" }, "Loading schedules…"));
  const message = h("p", { class: "form-error", id: "schedules-message", role: "status" });
  async function refresh() {
    const schedules = itemsOf(await api(`sites/${site.id}/schedules`));
    const runs = await Promise.all(schedules.map((schedule) => api(`schedules/${schedule.id}/runs?limit=${RECENT_RUNS}`).then(itemsOf)));
    list.replaceChildren(schedules.length
      ? h("table", { class: "table", id: "schedules-table" },
        h("thead", {}, h("tr", {}, ["Rhythm", "Source", "Policy", "Next run", "Recent runs", ""].map((title) => h("th", {}, title)))),
        h("tbody", {}, schedules.map((schedule, index) => scheduleRow(schedule, runs[index], refresh, message))))
      : h("p", { class: "muted", id: "no-schedules" }, "No schedule: scans are compared only when they are uploaded."));
  }
  const node = h("section", { class: "card", id: "schedules-card" },
    h("h2", {}, "Schedules"),
    h("p", { class: "muted" }, "Compare the newest scan with the reference on a rhythm; a period without a new scan is recorded as missed."),
    list, message, createForm(site.id, refresh));
  return { node, refresh };
}

/** The site's schedules section; live refreshes keep the same one (its form) and reload its list. */
export function reusableSchedulesSection(site) {
  if (section.siteId !== site.id || !document.body.contains(section.node)) {
    section = { siteId: site.id, ...buildSection(site) };
  }
  section.refresh().catch((failure) => handleFailure(failure, "Loading the schedules"));
  return section.node;
}
