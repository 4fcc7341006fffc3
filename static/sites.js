// The sites list: each site's reference, last scan and decision, and the form for a new site.

import { ApiError, api, describeError, itemsOf } from "./api.js";
import { loadCapabilities } from "./capabilities.js";
import { detectorFields } from "./detector.js";
import { decisionBadge, formatDate, formatNumber, h, jobProgress, statusBadge } from "./dom.js";
import { app, currentRender, schedulePoll, setCrumbs } from "./page.js";
import { canWrite, handleFailure } from "./session.js";

async function siteSummary(site) {
  const [jobs, reference] = await Promise.all([
    api(`sites/${site.id}/jobs?limit=1`).then(itemsOf).catch(() => []),
    site.reference_scan_id ? api(`scans/${site.reference_scan_id}`).catch(() => null) : Promise.resolve(null),
  ]);
  return { site, last: jobs[0] || null, reference };
}

export async function renderSites() {
  const generation = currentRender();
  setCrumbs(h("span", {}, "Sites"));
  const sites = itemsOf(await api("sites"));
  const writable = canWrite();
  const [summaries, capabilities] = await Promise.all([
    Promise.all(sites.map(siteSummary)),
    writable ? loadCapabilities() : Promise.resolve(null),
  ]);
  if (generation !== currentRender()) return;

  const rows = summaries.map(({ site, last, reference }) => h("tr", { dataset: { siteId: site.id } },
    h("td", {}, h("a", { href: `#/sites/${site.id}`, class: "site-link" }, site.name)),
    h("td", {}, reference ? `${reference.filename} · ${formatDate(reference.created_at)}` : h("span", { class: "muted" }, "no reference yet")),
    h("td", {}, last ? `${last.scan_filename || "?"} · ${formatDate(last.created_at)}` : h("span", { class: "muted" }, "no scan yet")),
    h("td", { class: "num" }, last ? formatNumber(last.score) : "—"),
    h("td", {}, last ? decisionBadge(last) : "—"),
    h("td", {}, last ? [statusBadge(last), " ", jobProgress(last)] : "—")));

  const nameInput = h("input", { id: "new-site-name", name: "name", required: true, maxlength: 200, placeholder: "e.g. Warehouse 3, aisle B" });
  const descriptionInput = h("input", { id: "new-site-description", name: "description", maxlength: 2000, placeholder: "optional" });
  const formError = h("p", { class: "form-error", role: "alert", id: "new-site-error" });
  const detector = capabilities ? detectorFields(capabilities, null, "new-site") : null;
  const form = h("form", { id: "new-site-form", class: "stacked-form" },
    h("div", { class: "inline-form" },
      h("label", { for: "new-site-name" }, "Name"), nameInput,
      h("label", { for: "new-site-description" }, "Description"), descriptionInput),
    detector ? detector.element : null,
    h("div", { class: "actions" }, h("button", { type: "submit", class: "primary", id: "create-site" }, "Create site")), formError);
  form.addEventListener("submit", async (event) => {
    event.preventDefault();
    formError.textContent = "";
    try {
      const body = { name: nameInput.value.trim() };
      if (descriptionInput.value.trim()) body.description = descriptionInput.value.trim();
      if (detector) {
        try {
          body.detector = detector.read();
        } catch (failure) {
          formError.textContent = `The site was not created: ${failure.message}.`;
          return;
        }
      }
      const site = await api("sites", { method: "POST", body });
      location.hash = `#/sites/${site.id}`;
    } catch (failure) {
      if (failure instanceof ApiError && failure.status === 401) return handleFailure(failure, "Creating the site");
      formError.textContent = `The site was not created: ${describeError(failure)}`;
    }
  });

  app.replaceChildren(
    h("section", { class: "card" },
      h("h1", {}, "Sites"),
      sites.length
        ? h("table", { class: "table", id: "sites-table" },
          h("thead", {}, h("tr", {}, ["Site", "Reference", "Last scan", "Last score", "Decision", "Last job"].map((title) => h("th", {}, title)))),
          h("tbody", {}, rows))
        : h("p", { class: "muted", id: "no-sites" }, "No site yet. Create one below, then upload its reference scan.")),
    writable ? h("section", { class: "card" }, h("h2", {}, "New site"), form) : null);

  if (summaries.some(({ last }) => last && (last.status === "queued" || last.status === "running"))) {
    schedulePoll(() => renderSites().catch((failure) => handleFailure(failure, "Refreshing the sites")));
  }
}
