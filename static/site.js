// One site: its reference, the upload panel, the timeline of scores and the filtered list of jobs.

import { api, itemsOf } from "./api.js";
import { loadCapabilities } from "./capabilities.js";
import { decisionBadge, formatDate, formatNumber, h, jobProgress, statusBadge } from "./dom.js";
import { warningBadge } from "./explain.js";
import { app, currentRender, schedulePoll, setCrumbs, startRender } from "./page.js";
import { siteScansCard } from "./scans.js";
import { canWrite, handleFailure } from "./session.js";
import { reusableSiteAdminPanel } from "./site_admin.js";
import { drawTimeline } from "./timeline.js";
import { reusableSchedulesSection } from "./schedules.js";
import { reusableUploadPanel } from "./upload.js";

const JOBS_PAGE = 100;
const TIMELINE_MAX_JOBS = 300;

const siteFilters = new Map();

async function fetchSiteJobs(siteId, filters) {
  const jobs = [];
  let cursor = null;
  do {
    const query = new URLSearchParams({ limit: String(JOBS_PAGE) });
    if (filters.changed) query.set("changed", "true");
    if (filters.status) query.set("status", filters.status);
    if (cursor) query.set("cursor", cursor);
    const page = await api(`sites/${siteId}/jobs?${query}`);
    jobs.push(...itemsOf(page));
    cursor = page && !Array.isArray(page) ? page.next_cursor : null;
  } while (cursor && jobs.length < TIMELINE_MAX_JOBS);
  return jobs;
}

/** "scan.ply vs reference.ply": the files a job compared. */
export function jobFiles(job) {
  return [h("span", { class: "scan-name" }, job.scan_filename || "?"), h("span", { class: "muted" }, " vs "),
    h("span", { class: "reference-name" }, job.reference_filename || "?")];
}

export async function renderSite(siteId) {
  const generation = currentRender();
  const filters = siteFilters.get(siteId) || { changed: false, status: "" };
  siteFilters.set(siteId, filters);
  const site = await api(`sites/${siteId}`);
  const writable = canWrite();
  const [reference, jobs, allJobs, scansCard, capabilities] = await Promise.all([
    site.reference_scan_id ? api(`scans/${site.reference_scan_id}`).catch(() => null) : Promise.resolve(null),
    fetchSiteJobs(siteId, filters),
    filters.changed || filters.status ? fetchSiteJobs(siteId, { changed: false, status: "" }) : Promise.resolve(null),
    siteScansCard(site, writable, rerender),
    writable ? loadCapabilities() : Promise.resolve(null),
  ]);
  if (generation !== currentRender()) return;
  const timelineJobs = allJobs || jobs;
  setCrumbs(h("a", { href: "#/" }, "Sites"), h("span", {}, site.name));

  const timeline = h("div", { id: "timeline", class: "timeline" });
  drawTimeline(timeline, timelineJobs, (job) => { location.hash = `#/jobs/${job.id}`; }, site);

  const changedOnly = h("input", { type: "checkbox", id: "filter-changed", checked: filters.changed });
  const statusSelect = h("select", { id: "filter-status" },
    ["", "queued", "running", "succeeded", "failed"].map((value) => h("option", { value, selected: filters.status === value }, value || "any status")));
  const applyFilters = () => {
    filters.changed = changedOnly.checked;
    filters.status = statusSelect.value;
    rerender();
  };
  changedOnly.addEventListener("change", applyFilters);
  statusSelect.addEventListener("change", applyFilters);

  const rows = jobs.map((job) => h("tr", { dataset: { jobId: job.id, status: job.status } },
    h("td", {}, h("a", { href: `#/jobs/${job.id}`, class: "job-link" }, formatDate(job.created_at))),
    h("td", { class: "job-files" }, jobFiles(job)),
    h("td", {}, statusBadge(job), " ", jobProgress(job)),
    h("td", { class: "num" }, formatNumber(job.score)),
    h("td", {}, decisionBadge(job), " ", warningBadge(job)),
    h("td", { class: "num" }, job.n_regions ?? "—"),
    h("td", {}, `${job.method} · ${job.variant}`),
    h("td", { class: "error-cell" }, job.status === "failed" ? (job.error || "failed without a reason") : "")));

  app.replaceChildren(
    h("section", { class: "card" },
      h("h1", { id: "site-name" }, site.name),
      site.description ? h("p", {}, site.description) : null,
      h("dl", { class: "facts" },
        h("dt", {}, "Reference"),
        h("dd", {}, reference ? `${reference.filename} · ${reference.n_points.toLocaleString()} points · uploaded ${formatDate(reference.created_at)}` : "none yet"),
        h("dt", {}, "Detector"),
        h("dd", {}, site.detector ? `${site.detector.method} · ${site.detector.variant}` : "default")),
      writable && capabilities ? reusableSiteAdminPanel(site, capabilities, rerender) : null),
    reusableUploadPanel(site, rerender),
    reusableSchedulesSection(site),
    h("section", { class: "card" }, h("h2", {}, "Timeline"), timeline),
    h("section", { class: "card" },
      h("h2", {}, "Jobs"),
      h("div", { class: "filters" },
        h("label", {}, changedOnly, " changed only"),
        h("label", {}, "Status ", statusSelect)),
      jobs.length
        ? h("table", { class: "table", id: "jobs-table" },
          h("thead", {}, h("tr", {}, ["Created", "Files", "Status", "Score", "Decision", "Regions", "Detector", "Error"].map((title) => h("th", {}, title)))),
          h("tbody", {}, rows))
        : h("p", { class: "muted", id: "no-jobs" }, filters.changed || filters.status ? "No job matches these filters." : "No comparison yet.")),
    scansCard);

  if (timelineJobs.some((job) => job.status === "queued" || job.status === "running")) {
    schedulePoll(() => refreshSite(siteId));
  }

  function rerender() {
    startRender();
    renderSite(siteId).catch((failure) => handleFailure(failure, "Loading the site"));
  }
}

async function refreshSite(siteId) {
  // Not under an open dialog (re-attaching a modal dialog would drop its modality); later.
  if (document.querySelector("dialog[open]")) {
    schedulePoll(() => refreshSite(siteId));
    return;
  }
  // Re-render in place, keeping the scroll position.
  const scroll = window.scrollY;
  try {
    await renderSite(siteId);
    window.scrollTo(0, scroll);
  } catch (failure) {
    handleFailure(failure, "Refreshing the site");
  }
}
