// The review panel inside the 3D view (issue 16): the job page's verdict buttons, for a reader
// signed in to the dashboard. A visitor who came by a view link (no session) is told where to
// sign in; giving a verdict always needs a writer's session.
//
// It never covers the scene (issue 31): open, it is a column docked to the left and the 3D
// view's root is narrowed beside it (the canvas follows its container's size); closed, it is
// a small tab in the bottom-left corner. Its content wraps to the column's width: no
// horizontal scrollbar, the note field fits.

import { ApiError, api, describeError } from "./api.js";
import { h } from "./dom.js";
import { reviewPanel } from "./verdicts.js";

const DOCK_WIDTH_PX = 320;
const jobId = decodeURIComponent(window.location.pathname.split("/")[2] || "");
const holder = h("details", { id: "view-review" });
Object.assign(holder.style, {
  position: "fixed", left: "0", zIndex: 1000, boxSizing: "border-box", overflowX: "hidden",
  overflowY: "auto", background: "rgba(255, 255, 255, 0.98)", color: "#1d2733",
  border: "1px solid #c9d3de", padding: "0.5rem 0.75rem", font: "14px system-ui, sans-serif",
  overflowWrap: "anywhere",
});
document.head.append(h("style", {}, `
  #view-review input, #view-review textarea, #view-review select { max-width: 100%; box-sizing: border-box; }
  #view-review input[type=text], #view-review textarea { width: 100%; }
  #view-review * { max-width: 100%; }
  #view-review summary { cursor: pointer; font-weight: 600; white-space: nowrap; }
`));

function dock() {
  const root = document.getElementById("root");
  if (holder.open) {
    Object.assign(holder.style, { top: "0", bottom: "0", left: "0", width: `${DOCK_WIDTH_PX}px`, borderRadius: "0" });
    if (root) Object.assign(root.style, { marginLeft: `${DOCK_WIDTH_PX}px`, width: `calc(100% - ${DOCK_WIDTH_PX}px)` });
  } else {
    Object.assign(holder.style, { top: "auto", bottom: "12px", left: "12px", width: "auto", borderRadius: "8px" });
    if (root) Object.assign(root.style, { marginLeft: "", width: "" });
  }
  window.dispatchEvent(new Event("resize"));
}

let first = true;
async function render() {
  let body;
  let available = true;
  try {
    const job = await api(`jobs/${jobId}`);
    body = reviewPanel(job, () => render());
  } catch (failure) {
    available = false;
    const signedOut = failure instanceof ApiError && failure.status === 401;
    body = h("p", { id: "view-review-unavailable" }, signedOut
      ? ["Sign in to the ", h("a", { href: `/#/jobs/${jobId}`, target: "_blank", rel: "noopener" }, "dashboard"), " to give a verdict."]
      : `The review panel is not available: ${describeError(failure)}`);
  }
  holder.replaceChildren(h("summary", {}, "Review this job"), body);
  if (first) {  // open for a reviewer who can give a verdict, a tab for a visitor
    first = false;
    holder.open = available;
    dock();
  }
}

holder.addEventListener("toggle", dock);
document.body.append(holder);
dock();
render();
