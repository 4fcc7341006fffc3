// Re-running a job on the same reference and scan with another detector or parameters
// (POST /jobs/{id}/rerun); the new job's page opens when it is queued.

import { ApiError, api, describeError } from "./api.js";
import { h } from "./dom.js";
import { detectorFields } from "./detector.js";
import { handleFailure } from "./session.js";

/** The re-run card of `job` (a writer's): a button that opens the detector form. */
export function rerunCard(job, capabilities) {
  const fields = detectorFields(capabilities, { method: job.method, variant: job.variant, params: job.params }, "rerun");
  const error = h("p", { class: "form-error", id: "rerun-error", role: "alert" });
  const submit = h("button", { type: "submit", class: "primary", id: "rerun-submit" }, "Queue the re-run");
  const form = h("form", { id: "rerun-form", class: "stacked-form", hidden: true },
    h("p", { class: "muted" }, `Compares ${job.scan_filename || "the scan"} with ${job.reference_filename || "the reference"} again, as a new job; this job is kept.`),
    fields.element, h("div", { class: "actions" }, submit), error);
  const open = h("button", { type: "button", id: "rerun-open" }, "Re-run with other settings…");
  open.addEventListener("click", () => {
    form.hidden = !form.hidden;
  });
  form.addEventListener("submit", async (event) => {
    event.preventDefault();
    error.textContent = "";
    let detector;
    try {
      detector = fields.read();
    } catch (failure) {
      error.textContent = `Not queued: ${failure.message}.`;
      return;
    }
    submit.disabled = true;
    try {
      const created = await api(`jobs/${job.id}/rerun`, { method: "POST", body: detector });
      location.hash = `#/jobs/${created.id}`;
    } catch (failure) {
      if (failure instanceof ApiError && failure.status === 401) return handleFailure(failure, "Re-running the job");
      error.textContent = `Not queued: ${describeError(failure)}`;
    } finally {
      submit.disabled = false;
    }
  });
  return h("section", { class: "card", id: "rerun-card" }, h("h2", {}, "Re-run"), open, form);
}
