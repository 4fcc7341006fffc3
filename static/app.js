// scandiff dashboard: sign in, sites, per-site timelines and jobs, job results, 3D view links.
// Plain ES modules, no framework and nothing from a CDN. Every request goes to this service
// with the HttpOnly session cookie (the page never holds the token after signing in).

import { drawTimeline } from "./timeline.js";

const API = "/api/v1";
const POLL_MS = 1500;
const JOBS_PAGE = 100;
const TIMELINE_MAX_JOBS = 300;

const app = document.getElementById("app");
const banner = document.getElementById("banner");
const crumbs = document.getElementById("crumbs");
let pollTimer = null;
let renderGeneration = 0;
let me = null;

// -- small helpers ---------------------------------------------------------------------------

/** Build an element: h("a", {href: "#"}, "text", child, ...). Text is never parsed as HTML. */
function h(tag, attributes = {}, ...children) {
  const element = document.createElement(tag);
  for (const [name, value] of Object.entries(attributes || {})) {
    if (value === null || value === undefined || value === false) continue;
    if (name.startsWith("on") && typeof value === "function") element.addEventListener(name.slice(2), value);
    else if (name === "dataset") Object.assign(element.dataset, value);
    else if (value === true) element.setAttribute(name, "");
    else element.setAttribute(name, String(value));
  }
  for (const child of children.flat()) {
    if (child === null || child === undefined || child === false) continue;
    element.append(child instanceof Node ? child : document.createTextNode(String(child)));
  }
  return element;
}

function formatDate(value) {
  if (!value) return "—";
  const date = new Date(value);
  return Number.isNaN(date.getTime()) ? String(value) : date.toLocaleString();
}

function formatNumber(value, digits = 4) {
  if (value === null || value === undefined || Number.isNaN(value)) return "—";
  if (typeof value !== "number") return String(value);
  if (Number.isInteger(value)) return value.toLocaleString();
  const magnitude = Math.abs(value);
  if (magnitude !== 0 && (magnitude >= 1e5 || magnitude < 1e-3)) return value.toExponential(2);
  return String(Number(value.toPrecision(digits)));
}

function formatBytes(bytes) {
  if (!Number.isFinite(bytes)) return "—";
  const units = ["B", "KB", "MB", "GB"];
  let value = bytes;
  let unit = 0;
  while (value >= 1024 && unit < units.length - 1) {
    value /= 1024;
    unit += 1;
  }
  return `${value.toFixed(unit ? 1 : 0)} ${units[unit]}`;
}

function formatVector(values) {
  return Array.isArray(values) ? values.map((v) => formatNumber(v, 5)).join(", ") : "—";
}

function itemsOf(payload) {
  if (Array.isArray(payload)) return payload;
  return payload && Array.isArray(payload.items) ? payload.items : [];
}

function statusBadge(job) {
  const classes = { succeeded: "ok", failed: "bad", running: "busy", queued: "wait" };
  return h("span", { class: `badge badge-${classes[job.status] || "wait"}`, dataset: { status: job.status } }, job.status);
}

function decisionBadge(job) {
  if (job.status !== "succeeded" || job.changed === null || job.changed === undefined) return h("span", { class: "muted" }, "—");
  return job.changed
    ? h("span", { class: "badge badge-changed", dataset: { decision: "changed" } }, "changed")
    : h("span", { class: "badge badge-same", dataset: { decision: "unchanged" } }, "no change");
}

function progressBar(fraction, label) {
  const percent = Math.round(Math.max(0, Math.min(1, fraction || 0)) * 100);
  return h("div", { class: "progress", role: "progressbar", "aria-valuemin": 0, "aria-valuemax": 100, "aria-valuenow": percent, title: label || `${percent}%` },
    h("div", { class: "progress-fill", style: `width:${percent}%` }),
    h("span", { class: "progress-text" }, label || `${percent}%`));
}

function jobProgress(job) {
  if (job.status === "running" || job.status === "queued") {
    const stage = job.stage ? ` · ${job.stage}` : "";
    return progressBar(job.progress, `${Math.round((job.progress || 0) * 100)}%${stage}`);
  }
  return null;
}

function showBanner(message, kind = "error") {
  if (!message) {
    banner.hidden = true;
    banner.textContent = "";
    return;
  }
  banner.className = `banner banner-${kind}`;
  banner.textContent = message;
  banner.hidden = false;
}

function setCrumbs(...parts) {
  crumbs.replaceChildren(...parts.flatMap((part, index) => (index ? [h("span", { class: "crumb-sep" }, "›"), part] : [part])));
}

function stopPolling() {
  if (pollTimer !== null) clearTimeout(pollTimer);
  pollTimer = null;
}

