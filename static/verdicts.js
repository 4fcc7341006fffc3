// The review panel of the job page: confirm the decision, mark it a false alarm, or make the
// job's scan the site's reference; the current verdict (who, when), its history, and what the
// decision was measured against (the site's learned threshold, when one applied).

import { ApiError, api, describeError, itemsOf } from "./api.js";
import { formatDate, formatNumber, h } from "./dom.js";
import { handleFailure } from "./session.js";
import { VERDICT_NAMES } from "./timeline.js";

function setByText(setBy) {
  if (!setBy) return "unknown";
  const who = setBy.name || (setBy.token_id ? `token ${setBy.token_id.slice(0, 8)}` : "unknown token");
  return `${who} (${setBy.role})`;
}

function verdictText(verdict) {
  const note = verdict.note ? ` — “${verdict.note}”` : "";
  return `${VERDICT_NAMES[verdict.verdict] || verdict.verdict}, by ${setByText(verdict.set_by)} on ${formatDate(verdict.set_at)}${note}`;
}

/** The largest region (the most points, as in the Why line), e.g. "region 2 (added, 1,282 points)". */
export function largestRegionName(job) {
  const largest = job.explanation && job.explanation.largest_region;
  if (!largest) return "the largest region";
  const points = Number.isFinite(largest.n_points) ? `, ${largest.n_points.toLocaleString()} points` : "";
  const number = Number.isInteger(largest.index) ? ` ${largest.index + 1}` : "";
  return `the largest region (region${number}: ${largest.kind}${points})`;
}

/** One decision test as a sentence: what was measured, against which threshold, what followed. */
function testSentence(job, test) {
  const value = formatNumber(test.value);
  const threshold = formatNumber(test.threshold);
  const learned = test.source === "site";
  if (test.statistic === "largest_region_extent_m") {
    if (!test.n_regions && !(test.value > 0)) {
      return "No region of changed points was left after the size floor, so the regions show no change.";
    }
    const region = largestRegionName(job);
    if (!learned) {
      return `A region of changed points was found, so the job counts as changed: ${region} is ${value} m across (no threshold learned from reviews applies, so any region counts).`;
    }
    return test.fires
      ? `${region[0].toUpperCase()}${region.slice(1)} is ${value} m across, more than the site's learned threshold of ${threshold} m, so the job counts as changed.`
      : `${region[0].toUpperCase()}${region.slice(1)} is ${value} m across, not more than the site's learned threshold of ${threshold} m, so the regions do not count as a change.`;
  }
  if (test.statistic === "score") {
    const against = learned ? `the site's learned threshold of ${threshold}` : `its threshold of ${threshold}`;
    return test.fires
      ? `The detector's score ${value} is above ${against}, so the detector says changed.`
      : `The detector's score ${value} is not above ${against}, so the detector says unchanged.`;
  }
  return `${test.statistic} ${value} ${test.fires ? "is above" : "is not above"} its threshold ${threshold}.`;
}

/** What decided the job, in sentences: each decision test and the site calibration's provenance. */
function decisionText(job) {
  const tests = job.calibration && job.calibration.decision && job.calibration.decision.tests;
  if (!Array.isArray(tests) || !tests.length) return "This job was decided before decisions recorded their statistic.";
  let text = tests.map((test) => testSentence(job, test)).join(" ");
  const site = job.calibration && job.calibration.site;
  if (site && site.applied) {
    text += ` The site's threshold was learned (${site.rule}) from ${site.n_samples} reviewed jobs, rank ${site.rank}, for a false-alarm rate of ${site.false_alarm_rate}.`;
  } else if (site && site.reason) {
    text += ` No threshold learned from reviews applied: ${site.reason}.`;
  }
  return text;
}

/** The review section for `job`; `onChanged()` is called after a verdict was saved. */
export function reviewPanel(job, onChanged) {
  const section = h("section", { class: "card", id: "review" }, h("h2", {}, "Review"));
  if (job.status !== "succeeded") {
    section.append(h("p", { class: "muted", id: "review-unavailable" }, "A verdict can be given once the job has succeeded."));
    return section;
  }
  const status = h("p", { id: "verdict-status", role: "status", class: "muted" });
  const note = h("input", { type: "text", id: "verdict-note", maxlength: 2000, size: 48, placeholder: "Note (optional): what you saw" });
  const buttons = [];

  async function send(verdict) {
    buttons.forEach((button) => { button.disabled = true; });
    status.className = "muted";
    status.textContent = "Saving…";
    try {
      await api(`jobs/${job.id}/verdict`, { method: "POST", body: { verdict, note: note.value.trim() || null } });
      status.textContent = `Saved: ${VERDICT_NAMES[verdict]}.`;
      onChanged();
    } catch (failure) {
      if (failure instanceof ApiError && failure.status === 401) return handleFailure(failure, "Saving the verdict");
      status.className = "form-error";
      status.textContent = `Not saved: ${describeError(failure)}`;
      buttons.forEach((button) => { button.disabled = false; });
    }
  }

  const confirm = h("button", { type: "button", id: "verdict-confirmed", onclick: () => send("confirmed") },
    job.changed ? "Confirm: a real change" : "Confirm: nothing changed");
  const falseAlarm = h("button", { type: "button", id: "verdict-false_alarm", onclick: () => send("false_alarm") }, "False alarm");
  const sure = h("span", { id: "new-reference-confirm", hidden: true },
    "This scan becomes the site's reference for the next comparisons. ",
    h("button", { type: "button", id: "verdict-new_reference", class: "primary", onclick: () => send("new_reference") }, "Yes, make it the reference"));
  const newReference = h("button", { type: "button", id: "verdict-new-reference-ask", onclick: () => { sure.hidden = false; } }, "Make this scan the reference…");
  buttons.push(confirm, falseAlarm, newReference, sure.querySelector("button"));

  const current = h("p", { id: "current-verdict", dataset: { verdict: job.verdict ? job.verdict.verdict : "" } },
    job.verdict ? [h("strong", {}, "Verdict: "), verdictText(job.verdict)] : h("span", { class: "muted" }, "No verdict yet."));
  const history = h("ol", { id: "verdict-history", class: "verdict-history" });
  api(`jobs/${job.id}/verdicts`).then(itemsOf).then((entries) => {
    history.replaceChildren(...entries.map((entry) => h("li", { dataset: { verdict: entry.verdict } }, verdictText(entry))));
  }).catch(() => history.replaceChildren());

  section.append(
    h("p", { id: "decision-explained" }, decisionText(job)),
    current,
    h("div", { class: "actions verdict-actions" }, confirm, falseAlarm, newReference),
    sure,
    h("label", { class: "verdict-note" }, "Note ", note),
    status,
    h("details", {}, h("summary", {}, "Verdict history (newest first)"), history));
  return section;
}
