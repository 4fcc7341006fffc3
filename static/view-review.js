// The review panel inside the 3D view (issue 16): the job page's verdict buttons, for a reader
// signed in to the dashboard. A visitor who came by a view link (no session) is told where to
// sign in; giving a verdict always needs a writer's session.

import { ApiError, api, describeError } from "./api.js";
import { h } from "./dom.js";
import { reviewPanel } from "./verdicts.js";

const jobId = decodeURIComponent(window.location.pathname.split("/")[2] || "");
const holder = h("details", { id: "view-review", open: true });
Object.assign(holder.style, {
  position: "fixed", left: "12px", bottom: "12px", zIndex: 1000, maxWidth: "26rem",
  maxHeight: "60vh", overflow: "auto", background: "rgba(255, 255, 255, 0.96)", color: "#1d2733",
  border: "1px solid #c9d3de", borderRadius: "8px", padding: "0.5rem 0.75rem",
  font: "14px system-ui, sans-serif", boxShadow: "0 2px 8px rgba(0, 0, 0, 0.15)",
});

async function render() {
  let body;
  try {
    const job = await api(`jobs/${jobId}`);
    body = reviewPanel(job, () => render());
  } catch (failure) {
    const signedOut = failure instanceof ApiError && failure.status === 401;
    body = h("p", { id: "view-review-unavailable" }, signedOut
      ? ["Sign in to the ", h("a", { href: `/#/jobs/${jobId}`, target: "_blank", rel: "noopener" }, "dashboard"), " to give a verdict."]
      : `The review panel is not available: ${describeError(failure)}`);
  }
  holder.replaceChildren(h("summary", {}, "Review this job"), body);
}

document.body.append(holder);
render();