function schedulePoll(callback) {
  stopPolling();
  const generation = renderGeneration;
  pollTimer = setTimeout(() => {
    if (generation === renderGeneration) callback();
  }, POLL_MS);
}

// -- API ---------------------------------------------------------------------------------------

class ApiError extends Error {
  constructor(status, code, detail) {
    super(detail || code || `HTTP ${status}`);
    this.status = status;
    this.code = code;
    this.detail = detail;
  }
}

function describeError(error) {
  if (!(error instanceof ApiError)) return `The service could not be reached (${error.message}). Is it running?`;
  if (error.status === 401) return "Your session has ended: the token was revoked or the session expired. Sign in again.";
  if (error.status === 403) return `Not allowed: ${error.detail || "this token's role cannot do this."}`;
  if (error.status === 404) return `Not found: ${error.detail || "it does not exist or belongs to another organisation."}`;
  if (error.status === 413) return `The file is too large for this service: ${error.detail || ""}`;
  if (error.status === 415) return `Unknown file format: ${error.detail || ""}`;
  return error.detail || error.message;
}

async function api(path, { method = "GET", body, headers = {} } = {}) {
  const options = { method, credentials: "same-origin", headers: { Accept: "application/json", ...headers } };
  if (body !== undefined) {
    options.body = JSON.stringify(body);
    options.headers["Content-Type"] = "application/json";
  }
  let response;
  try {
    response = await fetch(path.startsWith("/") ? path : `${API}/${path}`, options);
  } catch (error) {
    throw new Error(error.message || "network error");
  }
  const text = await response.text();
  let payload = null;
  if (text) {
    try {
      payload = JSON.parse(text);
    } catch {
      payload = { detail: text.slice(0, 300) };
    }
  }
  if (!response.ok) {
    let detail = payload && payload.detail;
    if (Array.isArray(detail)) detail = detail.map((item) => item.msg || JSON.stringify(item)).join("; ");
    throw new ApiError(response.status, payload && payload.error, detail);
  }
  return payload;
}

/** Upload `file` as the raw body with progress; resolves with the JSON answer. */
function uploadScan(siteId, file, reference, onProgress, sensorOrigin = "") {
  return new Promise((resolve, reject) => {
    const query = new URLSearchParams({ reference: String(reference), filename: file.name });
    if (sensorOrigin) query.set("sensor_origin", sensorOrigin);
    const request = new XMLHttpRequest();
    request.open("POST", `${API}/sites/${encodeURIComponent(siteId)}/scans?${query}`);
    request.withCredentials = true;
    request.setRequestHeader("Content-Type", "application/octet-stream");
    request.setRequestHeader("Accept", "application/json");
    request.setRequestHeader("Idempotency-Key", `${siteId}-${file.name}-${file.size}-${file.lastModified}-${reference}-${Date.now()}`);
    request.upload.onprogress = (event) => {
      if (event.lengthComputable) onProgress(event.loaded / event.total);
    };
    request.onload = () => {
      let payload = null;
      try {
        payload = request.responseText ? JSON.parse(request.responseText) : null;
      } catch {
        payload = { detail: request.responseText.slice(0, 300) };
      }
      if (request.status >= 200 && request.status < 300) resolve(payload);
      else reject(new ApiError(request.status, payload && payload.error, payload && payload.detail));
    };
    request.onerror = () => reject(new Error("the upload was interrupted"));
    request.send(file);
  });
}

async function handleFailure(error, where) {
  if (error instanceof ApiError && error.status === 401) {
    me = null;
    renderSignIn(describeError(error));
    return;
  }
  showBanner(`${where}: ${describeError(error)}`);
}

// -- sign in / out -------------------------------------------------------------------------------

function renderWho() {
  const who = document.getElementById("who");
  if (!me) {
    who.hidden = true;
    return;
  }
  document.getElementById("who-text").textContent = `${me.organisation || me.organisation_id} · ${me.role}`;
  who.hidden = false;
}

