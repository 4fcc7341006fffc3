// A site's timeline as SVG: what decides each job (its decisive statistic, e.g. the largest
// changed region in metres, against the threshold it was decided with: the default or the
// site's, learned from reviewed jobs) with the reviewers' verdicts on it; below, one small chart
// per detector with its global score and that detector's own threshold. Jobs that finished in
// the same instant (dots that would overlap) are spread side by side. Clicking a dot opens the job.

const SVG_NS = "http://www.w3.org/2000/svg";
const WIDTH = 800;
const MAIN_HEIGHT = 228;
const LEGEND_ROW = 18;
const DETECTOR_HEIGHT = 110;
const MARGIN = { top: 24, right: 16, bottom: 36, left: 56 };
const GROUP_PX = 12; // a changed job's dot diameter: closer dots would overlap
const JITTER_PX = 8;

const SECOND = 1000;
const MINUTE = 60 * SECOND;
const HOUR = 60 * MINUTE;
const DAY = 24 * HOUR;
const TIME_STEPS = [SECOND, 2 * SECOND, 5 * SECOND, 10 * SECOND, 15 * SECOND, 30 * SECOND, MINUTE,
  2 * MINUTE, 5 * MINUTE, 10 * MINUTE, 15 * MINUTE, 30 * MINUTE, HOUR, 2 * HOUR, 3 * HOUR, 6 * HOUR,
  12 * HOUR, DAY, 2 * DAY, 7 * DAY, 14 * DAY, 28 * DAY, 91 * DAY, 365 * DAY];

const STATISTICS = {
  largest_region_extent_m: { title: "Size of the largest region", unit: " m" },
  score: { title: "Detector score", unit: "" },
};
export const VERDICT_NAMES = { confirmed: "confirmed", false_alarm: "false alarm", new_reference: "new reference" };
const VERDICT_MARKS = { confirmed: "✓", false_alarm: "✗", new_reference: "R" };

function svg(tag, attributes = {}, text = null) {
  const element = document.createElementNS(SVG_NS, tag);
  for (const [name, value] of Object.entries(attributes)) element.setAttribute(name, String(value));
  if (text !== null) element.textContent = text;
  return element;
}

function niceTicks(low, high, count) {
  const span = high - low || 1;
  const step = 10 ** Math.floor(Math.log10(span / count));
  const multiple = [1, 2, 5, 10].find((m) => span / (step * m) <= count) || 10;
  const size = step * multiple;
  const ticks = [];
  for (let value = Math.ceil(low / size) * size; value <= high + size * 1e-9; value += size) {
    ticks.push(Number(value.toPrecision(12)));
  }
  return ticks;
}

function formatValue(value, unit = "") {
  if (!Number.isFinite(value)) return "—";
  if (value === 0) return `0${unit}`;
  const magnitude = Math.abs(value);
  const text = magnitude >= 1000 || magnitude < 0.01 ? value.toExponential(1) : String(Number(value.toPrecision(3)));
  return `${text}${unit}`;
}

/** The test that decided a job (calibration.decision.tests[0]), or null for older jobs. */
export function decisiveTest(job) {
  const tests = job.calibration && job.calibration.decision && job.calibration.decision.tests;
  return Array.isArray(tests) && tests.length ? tests[0] : null;
}

/** Ticks of a time axis from tMin to tMax (ms): a step from TIME_STEPS, aligned on local time. */
export function timeTicks(tMin, tMax, maxTicks = 6) {
  const span = Math.max(tMax - tMin, 1);
  const step = TIME_STEPS.find((candidate) => span / candidate <= maxTicks) || TIME_STEPS[TIME_STEPS.length - 1];
  const midnight = new Date(tMin);
  midnight.setHours(0, 0, 0, 0);
  const ticks = [];
  if (step < DAY) {
    const origin = midnight.getTime();
    for (let time = origin + Math.ceil((tMin - origin) / step) * step; time <= tMax; time += step) ticks.push(time);
  } else {
    const days = Math.round(step / DAY);
    if (midnight.getTime() < tMin) midnight.setDate(midnight.getDate() + 1);
    for (; midnight.getTime() <= tMax; midnight.setDate(midnight.getDate() + days)) ticks.push(midnight.getTime());
  }
  return { step, ticks };
}

/** Labels of those ticks: 24-hour times (seconds when the step needs them), and the date on a
 * second line at the first tick and wherever the day changes; dates only for steps of days. */
