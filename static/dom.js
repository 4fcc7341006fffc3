// Element building and formatting for the dashboard: every text goes in as a text node, never as HTML.

/** Build an element: h("a", {href: "#"}, "text", child, ...). Text is never parsed as HTML. */
export function h(tag, attributes = {}, ...children) {
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

export function formatDate(value) {
  if (!value) return "—";
  const date = new Date(value);
  return Number.isNaN(date.getTime()) ? String(value) : date.toLocaleString();
}

export function formatNumber(value, digits = 4) {
  if (value === null || value === undefined || Number.isNaN(value)) return "—";
  if (typeof value !== "number") return String(value);
  if (Number.isInteger(value)) return value.toLocaleString();
  const magnitude = Math.abs(value);
  if (magnitude !== 0 && (magnitude >= 1e5 || magnitude < 1e-3)) return value.toExponential(2);
  return String(Number(value.toPrecision(digits)));
}

export function formatBytes(bytes) {
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

export function formatVector(values) {
  return Array.isArray(values) ? values.map((v) => formatNumber(v, 5)).join(", ") : "—";
}

export function statusBadge(job) {
  const classes = { succeeded: "ok", failed: "bad", running: "busy", queued: "wait" };
  return h("span", { class: `badge badge-${classes[job.status] || "wait"}`, dataset: { status: job.status } }, job.status);
}

export function decisionBadge(job) {
  if (job.status !== "succeeded" || job.changed === null || job.changed === undefined) return h("span", { class: "muted" }, "—");
  return job.changed
    ? h("span", { class: "badge badge-changed", dataset: { decision: "changed" } }, "changed")
    : h("span", { class: "badge badge-same", dataset: { decision: "unchanged" } }, "no change");
}

export function progressBar(fraction, label) {
  const percent = Math.round(Math.max(0, Math.min(1, fraction || 0)) * 100);
  return h("div", { class: "progress", role: "progressbar", "aria-valuemin": 0, "aria-valuemax": 100, "aria-valuenow": percent, title: label || `${percent}%` },
    h("div", { class: "progress-fill", style: `width:${percent}%` }),
    h("span", { class: "progress-text" }, label || `${percent}%`));
}

export function jobProgress(job) {
  if (job.status === "running" || job.status === "queued") {
    const stage = job.stage ? ` · ${job.stage}` : "";
    // a job localised tile by tile on several workers says how many tiles are done
    const tiles = job.tiles ? ` · tiles ${job.tiles.done}/${job.tiles.total}` : "";
    return progressBar(job.progress, `${Math.round((job.progress || 0) * 100)}%${stage}${tiles}`);
  }
  return null;
}