function renderSignIn(message = "") {
  renderGeneration += 1;
  stopPolling();
  renderWho();
  setCrumbs();
  showBanner(message ? message : "", "error");
  const error = h("p", { class: "form-error", id: "sign-in-error", role: "alert" });
  const input = h("input", { id: "token", name: "token", type: "password", autocomplete: "off", required: true, placeholder: "sdt_…", size: 48 });
  const form = h("form", { id: "sign-in-form", class: "card sign-in" },
    h("h1", {}, "Sign in"),
    h("p", { class: "muted" }, "Paste an API token: the one ", h("code", {}, "make run"), " printed, or one from ",
      h("code", {}, "scandiff token create"), ". The page trades it for a session cookie and forgets it."),
    h("label", { for: "token" }, "Token"),
    input,
    h("div", { class: "actions" }, h("button", { type: "submit", id: "sign-in-button", class: "primary" }, "Sign in")),
    error);
  form.addEventListener("submit", async (event) => {
    event.preventDefault();
    error.textContent = "";
    const token = input.value.trim();
    if (!token) {
      error.textContent = "Enter a token.";
      return;
    }
    try {
      me = await api("session", { method: "POST", body: { token } });
      input.value = "";
      showBanner("");
      renderWho();
      route();
    } catch (failure) {
      error.textContent = failure instanceof ApiError && failure.status === 401
        ? "This token is not valid: it is unknown, or it was revoked. Check for a missing character."
        : describeError(failure);
    }
  });
  app.replaceChildren(form);
  input.focus();
}

document.getElementById("sign-out").addEventListener("click", async () => {
  try {
    await api("session", { method: "DELETE" });
  } catch {
    // Signing out locally is enough if the server is gone.
  }
  me = null;
  location.hash = "#/";
  renderSignIn("You are signed out.");
  showBanner("You are signed out.", "info");
});

// -- sites ---------------------------------------------------------------------------------------

async function siteSummary(site) {
  const [jobs, reference] = await Promise.all([
    api(`sites/${site.id}/jobs?limit=1`).then(itemsOf).catch(() => []),
    site.reference_scan_id ? api(`scans/${site.reference_scan_id}`).catch(() => null) : Promise.resolve(null),
  ]);
  return { site, last: jobs[0] || null, reference };
}

async function renderSites() {
  const generation = renderGeneration;
  setCrumbs(h("span", {}, "Sites"));
  const sites = itemsOf(await api("sites"));
  const summaries = await Promise.all(sites.map(siteSummary));
  if (generation !== renderGeneration) return;

  const rows = summaries.map(({ site, last, reference }) => h("tr", { dataset: { siteId: site.id } },
    h("td", {}, h("a", { href: `#/sites/${site.id}`, class: "site-link" }, site.name)),
    h("td", {}, reference ? formatDate(reference.created_at) : h("span", { class: "muted" }, "no reference yet")),
    h("td", {}, last ? formatDate(last.created_at) : h("span", { class: "muted" }, "no scan yet")),
    h("td", { class: "num" }, last ? formatNumber(last.score) : "—"),
    h("td", {}, last ? decisionBadge(last) : "—"),
    h("td", {}, last ? [statusBadge(last), " ", jobProgress(last)] : "—")));

  const nameInput = h("input", { id: "new-site-name", name: "name", required: true, maxlength: 200, placeholder: "e.g. Warehouse 3, aisle B" });
  const descriptionInput = h("input", { id: "new-site-description", name: "description", maxlength: 2000, placeholder: "optional" });
  const formError = h("p", { class: "form-error", role: "alert" });
  const form = h("form", { id: "new-site-form", class: "inline-form" },
    h("label", { for: "new-site-name" }, "Name"), nameInput,
    h("label", { for: "new-site-description" }, "Description"), descriptionInput,
    h("button", { type: "submit", class: "primary", id: "create-site" }, "Create site"), formError);
  form.addEventListener("submit", async (event) => {
    event.preventDefault();
    formError.textContent = "";
    try {
      const body = { name: nameInput.value.trim() };
      if (descriptionInput.value.trim()) body.description = descriptionInput.value.trim();
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
          h("thead", {}, h("tr", {}, ["Site", "Reference from", "Last scan", "Last score", "Decision", "Last job"].map((title) => h("th", {}, title)))),
          h("tbody", {}, rows))
        : h("p", { class: "muted", id: "no-sites" }, "No site yet. Create one below, then upload its reference scan.")),
    h("section", { class: "card" }, h("h2", {}, "New site"), form));

  if (summaries.some(({ last }) => last && (last.status === "queued" || last.status === "running"))) {
    schedulePoll(() => renderSites().catch((failure) => handleFailure(failure, "Refreshing the sites")));
  }
}

// -- one site --------------------------------------------------------------------------------------

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

const siteFilters = new Map();
let uploadCard = { siteId: null, node: null };

function uploadPanel(site, onDone) {
  const fileInput = h("input", { type: "file", id: "scan-file", name: "file", accept: ".ply,.pcd,.las,.laz,.xyz,.csv,.txt,.npy,.npz,.e57" });
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
    h("p", { class: "muted" }, "PLY, PCD, LAS/LAZ, XYZ/CSV/TXT or NPY. A new reference replaces the current one (the history is kept); a scan is compared with the current reference."),
    h("div", { class: "upload-row" }, fileInput, originInput, referenceButton, scanButton),
    hint, bar, status);
}

