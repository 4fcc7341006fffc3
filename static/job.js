// One comparison job: its numbers, its changed regions, the 3D view, view links and downloads.

import { API, ApiError, api, describeError } from "./api.js";
import { loadCapabilities } from "./capabilities.js";
import { decisionBadge, formatDate, formatNumber, h, jobProgress, statusBadge } from "./dom.js";
import { attemptsText, explanationPanel, sensorOriginsText, warningBadge, warningsPanel } from "./explain.js";
import { app, currentRender, schedulePoll, setCrumbs } from "./page.js";
import { evidenceBadge, metres, regionsPanel } from "./regions.js";
import { rerunCard } from "./rerun.js";
import { canWrite, handleFailure } from "./session.js";
import { jobFiles } from "./site.js";
import { reviewPanel } from "./verdicts.js";

function numbersTable(job) {
  const registration = job.registration || {};
  const timings = job.timings || {};
  const rows = [
    ["Scan", h("span", { id: "job-scan-file" }, job.scan_filename || "—")],
    ["Reference", h("span", { id: "job-reference-file" }, job.reference_filename || "—")],
    ["Status", [statusBadge(job), " ", jobProgress(job)]],
    ["Decision", [decisionBadge(job), " ", warningBadge(job)]],
    ["Score", formatNumber(job.score)],
    ["Threshold", formatNumber(job.threshold)],
    ["Regions", job.n_regions ?? "—"],
    ["Detector", `${job.method} · ${job.variant}`],
    ["Registration fitness", formatNumber(registration.fitness)],
    ["Registration RMSE", registration.rmse !== undefined ? `${formatNumber(registration.rmse)} m` : "—"],
    ["Sensor origins", sensorOriginsText(job)],
    ["Attempts", attemptsText(job)],
    ["Created", formatDate(job.created_at)],
    ["Started", formatDate(job.started_at)],
    ["Finished", formatDate(job.finished_at)],
  ];
  const timingText = Object.entries(timings).map(([stage, seconds]) => `${stage} ${formatNumber(seconds, 3)} s`).join(" · ");
  if (timingText) rows.push(["Timings", timingText]);
  return h("table", { class: "table facts-table", id: "job-numbers" },
    h("tbody", {}, rows.map(([name, value]) => h("tr", {}, h("th", {}, name), h("td", {}, value)))));
}

