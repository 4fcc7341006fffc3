// A site's upload panel: a new reference or a scan to compare, with the upload's progress.

import { ApiError, describeError, uploadScan } from "./api.js";
import { loadCapabilities } from "./capabilities.js";
import { formatBytes, h, progressBar } from "./dom.js";
import { handleFailure } from "./session.js";

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
        : `${file.name}${points} uploaded; the comparison job is queued.`;
      status.classList.add("ok-text");
      if (reference) hint.hidden = true;
      fileInput.value = "";
      onDone(answer);
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
    hint, bar, status);
}

/** The site's upload panel; live refreshes keep the same one (chosen file, upload in flight, its message). */
export function reusableUploadPanel(site, onDone) {
  if (uploadCard.siteId !== site.id || !document.body.contains(uploadCard.node)) {
    uploadCard = { siteId: site.id, node: uploadPanel(site, onDone) };
  }
  return uploadCard.node;
}
