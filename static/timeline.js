// A site's timeline as an SVG chart: one dot per finished job (score over time), the
// threshold as a dashed line, changed jobs in red. Clicking a dot opens the job.

const SVG_NS = "http://www.w3.org/2000/svg";
const WIDTH = 800;
const HEIGHT = 220;
const MARGIN = { top: 14, right: 16, bottom: 30, left: 56 };

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

function formatScore(value) {
  if (value === 0) return "0";
  const magnitude = Math.abs(value);
  return magnitude >= 1000 || magnitude < 0.01 ? value.toExponential(1) : String(Number(value.toPrecision(3)));
}

/**
 * Draw the timeline of `jobs` (objects with created_at, score, threshold, changed, id, status)
 * into `container`; `onSelect(job)` is called when a dot is clicked.
 */
export function drawTimeline(container, jobs, onSelect) {
  container.replaceChildren();
  const scored = jobs
    .filter((job) => job.status === "succeeded" && Number.isFinite(job.score))
    .map((job) => ({ ...job, time: Date.parse(job.created_at) }))
    .sort((a, b) => a.time - b.time);
  const chart = svg("svg", {
    viewBox: `0 0 ${WIDTH} ${HEIGHT}`,
    class: "timeline-chart",
    role: "img",
    "aria-label": `Scores of ${scored.length} finished jobs over time`,
  });
  container.append(chart);
  if (scored.length === 0) {
    chart.append(svg("text", { x: WIDTH / 2, y: HEIGHT / 2, "text-anchor": "middle", class: "chart-empty" },
      "No finished comparison yet: upload a scan to start the timeline."));
    return chart;
  }
  const thresholds = scored.map((job) => job.threshold).filter(Number.isFinite);
  const yMax = Math.max(...scored.map((job) => job.score), ...thresholds, 1e-12) * 1.12;
  let tMin = scored[0].time;
  let tMax = scored[scored.length - 1].time;
  if (tMax - tMin < 60_000) {
    tMin -= 30_000;
    tMax += 30_000;
  }
  const plotWidth = WIDTH - MARGIN.left - MARGIN.right;
  const plotHeight = HEIGHT - MARGIN.top - MARGIN.bottom;
  const x = (time) => MARGIN.left + ((time - tMin) / (tMax - tMin)) * plotWidth;
  const y = (value) => MARGIN.top + plotHeight - (value / yMax) * plotHeight;

  const axes = svg("g", { class: "chart-axes" });
  for (const tick of niceTicks(0, yMax, 4)) {
    axes.append(svg("line", { x1: MARGIN.left, x2: WIDTH - MARGIN.right, y1: y(tick), y2: y(tick), class: "grid" }));
    axes.append(svg("text", { x: MARGIN.left - 6, y: y(tick) + 4, "text-anchor": "end" }, formatScore(tick)));
  }
  const spanDays = (tMax - tMin) / 86_400_000;
  const timeFormat = spanDays > 2
    ? { month: "short", day: "numeric" }
    : { hour: "2-digit", minute: "2-digit" };
  for (let index = 0; index <= 4; index += 1) {
    const time = tMin + ((tMax - tMin) * index) / 4;
    const anchor = index === 0 ? "start" : index === 4 ? "end" : "middle";
    axes.append(svg("text", { x: x(time), y: HEIGHT - 8, "text-anchor": anchor },
      new Date(time).toLocaleString(undefined, timeFormat)));
  }
  axes.append(svg("line", { x1: MARGIN.left, x2: MARGIN.left, y1: MARGIN.top, y2: MARGIN.top + plotHeight, class: "axis" }));
  axes.append(svg("line", { x1: MARGIN.left, x2: WIDTH - MARGIN.right, y1: MARGIN.top + plotHeight, y2: MARGIN.top + plotHeight, class: "axis" }));
  chart.append(axes);

  // Threshold: a step line through each job's own threshold (it is calibrated per job).
  const withThreshold = scored.filter((job) => Number.isFinite(job.threshold));
  if (withThreshold.length) {
    let path = "";
    withThreshold.forEach((job, index) => {
      const nextTime = index + 1 < withThreshold.length ? withThreshold[index + 1].time : tMax;
      const left = index === 0 ? MARGIN.left : x(job.time);
      path += `${index === 0 ? "M" : "L"}${left.toFixed(1)},${y(job.threshold).toFixed(1)} `;
      path += `L${(index + 1 < withThreshold.length ? x(nextTime) : WIDTH - MARGIN.right).toFixed(1)},${y(job.threshold).toFixed(1)} `;
    });
    chart.append(svg("path", { d: path.trim(), class: "threshold-line" }));
  }

  const line = scored.map((job, index) => `${index === 0 ? "M" : "L"}${x(job.time).toFixed(1)},${y(job.score).toFixed(1)}`).join(" ");
  chart.append(svg("path", { d: line, class: "score-line" }));
  for (const job of scored) {
    const dot = svg("circle", {
      cx: x(job.time).toFixed(1),
      cy: y(job.score).toFixed(1),
      r: job.changed ? 6 : 4.5,
      class: job.changed ? "dot dot-changed" : "dot dot-unchanged",
      tabindex: 0,
      "data-job-id": job.id,
    });
    const when = new Date(job.time).toLocaleString();
    dot.append(svg("title", {}, `${when}\nscore ${formatScore(job.score)}` +
      (Number.isFinite(job.threshold) ? ` (threshold ${formatScore(job.threshold)})` : "") +
      `\n${job.changed ? "changed" : "no change"}`));
    dot.addEventListener("click", () => onSelect(job));
    dot.addEventListener("keydown", (event) => {
      if (event.key === "Enter") onSelect(job);
    });
    chart.append(dot);
  }
  const legend = svg("g", { class: "chart-legend", transform: `translate(${MARGIN.left + 8},${MARGIN.top + 4})` });
  legend.append(svg("circle", { cx: 4, cy: 4, r: 4, class: "dot dot-unchanged" }));
  legend.append(svg("text", { x: 12, y: 8 }, "no change"));
  legend.append(svg("circle", { cx: 90, cy: 4, r: 5, class: "dot dot-changed" }));
  legend.append(svg("text", { x: 99, y: 8 }, "changed"));
  legend.append(svg("line", { x1: 160, x2: 184, y1: 4, y2: 4, class: "threshold-line" }));
  legend.append(svg("text", { x: 190, y: 8 }, "threshold"));
  chart.append(legend);
  return chart;
}