export async function renderJob(jobId) {
  const generation = currentRender();
  const job = await api(`jobs/${jobId}`);
  const rerunnable = canWrite() && (job.status === "succeeded" || job.status === "failed");
  const [site, capabilities] = await Promise.all([
    api(`sites/${job.site_id}`).catch(() => null),
    rerunnable ? loadCapabilities().catch(() => null) : Promise.resolve(null),
  ]);
  if (generation !== currentRender()) return;
  setCrumbs(h("a", { href: "#/" }, "Sites"),
    site ? h("a", { href: `#/sites/${site.id}` }, site.name) : h("span", {}, "site"),
    h("span", {}, job.scan_filename ? `job · ${job.scan_filename}` : `job ${jobId.slice(0, 8)}`));

  const finished = job.status === "succeeded";
  const linkOutput = h("div", { id: "view-link-output", class: "view-link" });
  const shareButton = h("button", { type: "button", id: "make-view-link", disabled: !finished }, "Make a view link");
  shareButton.addEventListener("click", async () => {
    try {
      const answer = await api(`jobs/${jobId}/view-link`, { method: "POST" });
      const field = h("input", { type: "text", readonly: true, value: answer.url, id: "view-link-url", size: 60 });
      const copy = h("button", { type: "button" }, "Copy");
      copy.addEventListener("click", async () => {
        field.select();
        try {
          await navigator.clipboard.writeText(answer.url);
          copy.textContent = "Copied";
        } catch {
          document.execCommand("copy");
          copy.textContent = "Copied";
        }
      });
      linkOutput.replaceChildren(field, copy,
        h("p", { class: "muted" }, `Anyone with this link can open this job's 3D view, without a token, until ${formatDate(answer.expires_at)}.`));
    } catch (failure) {
      if (failure instanceof ApiError && failure.status === 401) return handleFailure(failure, "Making a view link");
      linkOutput.replaceChildren(h("p", { class: "form-error" }, `No link: ${describeError(failure)}`));
    }
  });

  const downloads = finished
    ? h("ul", { class: "downloads", id: "downloads" },
      h("li", {}, h("a", { href: `${API}/jobs/${jobId}/labels?format=ply`, download: `labels-${jobId}.ply` }, "Labels as PLY")),
      h("li", {}, h("a", { href: `${API}/jobs/${jobId}/labels?format=las`, download: `labels-${jobId}.las` }, "Labels as LAS")),
      h("li", {}, h("a", { href: `${API}/jobs/${jobId}/labels?format=npz`, download: `labels-${jobId}.npz`, id: "download-labels-npz" }, "Labels as npz")),
      h("li", {}, h("a", { href: `${API}/jobs/${jobId}/regions?limit=1000`, download: `regions-${jobId}.json` }, "Regions as JSON (first 1000)")))
    : h("p", { class: "muted" }, "Downloads appear when the job has succeeded.");

  const failure = job.status === "failed"
    ? h("div", { class: "failure", id: "job-error", role: "alert" },
      h("strong", {}, "This job failed. "),
      job.error || "No reason was recorded.",
      h("p", { class: "muted", id: "job-retry" }, `${attemptsText(job)}.`))
    : null;

  const viewButton = finished
    ? h("a", { class: "button primary", href: `/jobs/${jobId}/view`, target: "_blank", rel: "noopener", id: "open-3d-view" }, "Open 3D view")
    : h("span", { class: "button disabled", title: "The 3D view opens when the job has succeeded" }, "Open 3D view");

  app.replaceChildren(
    h("section", { class: "card" },
      h("div", { class: "title-row" }, h("h1", {}, "Comparison job"), h("div", { class: "actions" }, viewButton, shareButton)),
      h("p", { class: "job-files", id: "job-files" }, jobFiles(job)),
      linkOutput,
      failure,
      explanationPanel(job),
      warningsPanel(job),
      numbersTable(job)),
    reviewPanel(job, () => renderJob(jobId).catch((failure) => handleFailure(failure, "Refreshing the job"))),
    h("section", { class: "card", id: "regions-card" }, h("h2", {}, `Regions (${finished ? job.n_regions ?? "—" : "—"})`),
      finished ? regionsPanel(jobId, job.n_regions, (failure) => handleFailure(failure, "Reading the regions")) : h("p", { class: "muted" }, "Regions appear when the job has succeeded.")),
    uncertainRegionsCard(job),
    h("section", { class: "card" }, h("h2", {}, "Downloads"), downloads),
    capabilities ? rerunCard(job, capabilities) : null);

  if (job.status === "queued" || job.status === "running") {
    schedulePoll(() => renderJob(jobId).catch((failure) => handleFailure(failure, "Refreshing the job")));
  }
}

/** Places the other scan did not cover: listed for review, never counted as change. */
function uncertainRegionsCard(job) {
  const regions = job.uncertain_regions || [];
  if (!regions.length) return null;
  const points = regions.reduce((sum, region) => sum + region.n_points, 0);
  return h("section", { class: "card", id: "uncertain-regions-card" },
    h("h2", {}, `Not covered by the other scan (${regions.length})`),
    h("p", { class: "muted" }, `${formatNumber(points)} points lie where the other scan has no view of them (a surface it did not reach, a place it never came near). They are listed for review and do not count as change.`),
    h("table", { class: "table", id: "uncertain-regions-table" },
      h("thead", {}, h("tr", {}, ["Side", "Points", "Centroid (m)", "Size (m)", "Evidence"].map((title) => h("th", {}, title)))),
      h("tbody", {}, regions.slice(0, 50).map((region) => h("tr", { dataset: { kind: region.kind } },
        h("td", {}, region.kind === "removed" ? "reference" : "scan"),
        h("td", { class: "num" }, formatNumber(region.n_points)),
        h("td", { class: "num" }, region.centroid.map(metres).join(", ")),
        h("td", { class: "num" }, region.bbox_max.map((value, axis) => metres(value - region.bbox_min[axis])).join(" × ")),
        h("td", {}, evidenceBadge(region)))))));
}
