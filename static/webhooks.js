// Webhooks: the organisation's webhooks with their last delivery (status, attempts, last error),
// a form for a new one (its secret shown once), delete, send a test, and each webhook's
// deliveries (status, attempts, last answer, next attempt).
// Routes: #/webhooks and #/webhooks/<id> (the same page with that webhook's deliveries).

import { ApiError, api, describeError, itemsOf } from "./api.js";
import { formatDate, h } from "./dom.js";
import { app, currentRender, schedulePoll, setCrumbs } from "./page.js";
import { handleFailure } from "./session.js";

const EVENTS = [
  ["job.changed", "a comparison found a change", true],
  ["job.unchanged", "a comparison found no change", false],
  ["job.failed", "a comparison failed", true],
  ["site.stale", "a scheduled site sent no scan", true],
  ["schedule.missed", "a scheduled period had no scan", true],
];

const STATUS_BADGES = { delivered: "badge-ok", failed: "badge-bad", delivering: "badge-busy", pending: "badge-wait" };

let shownSecret = null; // { id, secret }: shown once, right after creating, until the page is left

/** A webhook's newest delivery in a cell: its status, attempts and last error, or "none yet". */
function lastDeliveryCell(webhook, delivery) {
  if (!delivery) return h("td", { class: "last-delivery muted" }, "none yet");
  return h("td", { class: "last-delivery", dataset: { status: delivery.status, deliveryId: delivery.id } },
    h("span", { class: `badge ${STATUS_BADGES[delivery.status] || "badge-wait"}` }, delivery.status), " ",
    h("span", { class: "delivery-event" }, delivery.event_type), " · ",
    h("span", { class: "delivery-attempts" }, `attempt ${delivery.attempts} of ${delivery.max_attempts}`),
    delivery.last_error ? h("div", { class: "delivery-error error-cell" }, delivery.last_error) : null,
    h("div", {}, h("a", { href: `#/webhooks/${webhook.id}`, class: "deliveries-link" }, "All deliveries ›")));
}

function deliveriesSection(webhook, deliveries) {
  const rows = deliveries.map((delivery) => h("tr", { dataset: { status: delivery.status, deliveryId: delivery.id } },
    h("td", {}, formatDate(delivery.created_at)),
    h("td", {}, h("code", {}, delivery.event_type)),
    h("td", {}, h("code", { title: delivery.event_id }, delivery.event_id.slice(0, 8))),
    h("td", {}, h("span", { class: `badge ${STATUS_BADGES[delivery.status] || "badge-wait"}` }, delivery.status)),
    h("td", { class: "num" }, `${delivery.attempts} / ${delivery.max_attempts}`),
    h("td", { class: "num" }, delivery.last_status_code ?? "—"),
    h("td", {}, delivery.next_attempt_at && delivery.status === "pending" ? formatDate(delivery.next_attempt_at) : "—"),
    h("td", { class: "muted" }, delivery.last_error || "")));
  return h("section", { class: "card", id: "webhook-deliveries" },
    h("h2", {}, "Deliveries to ", h("code", {}, webhook.url)),
    deliveries.length
      ? h("table", { class: "table", id: "deliveries-table" },
        h("thead", {}, h("tr", {}, ["Created", "Event", "Event id", "Status", "Attempts", "Last answer", "Next attempt", "Last error"].map((title) => h("th", {}, title)))),
        h("tbody", {}, rows))
      : h("p", { class: "muted", id: "no-deliveries" }, "No delivery yet. Send a test, or wait for an event."));
}

function newWebhookForm() {
  const urlInput = h("input", { id: "new-webhook-url", name: "url", type: "url", required: true, size: 48, maxlength: 2000, placeholder: "https://hooks.example.com/scandiff" });
  const boxes = EVENTS.map(([name, meaning, checked]) => h("label", { class: "checkbox" },
    h("input", { type: "checkbox", name: "events", value: name, checked: checked || undefined }), ` ${name} `, h("span", { class: "muted" }, `(${meaning})`)));
  const formError = h("p", { class: "form-error", role: "alert", id: "new-webhook-error" });
  const form = h("form", { id: "new-webhook-form", class: "inline-form" },
    h("label", { for: "new-webhook-url" }, "URL"), urlInput,
    h("fieldset", {}, h("legend", {}, "Events"), boxes),
    h("button", { type: "submit", class: "primary", id: "create-webhook" }, "Create webhook"), formError);
  form.addEventListener("submit", async (event) => {
    event.preventDefault();
    formError.textContent = "";
    const events = [...form.querySelectorAll("input[name=events]:checked")].map((box) => box.value);
    try {
      const created = await api("webhooks", { method: "POST", body: { url: urlInput.value.trim(), events } });
      shownSecret = { id: created.id, secret: created.secret };
      await renderWebhooks(created.id);
    } catch (failure) {
      if (failure instanceof ApiError && failure.status === 401) return handleFailure(failure, "Creating the webhook");
      formError.textContent = `The webhook was not created: ${describeError(failure)}`;
    }
  });
  return form;
}

