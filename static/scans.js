// A site's scans, newest first, with the one that is the reference marked; a writer can make
// an older scan the reference (the reference history keeps every change).

import { ApiError, api, describeError, itemsOf } from "./api.js";
import { formatBytes, formatDate, h } from "./dom.js";
import { handleFailure } from "./session.js";

const SCANS_PAGE = 50;

/** The scans card of `site`; `onChanged(site)` runs after the reference changed. */
export async function siteScansCard(site, writable, onChanged) {
  const page = await api(`sites/${site.id}/scans?limit=${SCANS_PAGE}`);
  const scans = itemsOf(page);
  const error = h("p", { class: "form-error", id: "scans-error", role: "alert" });

  function referenceCell(scan) {
    if (scan.id === site.reference_scan_id) return h("span", { class: "badge badge-ok", id: "current-reference" }, "reference");
    if (!writable) return "";
    const button = h("button", { type: "button", class: "make-reference", dataset: { scanId: scan.id } }, "Make reference");
    button.addEventListener("click", async () => {
      error.textContent = "";
      button.disabled = true;
      try {
        const updated = await api(`sites/${site.id}/reference`, { method: "POST", body: { scan_id: scan.id } });
        onChanged(updated);
      } catch (failure) {
        button.disabled = false;
        if (failure instanceof ApiError && failure.status === 401) return handleFailure(failure, "Changing the reference");
        error.textContent = `The reference was not changed: ${describeError(failure)}`;
      }
    });
    return button;
  }

  const rows = scans.map((scan) => h("tr", { dataset: { scanId: scan.id, reference: scan.id === site.reference_scan_id } },
    h("td", { class: "scan-filename" }, scan.filename),
    h("td", {}, formatDate(scan.created_at)),
    h("td", { class: "num" }, scan.n_points.toLocaleString()),
    h("td", { class: "num" }, formatBytes(scan.size_bytes)),
    h("td", {}, scan.format),
    h("td", {}, referenceCell(scan))));
  return h("section", { class: "card", id: "scans-card" },
    h("h2", {}, "Scans"),
    scans.length
      ? h("table", { class: "table", id: "scans-table" },
        h("thead", {}, h("tr", {}, ["File", "Uploaded", "Points", "Size", "Format", "Reference"].map((title) => h("th", {}, title)))),
        h("tbody", {}, rows))
      : h("p", { class: "muted", id: "no-scans" }, "No scan yet."),
    page && page.next_cursor ? h("p", { class: "muted" }, `Showing the ${SCANS_PAGE} newest scans.`) : null,
    h("p", { class: "muted" }, "New scans are compared with the reference; making an older scan the reference does not re-run earlier jobs."),
    error);
}
