"""The dashboard's webhooks page in the real Chromium, on ``scandiff serve`` with its worker.

An admin signs in, is refused a ``ftp://`` URL in words, creates a webhook to a real local
receiver and sees its secret once (gone after reloading), sends a test, and watches the
delivery arrive in the deliveries table as ``delivered`` after the receiver failed it once,
the receiver having checked the signature with the secret the page showed; then deletes it.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

from app.testing.service import ServiceProcess
from app.testing.webhooks import WebhookReceiver
from tests.helpers.browser import by_css as visible
from tests.helpers.browser import save_screenshot, wait_for_page

WEBHOOK_ENV = {
    "SCANDIFF_WEBHOOK_ALLOW_PRIVATE_ADDRESSES": "true",
    "SCANDIFF_WEBHOOK_BACKOFF_SECONDS": "0.3",
    "SCANDIFF_WEBHOOK_POLL_SECONDS": "0.2",
}


def texts(driver: Any, selector: str) -> str:
    from selenium.webdriver.common.by import By

    return " ".join(element.text for element in driver.find_elements(By.CSS_SELECTOR, selector))


def test_create_test_and_delete_a_webhook_in_the_page(
    service_factory: Callable[..., ServiceProcess], chrome_factory: Callable[[], Any]
) -> None:
    from selenium.webdriver.common.by import By

    service = service_factory(workers=1, env=WEBHOOK_ENV)
    driver = chrome_factory()
    with WebhookReceiver(fail_first=1) as receiver:
        driver.get(service.base_url + "/")
        visible(driver, "#token").send_keys(service.admin_token)
        visible(driver, "#sign-in-button").click()
        visible(driver, "#webhooks-link").click()
        visible(driver, "#no-webhooks")

        # A forbidden scheme is refused in words, nothing is created.
        url_field = visible(driver, "#new-webhook-url")
        driver.execute_script("arguments[0].type = 'text'", url_field)  # let ftp:// through
        url_field.send_keys("ftp://files.example.com/hook")
        visible(driver, "#create-webhook").click()
        wait_for_page(
            lambda: "http or https" in texts(driver, "#new-webhook-error"), 20, "no refusal"
        )

        # Created: the secret is shown once; job.unchanged is opt-in (unchecked).
        url_field = visible(driver, "#new-webhook-url")
        url_field.clear()
        url_field.send_keys(receiver.url)
        unchanged = driver.find_element(By.CSS_SELECTOR, "input[value='job.unchanged']")
        assert not unchanged.is_selected()
        visible(driver, "#create-webhook").click()
        receiver.secret = visible(driver, "#new-webhook-secret").text.strip()
        assert receiver.secret.startswith("whsec_")
        row_text = texts(driver, "#webhooks-table tbody tr")
        assert receiver.url in row_text and "job.changed" in row_text
        assert "job.unchanged" not in row_text

        # A test delivery: failed once by the receiver, retried, delivered, shown.
        visible(driver, ".test-webhook").click()
        wait_for_page(
            lambda: driver.find_elements(
                By.CSS_SELECTOR, "#deliveries-table tbody tr[data-status=delivered]"
            ),
            60,
            "the test delivery shown as delivered",
        )
        row = texts(driver, "#deliveries-table tbody tr")
        assert "webhook.test" in row and "200" in row and "2 /" in row
        save_screenshot(driver, "webhooks-page")
        assert [delivery.answered for delivery in receiver.received] == [500, 200]
        assert all(delivery.signature_valid for delivery in receiver.received)

        # The secret is gone once the page is reloaded.
        driver.refresh()
        visible(driver, "#webhooks-table")
        assert not driver.find_elements(By.CSS_SELECTOR, "#new-webhook-secret")
        assert receiver.secret not in driver.page_source

        # Delete (confirming the dialog).
        driver.execute_script("window.confirm = () => true")
        visible(driver, ".delete-webhook").click()
        visible(driver, "#no-webhooks")
    with service.client(service.admin_token) as client:
        assert client.get("/api/v1/webhooks").json()["items"] == []
