"""API-key authentication: every route but health needs ``X-API-Key`` or a bearer token, and
each route a scope (docs/operations.md "Scopes"; the keys themselves: ``server/keys.py``)."""

from __future__ import annotations

import logging
import os
import secrets
from pathlib import Path
from typing import Annotated

from fastapi import Depends, Request
from fastapi.security import APIKeyHeader, HTTPAuthorizationCredentials, HTTPBearer

from server.db.session import release_connection
from server.deps import DbDep
from server.errors import APIError, invalid
from server.keys import (
    ADMIN,
    DEVICE,
    OPERATOR,
    SCOPES,
    Principal,
    Scope,
    hash_secret,
    principal_for_hash,
)
from server.lookups import get_scene
from server.schemas.common import NUL_PROBLEM
from server.settings import Settings

log = logging.getLogger(__name__)

_api_key_header = APIKeyHeader(name="X-API-Key", auto_error=False)
_bearer = HTTPBearer(auto_error=False)
MAX_KEY_CHARS = 1024  # longer values are refused before hashing


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


def _given_key(header_key: str | None, bearer: HTTPAuthorizationCredentials | None) -> str | None:
    return header_key or (bearer.credentials if bearer is not None else None)


def authenticate(request: Request, given: str) -> Principal:
    """The principal of a key: a settings key or an active key of the database (401 otherwise).
    Looked up on every request, so revocation and expiry take effect at the next one."""
    services = request.app.state.services
    if len(given) > MAX_KEY_CHARS:
        raise APIError(
            401, "unauthorized", "invalid API key", headers={"WWW-Authenticate": "Bearer"}
        )
    with services.sessions() as db:
        return principal_for_hash(db, hash_secret(given), services.key_principals)


def require_api_key(
    request: Request,
    header_key: Annotated[str | None, Depends(_api_key_header)],
    bearer: Annotated[HTTPAuthorizationCredentials | None, Depends(_bearer)],
) -> Principal:
    """Dependency: reject the request unless it carries a valid key; the key's principal is
    kept in ``request.state.principal`` for the scope checks and the audit log."""
    given = _given_key(header_key, bearer)
    if not given:
        raise APIError(
            401,
            "unauthorized",
            "missing API key (send X-API-Key or Authorization: Bearer)",
            headers={"WWW-Authenticate": "Bearer"},
        )
    principal = authenticate(request, given)
    request.state.principal = principal
    return principal


def current_principal(request: Request) -> Principal:
    """The principal the router's authentication dependency found (API key or dashboard session)."""
    principal = getattr(request.state, "principal", None)
    if principal is None:  # a route mounted without authentication: a bug, never an open door
        raise APIError(401, "unauthorized", "not authenticated")
    return principal


def _scope_dependency(scope: Scope):
    def require_scope(request: Request) -> Principal:
        principal = current_principal(request)
        if not principal.allows(scope):
            raise APIError(
                403,
                "forbidden",
                f"this route needs scope {scope!r}; key {principal.name!r} has scope "
                f"{principal.scope!r}",
            )
        return principal

    require_scope.__name__ = f"require_{scope}_scope"
    return require_scope


_SCOPE_DEPENDENCIES = {scope: _scope_dependency(scope) for scope in SCOPES}


def require_scope(scope: Scope):
    """The dependency that refuses a principal below ``scope`` with 403 naming the scope needed
    (one function per scope, so FastAPI runs it once per request)."""
    return _SCOPE_DEPENDENCIES[scope]


def check_scene_access(request: Request, db: DbDep) -> None:
    """Dependency of the routes a device key may use on a scene (``scene_ref`` in the path):
    a device key reaches only the scenes it created; 403 for others' (404 for no scene)."""
    principal = current_principal(request)
    ref = request.path_params.get("scene_ref")
    if ref is None or principal.allows(OPERATOR):
        return
    if "\x00" in ref:  # this runs before the route checks its parameters (ParamText)
        raise invalid("scene_ref", NUL_PROBLEM)
    scene = get_scene(db, ref)
    # The route may go on to await a body (an upload) before it needs the database again.
    release_connection(db)
    if scene.owner_key_id is None or scene.owner_key_id != principal.key_id:
        raise APIError(
            403,
            "forbidden",
            f"scene {scene.name!r} was not created by key {principal.name!r}; other keys' scenes "
            f"need scope {OPERATOR!r}",
        )


PrincipalDep = Annotated[Principal, Depends(current_principal)]
DeviceScope = Depends(require_scope(DEVICE))
OperatorScope = Depends(require_scope(OPERATOR))
AdminScope = Depends(require_scope(ADMIN))
SceneAccess = Depends(check_scene_access)
