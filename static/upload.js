// A site's upload panel: a new reference or a scan to compare, with the upload's progress and
// then its comparison job's, followed to its end (queued → running → done or failed) by the long
// poll GET /api/v1/jobs/{id}?wait=, with a link to the job.

import { ApiError, api, describeError, uploadScan } from "./api.js";
import { loadCapabilities } from "./capabilities.js";
import { formatBytes, h, progressBar, statusBadge } from "./dom.js";
import { handleFailure } from "./session.js";

const JOB_WAIT_SECONDS = 10;
const JOB_ENDED = new Set(["succeeded", "failed"]);

function jobOutcome(job) {
  if (job.status === "failed") return `Comparison failed: ${job.error || "no reason was recorded"}.`;
  if (job.status === "succeeded") {
    const decision = job.changed ? `changed, ${job.n_regions ?? 0} ${job.n_regions === 1 ? "region" : "regions"}` : "no change";
    return `Comparison done: ${decision}.`;
  }
  const percent = Math.round((job.progress || 0) * 100);
  const tiles = job.tiles ? `, tiles ${job.tiles.done}/${job.tiles.total}` : "";
  return job.status === "running" ? `Comparison running${job.stage ? ` (${job.stage}, ${percent}%${tiles})` : ""}…` : "Comparison queued…";
}

/** Show `job` in `node` (a badge, where it is, a link to it) until it ends; then `onEnded()`. */
async function followJob(node, job, onEnded) {
  let current = job;
  node.dataset.jobId = job.id; // a later upload takes the line over
  for (;;) {
    if (node.dataset.jobId !== job.id) return;
    node.dataset.jobStatus = current.status;
    node.replaceChildren(statusBadge(current), " ", h("span", { class: "upload-job-text" }, jobOutcome(current)), " ",
      h("a", { href: `#/jobs/${current.id}`, id: "upload-job-link" }, "Open the job ›"));
    if (JOB_ENDED.has(current.status)) break;
    try {
      current = await api(`jobs/${current.id}?wait=${JOB_WAIT_SECONDS}`);
    } catch (failure) {
      if (failure instanceof ApiError && failure.status === 401) return handleFailure(failure, "Following the job");
      if (failure instanceof ApiError && failure.status === 404) return; // deleted with its site
      await new Promise((resolve) => { setTimeout(resolve, 2000); }); // the service is away: try again
    }
  }
  onEnded(current);
}

let uploadCard = { siteId: null, node: null };

function uploadPanel(site, onDone) {
  // The picker offers what the server reads (GET /capabilities), never a hard-coded list.
  const fileInput = h("input", { type: "file", id: "scan-file", name: "file" });
  const formats = h("p", { class: "muted", id: "upload-formats" }, "A new reference replaces the current one (the history is kept); a scan is compared with the current reference.");
  loadCapabilities().then((capabilities) => {
    fileInput.setAttribute("accept", capabilities.upload_extensions.join(","));
    formats.prepend(`Formats read: ${capabilities.upload_formats.join(", ")}. `);
  }).catch(() => {});
  const originInput = h("input", {
    type: "text", id: "sensor-origin", name: "sensor_origin", placeholder: "sensor x,y,z (optional)",
    title: "Where the lidar was, in the file's frame (0,0,0 for a scan in its sensor's frame): lets scandiff tell occluded parts from removed ones. PCD files may carry it as VIEWPOINT.",
  });
  const status = h("p", { class: "upload-status", id: "upload-status", role: "status" });
  const bar = h("div", { id: "upload-progress", class: "upload-progress", hidden: true });
  const jobLine = h("p", { id: "upload-job", class: "upload-job", role: "status", hidden: true });
  const referenceButton = h("button", { type: "button", id: "upload-reference" }, "Upload as reference");
  const scanButton = h("button", { type: "button", id: "upload-scan", class: "primary", disabled: !site.reference_scan_id },
    "Upload scan and compare");
  const buttons = [referenceButton, scanButton];
  const hint = h("p", { class: "hint", hidden: Boolean(site.reference_scan_id) }, "Upload a reference first: scans are compared with it.");

  async function send(reference) {
    const file = fileInput.files && fileInput.files[0];
    status.className = "upload-status";
    if (!file) {
      status.textContent = "Choose a scan file first.";
      return;
    }
    buttons.forEach((button) => { button.disabled = true; });
    bar.hidden = false;
    bar.replaceChildren(progressBar(0, `Uploading ${file.name} (${formatBytes(file.size)})…`));
    status.textContent = "";
    jobLine.hidden = true;
    try {
      const answer = await uploadScan(site.id, file, reference, (fraction) => {
        const label = fraction >= 1 ? "Checking the file…" : `Uploading ${file.name}: ${Math.round(fraction * 100)}%`;
        bar.replaceChildren(progressBar(fraction, label));
      }, originInput.value.trim());
      bar.replaceChildren(progressBar(1, "Uploaded"));
      const scan = answer && (answer.scan || answer);
      const points = scan && Number.isFinite(scan.n_points) ? ` (${scan.n_points.toLocaleString()} points)` : "";
      status.textContent = reference
        ? `${file.name}${points} is now the reference of this site.`
        : `${file.name}${points} uploaded.`;
      status.classList.add("ok-text");
      if (reference) hint.hidden = true;
      fileInput.value = "";
      onDone(answer);
      if (answer && answer.job) {
        jobLine.hidden = false;
        followJob(jobLine, answer.job, () => onDone(answer));
      }
    } catch (failure) {
      bar.hidden = true;
      if (failure instanceof ApiError && failure.status === 401) return handleFailure(failure, "Uploading");
      status.textContent = `The upload failed: ${describeError(failure)}`;
      status.classList.add("form-error");
    } finally {
      referenceButton.disabled = false;
      scanButton.disabled = false;
    }
  }
  referenceButton.addEventListener("click", () => send(true));
  scanButton.addEventListener("click", () => send(false));
  return h("section", { class: "card", id: "upload-card" },
    h("h2", {}, "Upload"),
    formats,
    h("div", { class: "upload-row" }, fileInput, originInput, referenceButton, scanButton),
    hint, bar, status, jobLine);
}

/** The site's upload panel; live refreshes keep the same one (chosen file, upload in flight, its message). */
export function reusableUploadPanel(site, onDone) {
  if (uploadCard.siteId !== site.id || !document.body.contains(uploadCard.node)) {
    uploadCard = { siteId: site.id, node: uploadPanel(site, onDone) };
  }
  return uploadCard.node;
}
