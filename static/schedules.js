// A site's schedules: their rhythm, source, detector, staleness and recent runs, run now /
// delete, and a create form (with the detector its runs compare with).

import { ApiError, api, describeError, itemsOf } from "./api.js";
import { loadCapabilities } from "./capabilities.js";
import { formatDate, h } from "./dom.js";
import { handleFailure } from "./session.js";

const CRON_EXAMPLE = "0 2 * * *";

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

function describeDetector(schedule, site) {
  if (schedule.detector) return `${schedule.detector.method} · ${schedule.detector.variant}`;
  const own = site && site.detector;
  return own ? `the site's (${own.method} · ${own.variant})` : "the site's";
}

/** "2 d", "5 h", "90 s": a staleness delay in words. */
function describeSeconds(seconds) {
  if (seconds % 86400 === 0) return `${seconds / 86400} d`;
  if (seconds % 3600 === 0) return `${seconds / 3600} h`;
  if (seconds % 60 === 0) return `${seconds / 60} min`;
  return `${seconds} s`;
}

function stalenessCell(schedule) {
  if (schedule.stale_since) {
    return h("span", { class: "badge badge-bad", dataset: { stale: "stale" } }, `stale since ${formatDate(schedule.stale_since)}`);
  }
  if (!schedule.stale_after_seconds) return h("span", { class: "muted", dataset: { stale: "unwatched" } }, "not watched");
  return h("span", { dataset: { stale: "fresh" } }, `fresh (stale after ${describeSeconds(schedule.stale_after_seconds)} without a scan)`);
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

function scheduleRow(schedule, runs, refresh, message, site) {
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
    h("td", { class: "schedule-detector" }, describeDetector(schedule, site)),
    h("td", {}, schedule.catch_up, schedule.compare_previous ? " · trend" : ""),
    h("td", { class: "schedule-staleness" }, stalenessCell(schedule)),
    h("td", {}, schedule.enabled ? formatDate(schedule.next_run_at) : "disabled"),
    h("td", {}, runs.length ? h("ul", { class: "schedule-runs" }, runs.map(runItem)) : h("span", { class: "muted" }, "no run yet")),
    h("td", {},
      h("button", { type: "button", class: "run-now", onclick: () => act("Running the schedule", () => api(`schedules/${schedule.id}/run`, { method: "POST" })) }, "Run now"),
      " ",
      h("button", { type: "button", class: "delete-schedule", onclick: () => act("Deleting the schedule", () => api(`schedules/${schedule.id}`, { method: "DELETE" })) }, "Delete")));
}

function detectorChoice(site) {
  const own = site.detector ? ` (${site.detector.method})` : "";
  const method = h("select", { id: "schedule-method", title: "The detector the schedule's comparisons use" },
    h("option", { value: "" }, `the site's detector${own}`));
  const variant = h("select", { id: "schedule-variant", title: "The detector's variant: improved (default) or as the paper wrote it" },
    h("option", { value: "improved", selected: true }, "improved"));
  loadCapabilities().then((capabilities) => {
    method.append(...capabilities.detector_methods.map((name) => h("option", { value: name }, name)));
    variant.replaceChildren(...capabilities.detector_variants.map((name) => h("option", { value: name, selected: name === "improved" }, name)));
  }).catch(() => {});
  const syncVariant = () => { variant.disabled = !method.value; };
  method.addEventListener("change", syncVariant);
  syncVariant();
  return { element: h("label", {}, "Detector ", method, " ", variant), read: () => (method.value ? { method: method.value, variant: variant.value } : null) };
}

function createForm(site, refresh) {
  const siteId = site.id;
  const kind = h("select", { id: "schedule-kind" }, h("option", { value: "cron" }, "cron"), h("option", { value: "interval" }, "interval (s)"));
  const rhythm = h("input", { type: "text", id: "schedule-rhythm", value: CRON_EXAMPLE, size: 14, placeholder: "minute hour day month weekday", title: "A cron expression (minute hour day month weekday) or a number of seconds" });
  const zone = h("input", { type: "text", id: "schedule-timezone", size: 16, value: Intl.DateTimeFormat().resolvedOptions().timeZone || "UTC" });
  const detector = detectorChoice(site);
  // A cron text means nothing as an interval (and the reverse): switching clears the field.
  kind.addEventListener("change", () => {
    const interval = kind.value === "interval";
    rhythm.value = interval ? "" : CRON_EXAMPLE;
    rhythm.placeholder = interval ? "seconds, e.g. 86400" : "minute hour day month weekday";
    rhythm.inputMode = interval ? "numeric" : "text";
    zone.disabled = interval;
  });
  const sourceKind = h("select", { id: "schedule-source-kind" }, ["uploads", "directory", "url"].map((value) => h("option", { value }, value)));
  const sourceValue = h("input", { type: "text", id: "schedule-source", placeholder: "directory path or https:// URL", size: 28 });
  const catchUp = h("select", { id: "schedule-catch-up" }, ["latest", "each", "none"].map((value) => h("option", { value }, `catch up: ${value}`)));
  const trend = h("input", { type: "checkbox", id: "schedule-trend" });
  const stale = h("input", { type: "number", id: "schedule-stale", min: 1, placeholder: "stale after (s)", size: 10 });
  const error = h("p", { class: "form-error", id: "schedule-error", role: "alert" });
  const button = h("button", { type: "button", id: "create-schedule", class: "primary" }, "Add schedule");
  button.addEventListener("click", async () => {
    error.textContent = "";
    const body = { catch_up: catchUp.value, compare_previous: trend.checked };
    if (kind.value === "cron") {
      body.cron = rhythm.value.trim();
      body.timezone = zone.value.trim();
    } else {
      const seconds = Number(rhythm.value.trim());
      if (!rhythm.value.trim() || !Number.isInteger(seconds) || seconds < 1) {
        error.textContent = "Give the interval as a whole number of seconds, e.g. 86400 for a day.";
        return;
      }
      body.interval_seconds = seconds;
    }
    if (sourceKind.value === "directory") body.source = { directory: sourceValue.value.trim() };
    else if (sourceKind.value === "url") body.source = { url: sourceValue.value.trim() };
    if (stale.value) body.stale_after_seconds = Number(stale.value);
    const chosen = detector.read();
    if (chosen) body.detector = chosen;
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
      h("label", {}, trend, " also compare with the previous scan"), stale, detector.element, button),
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
        h("thead", {}, h("tr", {}, ["Rhythm", "Source", "Detector", "Policy", "Staleness", "Next run", "Recent runs", ""].map((title) => h("th", {}, title)))),
        h("tbody", {}, schedules.map((schedule, index) => scheduleRow(schedule, runs[index], refresh, message, site))))
      : h("p", { class: "muted", id: "no-schedules" }, "No schedule: scans are compared only when they are uploaded."));
  }
  const node = h("section", { class: "card", id: "schedules-card" },
    h("h2", {}, "Schedules"),
    h("p", { class: "muted" }, "Compare the newest scan with the reference on a rhythm; a period without a new scan is recorded as missed."),
    list, message, createForm(site, refresh));
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
