"""Signed session cookies and view links (no server needed)."""

from __future__ import annotations

import stat
import time

import pytest

from app.api.session_auth import (
    SignatureInvalidError,
    secret_key,
    sign,
    verify,
)
from app.config import Settings


def test_signed_values_round_trip_and_refuse_tampering_purpose_and_expiry() -> None:
    key = b"k" * 32
    value = sign({"job": "abc", "exp": time.time() + 60}, "view-link", key)
    assert verify(value, "view-link", key)["job"] == "abc"
    body, mac = value.split(".")
    forged = sign({"job": "xyz", "exp": time.time() + 60}, "view-link", b"x" * 32)
    for bad in (f"{body}x.{mac}", f"{body}.{mac[:-2]}", forged, "garbage", ""):
        with pytest.raises(SignatureInvalidError) as refused:
            verify(bad, "view-link", key)
        assert not refused.value.expired
    with pytest.raises(SignatureInvalidError):
        verify(value, "session", key)  # signed for another purpose
    expired = sign({"job": "abc", "exp": time.time() - 1}, "view-link", key)
    with pytest.raises(SignatureInvalidError) as refused:
        verify(expired, "view-link", key)
    assert refused.value.expired


def test_secret_key_is_generated_once_per_data_dir_with_mode_0600(tmp_path) -> None:
    settings = Settings(data_dir=tmp_path / "data")
    key = secret_key(settings)
    path = tmp_path / "data" / "secret-key"
    assert len(key) >= 32 and path.read_text().strip().encode() == key
    assert stat.S_IMODE(path.stat().st_mode) == 0o600
    assert secret_key(Settings(data_dir=tmp_path / "data")) == key
    assert secret_key(Settings(data_dir=tmp_path / "data", secret_key="s" * 40)) == b"s" * 40
