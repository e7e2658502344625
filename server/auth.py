"""API-key authentication: every route but health needs ``X-API-Key`` or a bearer token."""

from __future__ import annotations

import hmac
import logging
import os
import secrets
from pathlib import Path
from typing import Annotated

from fastapi import Depends, Request
from fastapi.security import APIKeyHeader, HTTPAuthorizationCredentials, HTTPBearer

from server.errors import APIError
from server.settings import Settings

log = logging.getLogger(__name__)

_api_key_header = APIKeyHeader(name="X-API-Key", auto_error=False)
_bearer = HTTPBearer(auto_error=False)


def resolve_api_keys(settings: Settings) -> list[str]:
    """The configured keys, or one generated on first start and kept in ``data_dir/api_key``."""
    if settings.api_keys:
        return list(settings.api_keys)
    key_file = Path(settings.data_dir) / "api_key"
    if key_file.is_file():
        key = key_file.read_text().strip()
        if key:
            return [key]
    key_file.parent.mkdir(parents=True, exist_ok=True)
    key = secrets.token_urlsafe(32)
    fd = os.open(key_file, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o600)
    with os.fdopen(fd, "w") as f:
        f.write(key + "\n")
    log.warning("no CSA_API_KEYS set: generated an API key in %s", key_file)
    return [key]


def require_api_key(
    request: Request,
    header_key: Annotated[str | None, Depends(_api_key_header)],
    bearer: Annotated[HTTPAuthorizationCredentials | None, Depends(_bearer)],
) -> None:
    """Dependency: reject the request unless it carries one of the service's API keys."""
    given = header_key or (bearer.credentials if bearer is not None else None)
    keys: list[str] = request.app.state.services.api_keys
    if not given:
        raise APIError(401, "unauthorized", "missing API key (send X-API-Key or Authorization: Bearer)", headers={"WWW-Authenticate": "Bearer"})
    if not any(hmac.compare_digest(given.encode(), k.encode()) for k in keys):
        raise APIError(401, "unauthorized", "invalid API key", headers={"WWW-Authenticate": "Bearer"})
