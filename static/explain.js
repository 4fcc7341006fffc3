// A job a reviewer can trust at a glance: why it decided what it did, its quality warnings,
// its sensor origins, and whether a failed job will be tried again (issue 19).

import { formatNumber, h } from "./dom.js";

const WARNING_TITLES = {
  low_registration_fitness: "Low registration fitness",
  large_rotation: "Large rotation",
  large_translation: "Large translation",
  low_overlap: "Low overlap",
  sensor_origin: "Sensor origin contradicted",
  sensor_origin_unknown: "Sensor origin unknown",
  region_count_above_history: "Many more regions than usual",
};

function warningsOf(job) {
  return Array.isArray(job.warnings) ? job.warnings : [];
}

/** A badge with the number of quality warnings (their messages as its tooltip), or null. */
export function warningBadge(job) {
  const warnings = warningsOf(job);
  if (!warnings.length) return null;
  const titles = warnings.map((warning) => WARNING_TITLES[warning.code] || warning.code);
  return h("span", {
    class: "badge badge-warn",
    title: warnings.map((warning) => warning.message).join("\n"),
    dataset: { warningCount: String(warnings.length), warningCodes: warnings.map((w) => w.code).join(" ") },
  }, `⚠ ${warnings.length} ${warnings.length === 1 ? titles[0].toLowerCase() : "warnings"}`);
}

/** The one-line explanation of the decision, with what decided it. */
export function explanationPanel(job) {
  const explanation = job.explanation;
  if (!explanation || !explanation.text) return null;
  const decided = explanation.agrees === false
    ? `The ${explanation.decided_by} decided; the ${explanation.decided_by === "detector" ? "regions" : "detector"} disagreed.`
    : `Decision rule: ${explanation.rule}.`;
  return h("div", { class: "explanation", id: "job-explanation", dataset: { decision: explanation.decision, rule: explanation.rule } },
    h("strong", {}, "Why: "),
    h("span", { id: "job-explanation-text" }, explanation.text),
    h("p", { class: "muted" }, decided));
}

/** Every quality warning of the job, with its message (units and the setting that fixes it). */
export function warningsPanel(job) {
  const warnings = warningsOf(job);
  if (job.status !== "succeeded") return null;
  if (!warnings.length) return h("p", { class: "muted", id: "job-no-warnings" }, "No quality warning.");
  return h("div", { class: "warnings-panel", id: "job-warnings", role: "status" },
    h("strong", {}, `Quality warnings (${warnings.length})`),
    h("ul", {}, warnings.map((warning) => h("li", { dataset: { code: warning.code } },
      h("span", { class: "warning-title" }, `${WARNING_TITLES[warning.code] || warning.code}: `),
      warning.message))));
}

/** "given (1.00, 2.00, 1.20)", "trajectory (154 poses, ...)"... per side, or "unknown". */
export function sensorOriginsText(job) {
  const origins = job.sensor_origins;
  if (!origins) return "—";
  return ["reference", "scan"].map((side) => {
    const entries = origins[side] || [];
    if (!entries.length) return `${side}: unknown`;
    return `${side}: ${entries.map((entry) => (entry.source === "trajectory"
      ? `trajectory (${entry.poses} poses, ${entry.points_outside ?? 0} points outside its times)`
      : `${entry.source} (${entry.origin.map((value) => formatNumber(value, 4)).join(", ")})`)).join("; ")}`;
  }).join(" · ");
}

/** Attempts, and whether a failed attempt will be tried again. */
export function attemptsText(job) {
  if (job.status === "failed") return `failed, will not retry (${job.attempts} of ${job.max_attempts ?? "?"} attempts used)`;
  if (job.will_retry) return `attempt ${job.attempts} failed, will retry (${job.attempts} of ${job.max_attempts ?? "?"} used)`;
  return `${job.attempts} of ${job.max_attempts ?? "?"}`;
}
