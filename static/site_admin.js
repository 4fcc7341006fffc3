// A site's settings for writers: edit its name, description and detector, or delete it
// after a confirmation dialog. The card survives the site page's live refreshes.

import { ApiError, api, describeError } from "./api.js";
import { h } from "./dom.js";
import { detectorFields } from "./detector.js";
import { handleFailure } from "./session.js";

let adminCard = { key: null, node: null };

function deleteDialog(site) {
  const error = h("p", { class: "form-error", id: "delete-site-error", role: "alert" });
  const confirm = h("button", { type: "button", class: "danger", id: "confirm-delete-site" }, "Delete the site");
  const cancel = h("button", { type: "button", id: "cancel-delete-site" }, "Cancel");
  const dialog = h("dialog", { id: "delete-site-dialog", class: "dialog" },
    h("h2", {}, `Delete ${site.name}?`),
    h("p", {}, "This deletes the site with all its scans, comparison jobs, regions and result files. It cannot be undone."),
    h("p", { class: "muted" }, "Queued jobs are deleted too; while a job of the site is running, the deletion is refused."),
    h("div", { class: "actions" }, confirm, cancel),
    error);
  cancel.addEventListener("click", () => dialog.close());
  confirm.addEventListener("click", async () => {
    error.textContent = "";
    confirm.disabled = true;
    try {
      await api(`sites/${site.id}`, { method: "DELETE" });
      dialog.close();
      dialog.remove();
      location.hash = "#/";
    } catch (failure) {
      if (failure instanceof ApiError && failure.status === 401) return handleFailure(failure, "Deleting the site");
      error.textContent = `Not deleted: ${describeError(failure)}`;
    } finally {
      confirm.disabled = false;
    }
  });
  return dialog;
}

function siteAdminPanel(site, capabilities, onSaved) {
  const nameInput = h("input", { id: "edit-site-name", name: "name", required: true, maxlength: 200, value: site.name });
  const descriptionInput = h("input", { id: "edit-site-description", name: "description", maxlength: 2000, value: site.description || "", size: 40 });
  const fields = detectorFields(capabilities, site.detector, "edit-site");
  const error = h("p", { class: "form-error", id: "edit-site-error", role: "alert" });
  const form = h("form", { id: "edit-site-form", class: "stacked-form", hidden: true },
    h("div", { class: "inline-form" },
      h("label", { for: "edit-site-name" }, "Name"), nameInput,
      h("label", { for: "edit-site-description" }, "Description"), descriptionInput),
    fields.element,
    h("p", { class: "muted" }, "A new detector applies to the next comparisons; finished jobs keep theirs (re-run them from a job's page)."),
    h("div", { class: "actions" }, h("button", { type: "submit", class: "primary", id: "save-site" }, "Save"),
      h("button", { type: "button", id: "cancel-edit-site", onclick: () => { form.hidden = true; } }, "Cancel")),
    error);
  form.addEventListener("submit", async (event) => {
    event.preventDefault();
    error.textContent = "";
    let detector;
    try {
      detector = fields.read();
    } catch (failure) {
      error.textContent = `Not saved: ${failure.message}.`;
      return;
    }
    const body = { name: nameInput.value.trim(), description: descriptionInput.value.trim() || null, detector };
    try {
      const saved = await api(`sites/${site.id}`, { method: "PATCH", body });
      form.hidden = true;
      onSaved(saved);
    } catch (failure) {
      if (failure instanceof ApiError && failure.status === 401) return handleFailure(failure, "Saving the site");
      error.textContent = `Not saved: ${describeError(failure)}`;
    }
  });
  const dialog = deleteDialog(site);
  const editButton = h("button", { type: "button", id: "edit-site" }, "Edit site");
  editButton.addEventListener("click", () => { form.hidden = !form.hidden; });
  const deleteButton = h("button", { type: "button", class: "danger", id: "delete-site" }, "Delete site…");
  deleteButton.addEventListener("click", () => dialog.showModal());
  return h("div", { class: "site-admin", id: "site-admin" },
    h("div", { class: "actions" }, editButton, deleteButton),
    form, dialog);
}

/** The site's edit and delete tools (for its header card); live refreshes keep the same one until the site changes. */
export function reusableSiteAdminPanel(site, capabilities, onSaved) {
  const key = `${site.id}:${site.updated_at}`;
  if (adminCard.key !== key || !document.body.contains(adminCard.node)) {
    adminCard = { key, node: siteAdminPanel(site, capabilities, onSaved) };
  }
  return adminCard.node;
}