async function renderSite(siteId) {
  const generation = renderGeneration;
  const filters = siteFilters.get(siteId) || { changed: false, status: "" };
  siteFilters.set(siteId, filters);
  const site = await api(`sites/${siteId}`);
  const [reference, jobs, allJobs] = await Promise.all([
    site.reference_scan_id ? api(`scans/${site.reference_scan_id}`).catch(() => null) : Promise.resolve(null),
    fetchSiteJobs(siteId, filters),
    filters.changed || filters.status ? fetchSiteJobs(siteId, { changed: false, status: "" }) : Promise.resolve(null),
  ]);
  if (generation !== renderGeneration) return;
  const timelineJobs = allJobs || jobs;
  setCrumbs(h("a", { href: "#/" }, "Sites"), h("span", {}, site.name));

  const timeline = h("div", { id: "timeline", class: "timeline" });
  drawTimeline(timeline, timelineJobs, (job) => { location.hash = `#/jobs/${job.id}`; });

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
    h("td", {}, statusBadge(job), " ", jobProgress(job)),
    h("td", { class: "num" }, formatNumber(job.score)),
    h("td", {}, decisionBadge(job)),
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
        h("dd", {}, site.detector ? `${site.detector.method} · ${site.detector.variant}` : "default"))),
    reusableUploadPanel(site, rerender),
    h("section", { class: "card" }, h("h2", {}, "Timeline"), timeline),
    h("section", { class: "card" },
      h("h2", {}, "Jobs"),
      h("div", { class: "filters" },
        h("label", {}, changedOnly, " changed only"),
        h("label", {}, "Status ", statusSelect)),
      jobs.length
        ? h("table", { class: "table", id: "jobs-table" },
          h("thead", {}, h("tr", {}, ["Created", "Status", "Score", "Decision", "Regions", "Detector", "Error"].map((title) => h("th", {}, title)))),
          h("tbody", {}, rows))
        : h("p", { class: "muted", id: "no-jobs" }, filters.changed || filters.status ? "No job matches these filters." : "No comparison yet.")));

  if (timelineJobs.some((job) => job.status === "queued" || job.status === "running")) {
    schedulePoll(() => refreshSite(siteId));
  }

  function rerender() {
    renderGeneration += 1;
    stopPolling();
    renderSite(siteId).catch((failure) => handleFailure(failure, "Loading the site"));
  }
}

function reusableUploadPanel(site, onDone) {
  // Live refreshes keep the same upload panel (chosen file, upload in flight, its message).
  if (uploadCard.siteId !== site.id || !document.body.contains(uploadCard.node)) {
    uploadCard = { siteId: site.id, node: uploadPanel(site, onDone) };
  }
  return uploadCard.node;
}

async function refreshSite(siteId) {
  // Re-render in place, keeping the scroll position.
  const scroll = window.scrollY;
  try {
    await renderSite(siteId);
    window.scrollTo(0, scroll);
  } catch (failure) {
    handleFailure(failure, "Refreshing the site");
  }
}

// -- one job ---------------------------------------------------------------------------------------

function numbersTable(job) {
  const registration = job.registration || {};
  const timings = job.timings || {};
  const rows = [
    ["Status", [statusBadge(job), " ", jobProgress(job)]],
    ["Decision", decisionBadge(job)],
    ["Score", formatNumber(job.score)],
    ["Threshold", formatNumber(job.threshold)],
    ["Regions", job.n_regions ?? "—"],
    ["Detector", `${job.method} · ${job.variant}`],
    ["Registration fitness", formatNumber(registration.fitness)],
    ["Registration RMSE", registration.rmse !== undefined ? `${formatNumber(registration.rmse)} m` : "—"],
    ["Attempts", `${job.attempts} of ${job.max_attempts ?? "?"}`],
    ["Created", formatDate(job.created_at)],
    ["Started", formatDate(job.started_at)],
    ["Finished", formatDate(job.finished_at)],
  ];
  const timingText = Object.entries(timings).map(([stage, seconds]) => `${stage} ${formatNumber(seconds, 3)} s`).join(" · ");
  if (timingText) rows.push(["Timings", timingText]);
  return h("table", { class: "table facts-table", id: "job-numbers" },
    h("tbody", {}, rows.map(([name, value]) => h("tr", {}, h("th", {}, name), h("td", {}, value)))));
}

