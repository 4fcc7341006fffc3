// The review panel of the job page: confirm the decision, mark it a false alarm, or make the
// job's scan the site's reference; the current verdict (who, when), its history, and what the
// decision was measured against (the site's learned threshold, when one applied).

import { ApiError, api, describeError, itemsOf } from "./api.js";
import { formatDate, formatNumber, h } from "./dom.js";
import { handleFailure } from "./session.js";
import { VERDICT_NAMES, decisiveTest } from "./timeline.js";

const STATISTIC_NAMES = { largest_region_extent_m: "largest changed region", score: "detector score" };
const UNITS = { largest_region_extent_m: " m" };

function setByText(setBy) {
  if (!setBy) return "unknown";
  const who = setBy.name || (setBy.token_id ? `token ${setBy.token_id.slice(0, 8)}` : "unknown token");
  return `${who} (${setBy.role})`;
}

function verdictText(verdict) {
  const note = verdict.note ? ` — “${verdict.note}”` : "";
  return `${VERDICT_NAMES[verdict.verdict] || verdict.verdict}, by ${setByText(verdict.set_by)} on ${formatDate(verdict.set_at)}${note}`;
}

/** What decided the job, in words: the decisive test and the site calibration's provenance. */
function decisionText(job) {
  const test = decisiveTest(job);
  if (!test) return "This job was decided before decisions recorded their statistic.";
  const unit = UNITS[test.statistic] || "";
  const name = STATISTIC_NAMES[test.statistic] || test.statistic;
  const threshold = test.source === "site" ? "the site's learned threshold" : "the default threshold";
  let text = `Decided by the ${name}: ${formatNumber(test.value)}${unit} ${test.comparison} ${threshold} ${formatNumber(test.threshold)}${unit} → ${test.fires ? "fires" : "does not fire"}.`;
  const site = job.calibration && job.calibration.site;
  if (site && site.applied) {
    text += ` Site calibration: ${site.rule}, ${site.n_samples} reviewed jobs, rank ${site.rank}, target false-alarm rate ${site.false_alarm_rate}.`;
  } else if (site && site.reason) {
    text += ` No site calibration applied: ${site.reason}.`;
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