export function timeTickLabels(ticks, step) {
  if (!ticks.length) return [];
  const years = new Set(ticks.map((time) => new Date(time).getFullYear()));
  const dateFormat = { day: "numeric", month: "short", ...(years.size > 1 || step >= 91 * DAY ? { year: "numeric" } : {}) };
  const timeFormat = { hour: "2-digit", minute: "2-digit", hourCycle: "h23", ...(step < MINUTE ? { second: "2-digit" } : {}) };
  let previousDay = null;
  return ticks.map((time) => {
    const date = new Date(time);
    const dateText = date.toLocaleDateString(undefined, dateFormat);
    if (step >= DAY) return [dateText];
    const day = date.toDateString();
    const first = day !== previousDay;
    previousDay = day;
    const timeText = date.toLocaleTimeString(undefined, timeFormat);
    return first ? [timeText, dateText] : [timeText];
  });
}

/** x positions of time-sorted items, with items closer than GROUP_PX (overlapping dots) spread side by side. */
function spread(items, x) {
  const groups = [];
  for (const item of items) {
    const position = x(item.time);
    const group = groups[groups.length - 1];
    if (group && position - group.position < GROUP_PX) group.members.push(item);
    else groups.push({ position, members: [item] });
  }
  const placed = new Map();
  groups.forEach((group, groupIndex) => {
    const size = group.members.length;
    group.members.forEach((item, index) => {
      placed.set(item.id, { x: group.position + (index - (size - 1) / 2) * JITTER_PX, groupSize: size, group: groupIndex });
    });
  });
  return placed;
}

function timeDomain(items) {
  let tMin = items[0].time;
  let tMax = items[items.length - 1].time;
  const pad = Math.max((tMax - tMin) * 0.04, 30 * SECOND);
  tMin -= pad;
  tMax += pad;
  return [tMin, tMax];
}

function drawTimeAxis(group, tMin, tMax, x, height, top = MARGIN.top) {
  const { step, ticks } = timeTicks(tMin, tMax);
  const labels = timeTickLabels(ticks, step);
  ticks.forEach((time, index) => {
    group.append(svg("line", { x1: x(time), x2: x(time), y1: top, y2: height - MARGIN.bottom, class: "grid" }));
    const label = svg("text", { x: x(time), y: height - MARGIN.bottom + 14, "text-anchor": "middle", class: "time-tick", "data-time": new Date(time).toISOString() });
    labels[index].forEach((line, lineIndex) => {
      label.append(svg("tspan", { x: x(time), dy: lineIndex ? 12 : 0, class: lineIndex ? "tick-date" : "tick-main" }, line));
    });
    group.append(label);
  });
}

function frame(height, label, className) {
  return svg("svg", { viewBox: `0 0 ${WIDTH} ${height}`, class: `timeline-chart ${className}`, role: "img", "aria-label": label });
}

function valueAxis(chart, yMax, y, height, unit, title, top = MARGIN.top) {
  const axes = svg("g", { class: "chart-axes" });
  for (const tick of niceTicks(0, yMax, 4)) {
    axes.append(svg("line", { x1: MARGIN.left, x2: WIDTH - MARGIN.right, y1: y(tick), y2: y(tick), class: "grid" }));
    axes.append(svg("text", { x: MARGIN.left - 6, y: y(tick) + 4, "text-anchor": "end" }, formatValue(tick, unit)));
  }
  axes.append(svg("line", { x1: MARGIN.left, x2: MARGIN.left, y1: top, y2: height - MARGIN.bottom, class: "axis" }));
  axes.append(svg("line", { x1: MARGIN.left, x2: WIDTH - MARGIN.right, y1: height - MARGIN.bottom, y2: height - MARGIN.bottom, class: "axis" }));
  axes.append(svg("text", { x: MARGIN.left, y: 14, class: "chart-title" }, title));
  chart.append(axes);
}

/** A decision test as a sentence: "Size of the largest region: 1.41 m, above the site's
 * learned threshold of 1.2 m." (the default region threshold is "any region counts"). */
function comparisonSentence(test, info) {
  const value = formatValue(test.value, info.unit);
  const threshold = formatValue(test.threshold, info.unit);
  const relation = test.fires ? "above" : "not above";
  if (test.source === "site") return `${info.title}: ${value}, ${relation} the site's learned threshold of ${threshold}.`;
  if (test.statistic === "largest_region_extent_m") {
    return test.fires ? `${info.title}: ${value}; any region counts (no learned threshold).` : "No region of changed points.";
  }
  return `${info.title}: ${value}, ${relation} the default threshold of ${threshold}.`;
}

/** Horizontal steps through each item's threshold, to the next item (the last to the edge). */
function thresholdSteps(chart, items, placed, y, thresholdOf, classOf) {
  items.forEach((item, index) => {
    const threshold = thresholdOf(item);
    if (!Number.isFinite(threshold)) return;
    const left = index === 0 ? MARGIN.left : placed.get(item.id).x;
    const right = index + 1 < items.length ? placed.get(items[index + 1].id).x : WIDTH - MARGIN.right;
    chart.append(svg("line", { x1: left.toFixed(1), x2: right.toFixed(1), y1: y(threshold).toFixed(1), y2: y(threshold).toFixed(1), class: classOf(item) }));
  });
}