function regionsTable(regions) {
  if (!regions.length) return h("p", { class: "muted", id: "no-regions" }, "No changed region.");
  return h("table", { class: "table", id: "regions-table" },
    h("thead", {}, h("tr", {}, ["#", "Kind", "Points", "Centroid (m)", "Size (m)", "Mean distance", "Max distance"].map((title) => h("th", {}, title)))),
    h("tbody", {}, regions.map((region, index) => {
      const size = region.bbox_min && region.bbox_max ? region.bbox_max.map((value, axis) => value - region.bbox_min[axis]) : null;
      return h("tr", { dataset: { kind: region.kind } },
        h("td", {}, String(index + 1)),
        h("td", {}, h("span", { class: `badge badge-${region.kind}` }, region.kind)),
        h("td", { class: "num" }, formatNumber(region.n_points)),
        h("td", {}, formatVector(region.centroid)),
        h("td", {}, size ? size.map((value) => formatNumber(value, 3)).join(" × ") : "—"),
        h("td", { class: "num" }, formatNumber(region.mean_distance)),
        h("td", { class: "num" }, formatNumber(region.max_distance)));
    })));
}

async function renderJob(jobId) {
  const generation = renderGeneration;
  const job = await api(`jobs/${jobId}`);
  const [site, regions] = await Promise.all([
    api(`sites/${job.site_id}`).catch(() => null),
    job.status === "succeeded" ? api(`jobs/${jobId}/regions`).then(itemsOf) : Promise.resolve([]),
  ]);
  if (generation !== renderGeneration) return;
  setCrumbs(h("a", { href: "#/" }, "Sites"),
    site ? h("a", { href: `#/sites/${site.id}` }, site.name) : h("span", {}, "site"),
    h("span", {}, `job ${jobId.slice(0, 8)}`));

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
      h("li", {}, h("a", { href: `${API}/jobs/${jobId}/regions`, download: `regions-${jobId}.json` }, "Regions as JSON")))
    : h("p", { class: "muted" }, "Downloads appear when the job has succeeded.");

  const failure = job.status === "failed"
    ? h("div", { class: "failure", id: "job-error", role: "alert" },
      h("strong", {}, "This job failed. "),
      job.error || "No reason was recorded.",
      h("p", { class: "muted" }, `Attempts: ${job.attempts} of ${job.max_attempts ?? "?"}.`))
    : null;

  const viewButton = finished
    ? h("a", { class: "button primary", href: `/jobs/${jobId}/view`, target: "_blank", rel: "noopener", id: "open-3d-view" }, "Open 3D view")
    : h("span", { class: "button disabled", title: "The 3D view opens when the job has succeeded" }, "Open 3D view");

  app.replaceChildren(
    h("section", { class: "card" },
      h("div", { class: "title-row" }, h("h1", {}, "Comparison job"), h("div", { class: "actions" }, viewButton, shareButton)),
      linkOutput,
      failure,
      numbersTable(job)),
    h("section", { class: "card" }, h("h2", {}, `Regions (${finished ? regions.length : "—"})`), finished ? regionsTable(regions) : h("p", { class: "muted" }, "Regions appear when the job has succeeded.")),
    h("section", { class: "card" }, h("h2", {}, "Downloads"), downloads));

  if (job.status === "queued" || job.status === "running") {
    schedulePoll(() => renderJob(jobId).catch((failure) => handleFailure(failure, "Refreshing the job")));
  }
}

// -- routing ---------------------------------------------------------------------------------------

async function route() {
  renderGeneration += 1;
  stopPolling();
  showBanner("");
  if (!me) {
    try {
      me = await api("session");
    } catch (failure) {
      if (failure instanceof ApiError && failure.status === 401) {
        renderSignIn(failure.code === "session_ended" ? `Please sign in again: ${failure.detail}.` : "");
        return;
      }
      showBanner(describeError(failure));
      return;
    }
  }
  renderWho();
  const hash = location.hash.replace(/^#/, "") || "/";
  const siteMatch = hash.match(/^\/sites\/([^/]+)$/);
  const jobMatch = hash.match(/^\/jobs\/([^/]+)$/);
  try {
    if (siteMatch) await renderSite(decodeURIComponent(siteMatch[1]));
    else if (jobMatch) await renderJob(decodeURIComponent(jobMatch[1]));
    else await renderSites();
  } catch (failure) {
    if (failure instanceof ApiError && failure.status === 404) {
      app.replaceChildren(h("section", { class: "card" }, h("h1", {}, "Not found"),
        h("p", {}, describeError(failure)), h("p", {}, h("a", { href: "#/" }, "Back to the sites"))));
      return;
    }
    await handleFailure(failure, "Loading this page");
  }
}

window.addEventListener("hashchange", route);
route();
