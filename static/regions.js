// A job's region table: sortable columns, filters by kind and minimum points, 25 per page.
// The API filters, sorts and pages (a job can have thousands of regions) like its other lists,
// `{items, next_cursor}`; X-Total-Count gives the number of matches. Lengths are in metres with 2 decimals (centimetres).

import { API, ApiError, describeError, itemsOf } from "./api.js";
import { formatNumber, h } from "./dom.js";

export const REGIONS_PER_PAGE = 25;
const KINDS = ["added", "removed"];
const COLUMNS = [
  { title: "#", sort: "ordinal" },
  { title: "Kind", sort: "kind" },
  { title: "Points", sort: "n_points" },
  { title: "Centroid (m)" },
  { title: "Size (m)" },
  { title: "Mean distance (m)", sort: "mean_distance" },
  { title: "Max distance (m)", sort: "max_distance" },
  { title: "Evidence" },
];

const EVIDENCE_TEXT = {
  seen_empty: "seen empty",
  surface_moved: "surface moved",
  no_coverage: "not covered",
};
const EVIDENCE_HINT = {
  seen_empty: "the other scan saw this place empty: through, behind or beneath it",
  surface_moved: "the surface is found again, displaced, within a metre",
  no_coverage: "the other scan did not cover this place: not counted as change",
};

/** A region's evidence and confidence, as a badge with its meaning on hover. */
export function evidenceBadge(region) {
  const evidence = region.evidence || "seen_empty";
  const confidence = Number.isFinite(region.confidence) ? ` ${Math.round(region.confidence * 100)} %` : "";
  return h("span", { class: `badge badge-evidence badge-${evidence}`, title: EVIDENCE_HINT[evidence] || evidence },
    (EVIDENCE_TEXT[evidence] || evidence) + confidence);
}

/** Metres with centimetre precision. */
export function metres(value) {
  return Number.isFinite(value) ? value.toFixed(2) : "—";
}

async function fetchRegions(jobId, state) {
  const query = new URLSearchParams({ sort: state.sort, order: state.order, limit: String(REGIONS_PER_PAGE) });
  const cursor = state.cursors[state.page];
  if (cursor) query.set("cursor", cursor);
  if (state.kind) query.set("kind", state.kind);
  if (state.minPoints > 0) query.set("min_points", String(state.minPoints));
  const response = await fetch(`${API}/jobs/${encodeURIComponent(jobId)}/regions?${query}`,
    { credentials: "same-origin", headers: { Accept: "application/json" } });
  const payload = await response.json().catch(() => null);
  if (!response.ok) throw new ApiError(response.status, payload && payload.error, payload && payload.detail);
  const regions = itemsOf(payload);
  return { regions, nextCursor: payload.next_cursor || null, total: Number(response.headers.get("X-Total-Count") || regions.length) };
}

function regionRow(region) {
  const size = region.bbox_min && region.bbox_max ? region.bbox_max.map((value, axis) => value - region.bbox_min[axis]) : null;
  return h("tr", { dataset: { kind: region.kind, regionId: region.id, points: region.n_points } },
    h("td", { class: "num" }, String(region.ordinal + 1)),
    h("td", {}, h("span", { class: `badge badge-${region.kind}` }, region.kind)),
    h("td", { class: "num" }, formatNumber(region.n_points)),
    h("td", { class: "num" }, Array.isArray(region.centroid) ? region.centroid.map(metres).join(", ") : "—"),
    h("td", { class: "num" }, size ? size.map(metres).join(" × ") : "—"),
    h("td", { class: "num" }, metres(region.mean_distance)),
    h("td", { class: "num" }, metres(region.max_distance)),
    h("td", {}, evidenceBadge(region)));
}

/** The region card's body for job `jobId` with `count` regions; fetches its pages itself. */
export function regionsPanel(jobId, count, onUnauthorised) {
  // cursors[i]: the cursor of page i (null for the first), so "Previous" goes back a page
  const state = { sort: "ordinal", order: "asc", kind: "", minPoints: 0, page: 0, cursors: [null] };
  const firstPage = () => { state.page = 0; state.cursors = [null]; };
  const kindSelect = h("select", { id: "regions-kind" },
    h("option", { value: "" }, "any kind"), KINDS.map((kind) => h("option", { value: kind }, kind)));
  const minPointsInput = h("input", { type: "number", id: "regions-min-points", min: 0, step: 1, value: 0, size: 7 });
  const summary = h("span", { id: "regions-summary", class: "muted" });
  const previous = h("button", { type: "button", id: "regions-previous" }, "‹ Previous");
  const next = h("button", { type: "button", id: "regions-next" }, "Next ›");
  const error = h("p", { class: "form-error", id: "regions-error", role: "alert" });
  const headerRow = h("tr", {});
  const body = h("tbody", {});
  const table = h("table", { class: "table", id: "regions-table" }, h("thead", {}, headerRow), body);
  let request = 0;

  function drawHeader() {
    headerRow.replaceChildren(...COLUMNS.map((column) => {
      if (!column.sort) return h("th", {}, column.title);
      const active = state.sort === column.sort;
      const arrow = active ? (state.order === "asc" ? " ▲" : " ▼") : "";
      const button = h("button", { type: "button", class: "sort-button", dataset: { sort: column.sort } }, column.title + arrow);
      button.addEventListener("click", () => {
        if (active) state.order = state.order === "asc" ? "desc" : "asc";
        else Object.assign(state, { sort: column.sort, order: column.sort === "ordinal" || column.sort === "kind" ? "asc" : "desc" });
        firstPage();
        load();
      });
      return h("th", { "aria-sort": active ? (state.order === "asc" ? "ascending" : "descending") : "none" }, button);
    }));
  }

  async function load() {
    const mine = ++request;
    drawHeader();
    error.textContent = "";
    try {
      const { regions, nextCursor, total } = await fetchRegions(jobId, state);
      if (mine !== request) return;
      const pages = Math.max(1, Math.ceil(total / REGIONS_PER_PAGE));
      state.cursors[state.page + 1] = nextCursor;
      body.replaceChildren(...regions.map(regionRow));
      const first = total ? state.page * REGIONS_PER_PAGE + 1 : 0;
      summary.textContent = total
        ? `${first}–${first + regions.length - 1} of ${total} (page ${state.page + 1} of ${pages})`
        : "No region matches these filters.";
      previous.disabled = state.page === 0;
      next.disabled = !nextCursor;
    } catch (failure) {
      if (failure instanceof ApiError && failure.status === 401) return onUnauthorised(failure);
      error.textContent = `The regions could not be read: ${describeError(failure)}`;
    }
  }

  kindSelect.addEventListener("change", () => { state.kind = kindSelect.value; firstPage(); load(); });
  minPointsInput.addEventListener("change", () => {
    const value = Number.parseInt(minPointsInput.value, 10);
    state.minPoints = Number.isFinite(value) && value > 0 ? value : 0;
    minPointsInput.value = String(state.minPoints);
    firstPage();
    load();
  });
  previous.addEventListener("click", () => { state.page = Math.max(0, state.page - 1); load(); });
  next.addEventListener("click", () => { if (state.cursors[state.page + 1]) { state.page += 1; load(); } });

  if (count === 0) return h("p", { class: "muted", id: "no-regions" }, "No changed region.");
  load();
  return h("div", { id: "regions-panel" },
    h("div", { class: "filters" },
      h("label", {}, "Kind ", kindSelect),
      h("label", {}, "Min. points ", minPointsInput),
      summary),
    table,
    h("div", { class: "pager" }, previous, next),
    error);
}
