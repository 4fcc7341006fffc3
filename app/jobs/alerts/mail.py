"""E-mail alerts: a webhook whose url is ``mailto:...`` gets its events by SMTP.

The delivery machinery is the webhooks' (:mod:`app.jobs.alerts.deliveries`: claims, leases, retries
with backoff, the deliveries route); only the sending differs.  The message has a subject that
says what happened, a short text (site, decision, score against threshold, regions, the view
link) and the delivery's JSON body as an attachment; it carries the same ``Scandiff-Event-Id``
and ``Scandiff-Signature`` headers as a webhook POST.  The server is ``SCANDIFF_SMTP_HOST``
(``SCANDIFF_SMTP_PORT``, ``..._SECURITY``, ``..._USERNAME``, ``..._PASSWORD``, ``..._FROM``).
"""

from __future__ import annotations

import json
import smtplib
import ssl
from email.message import EmailMessage
from email.utils import make_msgid
from typing import Any

from app.config import Settings

SMTP_ACCEPTED = 250


def subject_of(document: dict[str, Any]) -> str:
    """``[scandiff] job.changed: warehouse-north (changed)`` and the like."""
    site = document.get("site") if isinstance(document.get("site"), dict) else {}
    where = f": {site.get('name')}" if site and site.get("name") else ""
    decision = f" ({document['decision']})" if document.get("decision") else ""
    return f"[scandiff] {document.get('type', 'event')}{where}{decision}"[:200]


def text_of(document: dict[str, Any]) -> str:
    """The message's plain text: what happened, in a few lines."""
    lines = [
        f"Event {document.get('type')} ({document.get('id')}) at {document.get('created_at')}."
    ]
    site = document.get("site")
    if isinstance(site, dict):
        lines.append(f"Site: {site.get('name')} ({site.get('id')})")
    job = document.get("job")
    if isinstance(job, dict):
        lines.append(f"Job: {job.get('id')}, {job.get('status')}")
        if job.get("error"):
            lines.append(f"Error: {job['error']}")
    if document.get("decision"):
        lines.append(
            f"Decision: {document['decision']} (score {document.get('score')}, "
            f"threshold {document.get('threshold')})"
        )
    regions = document.get("regions")
    if isinstance(regions, dict):
        lines.append(
            f"Regions: {regions.get('count')} ({regions.get('added')} added, "
            f"{regions.get('removed')} removed), {regions.get('changed_points')} changed points"
        )
    link = document.get("view_link")
    if isinstance(link, dict):
        lines.append(f"3D view (until {link.get('expires_at')}): {link.get('url')}")
    if document.get("message"):
        lines.append(str(document["message"]))
    lines.append("")
    lines.append("The event as JSON is attached (event.json).")
    return "\n".join(lines) + "\n"


def send_email(
    recipients: list[str], body: bytes, headers: dict[str, str], settings: Settings
) -> tuple[int | None, str | None]:
    """Send the delivery ``body`` to ``recipients``; ``(smtp status, error or None)``."""
    if not settings.smtp_host:
        return None, "not sent: e-mail alerts need SCANDIFF_SMTP_HOST"
    document = json.loads(body)
    message = EmailMessage()
    message["From"] = settings.smtp_from
    message["To"] = ", ".join(recipients)
    message["Subject"] = subject_of(document)
    message["Message-ID"] = make_msgid(idstring=headers.get("Scandiff-Delivery-Id"))
    for name in ("Scandiff-Event-Id", "Scandiff-Event-Type", "Scandiff-Signature"):
        if name in headers:
            message[name] = headers[name]
    message.set_content(text_of(document))
    message.add_attachment(body, maintype="application", subtype="json", filename="event.json")
    timeout = settings.webhook_timeout_seconds
    try:
        if settings.smtp_security == "ssl":
            client: smtplib.SMTP = smtplib.SMTP_SSL(
                settings.smtp_host,
                settings.smtp_port,
                timeout=timeout,
                context=ssl.create_default_context(),
            )
        else:
            client = smtplib.SMTP(settings.smtp_host, settings.smtp_port, timeout=timeout)
        with client:
            if settings.smtp_security == "starttls":
                client.starttls(context=ssl.create_default_context())
            if settings.smtp_username:
                client.login(settings.smtp_username, settings.smtp_password or "")
            client.send_message(message)  # accepted for some recipients only: no retry either,
            # which would send the message twice to the others
    except smtplib.SMTPResponseException as exc:
        return int(exc.smtp_code), f"SMTP {exc.smtp_code}: {exc.smtp_error!r}"[:500]
    except smtplib.SMTPRecipientsRefused as exc:
        return None, f"every recipient was refused: {sorted(exc.recipients)}"[:500]
    except (OSError, smtplib.SMTPException) as exc:
        return None, f"{type(exc).__name__}: {exc}"[:500]
    return SMTP_ACCEPTED, None