function selectable(element, job, onSelect) {
  element.setAttribute("tabindex", "0");
  element.addEventListener("click", () => onSelect(job));
  element.addEventListener("keydown", (event) => {
    if (event.key === "Enter") onSelect(job);
  });
  return element;
}

function drawDecisive(items, statistic, site, onSelect, tMin, tMax) {
  const info = STATISTICS[statistic] || { title: statistic, unit: "" };
  const chart = frame(MAIN_HEIGHT, `${info.title} in ${items.length} finished jobs over time, with the threshold that decided each`, "decisive-chart");
  chart.dataset.statistic = statistic;
  const calibration = site && site.calibration;
  const forThisDetector = calibration && site.detector
    && calibration.method === site.detector.method && calibration.variant === site.detector.variant;
  const learned = forThisDetector && calibration.status === "learned" && calibration.thresholds
    ? calibration.thresholds[statistic] : null;
  const values = items.flatMap((item) => [item.test.value, item.test.threshold]).filter(Number.isFinite);
  if (Number.isFinite(learned)) values.push(learned);
  const yMax = (Math.max(...values, 0) || 1) * 1.15;
  const plotWidth = WIDTH - MARGIN.left - MARGIN.right;
  const top = MARGIN.top + LEGEND_ROW;
  const plotHeight = MAIN_HEIGHT - top - MARGIN.bottom;
  const x = (time) => MARGIN.left + ((time - tMin) / (tMax - tMin)) * plotWidth;
  const y = (value) => top + plotHeight - (value / yMax) * plotHeight;
  valueAxis(chart, yMax, y, MAIN_HEIGHT, info.unit, `What decides: ${info.title.toLowerCase()} (dots) against the threshold (dashed)`, top);
  drawTimeAxis(chart, tMin, tMax, x, MAIN_HEIGHT, top);
  const placed = spread(items, x);
  thresholdSteps(chart, items, placed, y, (item) => item.test.threshold,
    (item) => `threshold-line threshold-${item.test.source === "site" ? "site" : "default"}`);
  if (Number.isFinite(learned)) {
    const last = placed.get(items[items.length - 1].id).x;
    const line = svg("line", { x1: last.toFixed(1), x2: WIDTH - MARGIN.right, y1: y(learned).toFixed(1), y2: y(learned).toFixed(1), class: "threshold-line threshold-site threshold-next" });
    line.append(svg("title", {}, `Learned from ${site.calibration.n_samples} reviewed jobs: ${formatValue(learned, info.unit)}; applies to the next jobs`));
    chart.append(line);
    chart.append(svg("text", { x: WIDTH - MARGIN.right, y: y(learned) - 4, "text-anchor": "end", class: "threshold-label" },
      `site threshold ${formatValue(learned, info.unit)} (${site.calibration.n_samples} reviews)`));
  }
  for (const item of items) {
    const { x: cx, groupSize, group } = placed.get(item.id);
    const cy = y(item.test.value);
    const dot = selectable(svg("circle", {
      cx: cx.toFixed(1), cy: cy.toFixed(1), r: item.changed ? 6 : 4.5,
      class: item.changed ? "dot dot-changed" : "dot dot-unchanged",
      "data-job-id": item.id, "data-group": group, "data-group-size": groupSize,
    }), item, onSelect);
    const comparison = comparisonSentence(item.test, info);
    const verdict = item.verdict ? `\nverdict: ${VERDICT_NAMES[item.verdict.verdict] || item.verdict.verdict}` : "";
    dot.append(svg("title", {}, `${new Date(item.time).toLocaleString()}\n${comparison}\n${item.changed ? "changed" : "no change"}${verdict}`));
    chart.append(dot);
    if (item.verdict) {
      const kind = item.verdict.verdict;
      const mark = selectable(svg("text", { x: cx.toFixed(1), y: (cy - 10).toFixed(1), "text-anchor": "middle", class: `verdict-mark verdict-${kind}`, "data-job-id": item.id, "data-verdict": kind },
        VERDICT_MARKS[kind] || "?"), item, onSelect);
      mark.append(svg("title", {}, `verdict: ${VERDICT_NAMES[kind] || kind}`));
      chart.append(mark);
    }
  }
  const legend = svg("g", { class: "chart-legend", transform: `translate(${MARGIN.left + 4},${MARGIN.top + 6})` });
  [
    ["circle", { cx: 4, cy: 0, r: 4, class: "dot dot-unchanged" }, 12, "no change"],
    ["circle", { cx: 80, cy: 0, r: 5, class: "dot dot-changed" }, 89, "changed"],
    ["line", { x1: 146, x2: 166, y1: 0, y2: 0, class: "threshold-line threshold-default" }, 170, "default"],
    ["line", { x1: 220, x2: 240, y1: 0, y2: 0, class: "threshold-line threshold-site" }, 244, "site threshold"],
    ["text", { x: 330, y: 4, class: "verdict-mark verdict-false_alarm" }, 340, "false alarm"],
    ["text", { x: 410, y: 4, class: "verdict-mark verdict-confirmed" }, 420, "confirmed"],
  ].forEach(([tag, attributes, textX, label]) => {
    legend.append(svg(tag, attributes, tag === "text" ? (label === "false alarm" ? "✗" : "✓") : null));
    legend.append(svg("text", { x: textX, y: 4 }, label));
  });
  chart.append(legend);
  return chart;
}