async function act(action, what) {
  try {
    await action();
  } catch (failure) {
    await handleFailure(failure, what);
  }
}

export async function renderWebhooks(selectedId = null) {
  const generation = currentRender();
  setCrumbs(h("a", { href: "#/" }, "Sites"), h("span", {}, "Webhooks"));
  const webhooks = itemsOf(await api("webhooks?limit=200"));
  const selected = webhooks.find((webhook) => webhook.id === selectedId) || null;
  const [deliveries, lastDeliveries] = await Promise.all([
    selected ? api(`webhooks/${selected.id}/deliveries?limit=50`).then(itemsOf) : Promise.resolve([]),
    Promise.all(webhooks.map((webhook) => api(`webhooks/${webhook.id}/deliveries?limit=1`).then((page) => itemsOf(page)[0] || null).catch(() => null))),
  ]);
  if (generation !== currentRender()) return;

  const rows = webhooks.map((webhook, index) => {
    const test = h("button", { type: "button", class: "test-webhook" }, "Send test");
    test.addEventListener("click", () => act(async () => {
      await api(`webhooks/${webhook.id}/test`, { method: "POST" });
      if (location.hash === `#/webhooks/${webhook.id}`) await renderWebhooks(webhook.id);
      else location.hash = `#/webhooks/${webhook.id}`;
    }, "Sending a test delivery"));
    const remove = h("button", { type: "button", class: "delete-webhook danger" }, "Delete");
    remove.addEventListener("click", () => act(async () => {
      if (!window.confirm(`Delete the webhook to ${webhook.url}? Its pending deliveries are dropped.`)) return;
      await api(`webhooks/${webhook.id}`, { method: "DELETE" });
      shownSecret = null;
      if (location.hash === "#/webhooks") await renderWebhooks();
      else location.hash = "#/webhooks";
    }, "Deleting the webhook"));
    return h("tr", { dataset: { webhookId: webhook.id }, class: webhook.id === selectedId ? "selected" : "" },
      h("td", {}, h("a", { href: `#/webhooks/${webhook.id}`, class: "webhook-link" }, webhook.url)),
      h("td", {}, webhook.events.join(", ")),
      h("td", {}, formatDate(webhook.created_at)),
      lastDeliveryCell(webhook, lastDeliveries[index]),
      h("td", {}, test, " ", remove));
  });

  const secretBox = shownSecret && webhooks.some((webhook) => webhook.id === shownSecret.id)
    ? h("section", { class: "card secret", id: "new-webhook-secret-card" },
      h("h2", {}, "The webhook's secret"),
      h("p", {}, "Copy it now: it is shown this once only. Receivers check each delivery's ",
        h("code", {}, "Scandiff-Signature"), " with it (see docs/webhooks.md)."),
      h("pre", { id: "new-webhook-secret" }, shownSecret.secret))
    : null;

  app.replaceChildren(
    ...(secretBox ? [secretBox] : []),
    h("section", { class: "card" },
      h("h1", {}, "Webhooks"),
      webhooks.length
        ? h("table", { class: "table", id: "webhooks-table" },
          h("thead", {}, h("tr", {}, ["URL", "Events", "Created", "Last delivery", ""].map((title) => h("th", {}, title)))),
          h("tbody", {}, rows))
        : h("p", { class: "muted", id: "no-webhooks" }, "No webhook yet. Create one below to hear about changes outside the dashboard.")),
    ...(selected ? [deliveriesSection(selected, deliveries)] : []),
    h("section", { class: "card" }, h("h2", {}, "New webhook"),
      h("p", { class: "muted" }, "Admins only. The URL must be http(s) on a public address."), newWebhookForm()));
  const unfinished = (delivery) => delivery && (delivery.status === "pending" || delivery.status === "delivering");
  if (deliveries.some(unfinished) || lastDeliveries.some(unfinished)) {
    schedulePoll(() => renderWebhooks(selectedId).catch((failure) => handleFailure(failure, "Refreshing the deliveries")));
  }
}