function drawDetector(detector, items, tMin, tMax, onSelect) {
  const chart = frame(DETECTOR_HEIGHT, `Scores of the ${detector} detector over time, with its threshold`, "detector-chart");
  chart.dataset.detector = detector;
  const values = items.flatMap((item) => [item.score, item.threshold]).filter(Number.isFinite);
  const yMax = (Math.max(...values, 0) || 1) * 1.15;
  const plotWidth = WIDTH - MARGIN.left - MARGIN.right;
  const plotHeight = DETECTOR_HEIGHT - MARGIN.top - MARGIN.bottom;
  const x = (time) => MARGIN.left + ((time - tMin) / (tMax - tMin)) * plotWidth;
  const y = (value) => MARGIN.top + plotHeight - (value / yMax) * plotHeight;
  valueAxis(chart, yMax, y, DETECTOR_HEIGHT, "", `Detector ${detector}: global score (line) and its own threshold (dashed)`);
  drawTimeAxis(chart, tMin, tMax, x, DETECTOR_HEIGHT);
  const placed = spread(items, x);
  thresholdSteps(chart, items, placed, y, (item) => item.threshold, () => "threshold-line detector-threshold");
  const path = items.map((item, index) => `${index ? "L" : "M"}${placed.get(item.id).x.toFixed(1)},${y(item.score).toFixed(1)}`).join(" ");
  chart.append(svg("path", { d: path, class: "score-line" }));
  for (const item of items) {
    const dot = selectable(svg("circle", { cx: placed.get(item.id).x.toFixed(1), cy: y(item.score).toFixed(1), r: 3, class: "score-dot", "data-job-id": item.id }), item, onSelect);
    dot.append(svg("title", {}, `${new Date(item.time).toLocaleString()}\nscore ${formatValue(item.score)} (threshold ${formatValue(item.threshold)})`));
    chart.append(dot);
  }
  return chart;
}

/**
 * Draw the timeline of `jobs` (JobRead objects) into `container`; `site` (SiteRead, optional)
 * gives the site's learned threshold; `onSelect(job)` is called when a dot is clicked.
 */
export function drawTimeline(container, jobs, onSelect, site = null) {
  container.replaceChildren();
  const finished = jobs
    .filter((job) => job.status === "succeeded")
    .map((job) => ({ ...job, time: Date.parse(job.created_at), test: decisiveTest(job) }))
    .sort((a, b) => a.time - b.time || (a.id < b.id ? -1 : 1));
  if (!finished.length) {
    const empty = document.createElement("p");
    empty.className = "muted timeline-empty";
    empty.textContent = "No finished comparison yet: upload a scan to start the timeline.";
    container.append(empty);
    return empty;
  }
  const counts = new Map();
  for (const job of finished) if (job.test) counts.set(job.test.statistic, (counts.get(job.test.statistic) || 0) + 1);
  const statistic = [...counts.entries()].sort((a, b) => b[1] - a[1])[0]?.[0];
  const decided = finished.filter((job) => job.test && job.test.statistic === statistic && Number.isFinite(job.test.value));
  const [tMin, tMax] = timeDomain(finished);
  if (decided.length) container.append(drawDecisive(decided, statistic, site, onSelect, tMin, tMax));
  const left = finished.length - decided.length;
  if (left) {
    const note = document.createElement("p");
    note.className = "muted timeline-note";
    note.textContent = `${left} job${left > 1 ? "s" : ""} without this decisive statistic (older results or another decision rule) appear only in the detector charts below.`;
    container.append(note);
  }
  const detectors = new Map();
  for (const job of finished) {
    if (!Number.isFinite(job.score)) continue;
    const key = `${job.method} · ${job.variant}`;
    if (!detectors.has(key)) detectors.set(key, []);
    detectors.get(key).push(job);
  }
  for (const [detector, items] of detectors) container.append(drawDetector(detector, items, tMin, tMax, onSelect));
  return container;
}
