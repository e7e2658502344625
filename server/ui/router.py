"""The dashboard at ``/ui``: server-rendered pages, their pictures and a few actions of their
own, reading and changing the service's state through the service layer (``server/services``),
as the REST routers do.

The pages' scripts call the REST API again under ``/ui/api/v1``, with the session cookie
instead of a key header: ``server/app.py`` includes the REST routers a second time there
rather than re-implementing them, so every answer, check and error is the one ``/api/v1``
gives; only authentication differs (:func:`server.ui.session.require_ui_session`). The REST
API under ``/api/v1`` never reads the cookie.
"""

from __future__ import annotations

import json
import logging
import math
import threading
from collections.abc import Callable
from pathlib import Path
from typing import Annotated, Any, Literal
from urllib.parse import quote

from fastapi import (
    APIRouter,
    Depends,
    File,
    Form,
    HTTPException,
    Query,
    Request,
    UploadFile,
    status,
)
from fastapi.responses import FileResponse, RedirectResponse, Response
from fastapi.templating import Jinja2Templates
from starlette.concurrency import run_in_threadpool

from csa_core.data.scene import split_point
from server import capabilities
from server.auth import DeviceScope, OperatorScope, SceneAccess, check_scene_access
from server.deps import DbDep, ServicesDep
from server.errors import APIError, not_found, too_large
from server.jobs.queue import TERMINAL
from server.keys import ADMIN, DEVICE, OPERATOR, Principal, Scope
from server.schemas.common import ParamText
from server.schemas.jobs import JobId, JobOut
from server.services import audit, frames, jobs, models, nerfs, scenes
from server.ui import page_data, panels
from server.ui.session import (
    COOKIE,
    COOKIE_PATH,
    CSRF_FIELD,
    SESSION_SECONDS,
    UISession,
    check_csrf,
    current_session,
    is_https,
    require_ui_session,
    same_origin,
    signer,
    valid_key,
)

log = logging.getLogger(__name__)

HERE = Path(__file__).resolve().parent
STATIC = {p.name: p for p in (HERE / "static").iterdir() if p.suffix in (".css", ".js", ".svg")}
FRAMES_PER_PAGE = 40
# Pages allow their own scripts and styles only; inline style attributes carry data colours.
CSP = (
    "default-src 'self'; script-src 'self'; style-src 'self' 'unsafe-inline'; "
    "img-src 'self' data: blob:; connect-src 'self'; form-action 'self'; "
    "frame-ancestors 'none'; base-uri 'none'; object-src 'none'"
)
PAGE_HEADERS = {
    "Content-Security-Policy": CSP,
    "X-Content-Type-Options": "nosniff",
    "X-Frame-Options": "DENY",
    "Referrer-Policy": "same-origin",
    "Cache-Control": "no-store",
}

NAV = (
    ("scenes", "Scenes"),
    ("jobs", "Jobs"),
    ("models", "Models"),
    ("continual", "Continual metrics"),
    ("memory", "Memory bank"),
    ("try", "Try it"),
    ("work", "Start work"),
    ("audit", "Audit log"),
)
# The scope each page needs, the REST routes' scopes (docs/operations.md "Dashboard").
PAGE_SCOPES: dict[str, Scope] = {
    "scenes": DEVICE,
    "jobs": OPERATOR,
    "models": OPERATOR,
    "continual": OPERATOR,
    "memory": OPERATOR,
    "try": DEVICE,
    "work": OPERATOR,
    "audit": ADMIN,
}
AUDIT_PER_PAGE = 100

templates = Jinja2Templates(directory=HERE / "templates")


def _pct(value: Any, digits: int = 1) -> str:
    if not isinstance(value, int | float) or not math.isfinite(value):
        return "–"
    return f"{100 * value:.{digits}f}%"


def _signed_pct(value: Any) -> str:
    if not isinstance(value, int | float) or not math.isfinite(value):
        return "–"
    return f"{100 * value:+.1f} pts"


def _bytes(value: Any) -> str:
    if not isinstance(value, int | float):
        return "–"
    for unit, scale in (("GB", 1e9), ("MB", 1e6), ("kB", 1e3)):
        if value >= scale:
            return f"{value / scale:.2f} {unit}"
    return f"{int(value)} B"


def _heat(value: Any) -> str:
    """Inline style of an R-matrix cell: viridis over mIoU 0..1, text readable on it."""
    if not isinstance(value, int | float) or not math.isfinite(value):
        return ""
    from matplotlib import colormaps

    r, g, b, _ = colormaps["viridis"](min(max(float(value), 0.0), 1.0))
    text = "#000" if 0.299 * r + 0.587 * g + 0.114 * b > 0.5 else "#fff"
    return f"background:#{int(255 * r):02x}{int(255 * g):02x}{int(255 * b):02x};color:{text}"


templates.env.filters.update(
    pct=_pct,
    signed_pct=_signed_pct,
    nbytes=_bytes,
    heat=_heat,
    tojson_pretty=lambda v: json.dumps(v, indent=2, sort_keys=True, default=str),
)
templates.env.globals["class_legend"] = panels.class_legend()  # the pictures' colours


def _page(
    request: Request, name: str, session: UISession | None, status_code: int = 200, **context: Any
) -> Response:
    principal = session.principal if session else None
    context |= {
        "nav": [(k, label) for k, label in NAV if principal and principal.allows(PAGE_SCOPES[k])],
        "csrf_token": session.csrf_token if session else "",
        "signed_in": session is not None,
        "principal": principal,
    }
    return templates.TemplateResponse(
        request, name, context, status_code=status_code, headers=PAGE_HEADERS
    )


def _safe_next(target: str | None) -> str:
    """Only a path of the dashboard itself (never another host) after signing in."""
    if (
        target
        and (target == "/ui" or target.startswith("/ui/"))
        and "//" not in target
        and "\\" not in target
    ):
        return target
    return "/ui/scenes"


def page_session(request: Request) -> UISession:
    """Dependency of pages: the session, or a redirect to the sign-in page; 403 naming the
    scope when the key's scope does not reach the page."""
    session = current_session(request)
    if session is None:
        target = request.url.path + (f"?{request.url.query}" if request.url.query else "")
        raise HTTPException(
            status_code=status.HTTP_303_SEE_OTHER,
            detail="sign in first",
            headers={"Location": f"/ui/login?next={quote(target, safe='/')}", **PAGE_HEADERS},
        )
    request.state.principal = session.principal
    page = request.url.path.removeprefix("/ui/").split("/", 1)[0]
    needed = PAGE_SCOPES.get(page)
    principal: Principal = session.principal
    if needed is not None and not principal.allows(needed):
        raise APIError(
            403,
            "forbidden",
            f"this page needs scope {needed!r}; key {principal.name!r} has {principal.scope!r}",
        )
    return session


PageSession = Annotated[UISession, Depends(page_session)]
ApiSession = Annotated[UISession, Depends(require_ui_session)]

router = APIRouter(prefix="/ui", include_in_schema=False)


# -- signing in ---------------------------------------------------------------------------


@router.get("")
def root() -> RedirectResponse:
    return RedirectResponse("/ui/scenes", status_code=status.HTTP_303_SEE_OTHER)


@router.get("/login")
def login_page(request: Request, next: str | None = None) -> Response:
    if current_session(request) is not None:
        return RedirectResponse(_safe_next(next), status_code=status.HTTP_303_SEE_OTHER)
    return _page(request, "login.html", None, next=_safe_next(next), error=None)


@router.post("/login")
def login(
    request: Request, api_key: Annotated[str, Form()] = "", next: Annotated[str, Form()] = ""
) -> Response:
    """Check the key once and hand out a session cookie; the key itself is kept nowhere."""
    target = _safe_next(next)
    if not same_origin(request):
        return _page(
            request,
            "login.html",
            None,
            status_code=403,
            next=target,
            error="This sign-in form was sent from another site.",
        )
    if not api_key.strip():
        return _page(
            request, "login.html", None, status_code=401, next=target, error="Enter an API key."
        )
    principal = valid_key(request, api_key.strip()) if len(api_key) <= 1024 else None
    if principal is None:
        log.warning(
            "dashboard sign-in refused (invalid API key) from %s",
            request.client.host if request.client else "?",
        )
        return _page(
            request,
            "login.html",
            None,
            status_code=401,
            next=target,
            error="That API key is not valid.",
        )
    request.state.principal = principal  # the audit log records who signed in
    response = RedirectResponse(target, status_code=status.HTTP_303_SEE_OTHER)
    response.set_cookie(
        COOKIE,
        signer(request).issue(api_key.strip(), key_row=principal.key_id),
        max_age=SESSION_SECONDS,
        path=COOKIE_PATH,
        secure=is_https(request),
        httponly=True,
        samesite="strict",
    )
    return response


@router.post("/logout")
def logout(
    request: Request, session: PageSession, csrf_token: Annotated[str, Form(alias=CSRF_FIELD)] = ""
) -> Response:
    check_csrf(request, session, csrf_token)
    response = RedirectResponse("/ui/login", status_code=status.HTTP_303_SEE_OTHER)
    response.delete_cookie(
        COOKIE, path=COOKIE_PATH, secure=is_https(request), httponly=True, samesite="strict"
    )
    return response


@router.get("/static/{name}")
def static_file(name: str) -> FileResponse:
    path = STATIC.get(name)
    if path is None:
        raise not_found("file", name)
    return FileResponse(
        path, headers={"Cache-Control": "no-cache", "X-Content-Type-Options": "nosniff"}
    )


# -- pages --------------------------------------------------------------------------------


_state_lock = threading.Lock()


def _app_object(request: Request, name: str, make: Callable[[], Any]) -> Any:
    """An object the dashboard keeps for the app's lifetime (caches), made on first use."""
    state = request.app.state
    with _state_lock:
        if getattr(state, name, None) is None:
            setattr(state, name, make())
        return getattr(state, name)


def _coverage(request: Request, services) -> page_data.DepthCoverage:
    return _app_object(
        request, "ui_depth_coverage", lambda: page_data.DepthCoverage(services.store)
    )


@router.get("/scenes")
def scenes_page(
    request: Request, session: PageSession, db: DbDep, services: ServicesDep
) -> Response:
    rows = page_data.scene_rows(db, _coverage(request, services), visible_to=session.principal)
    return _page(request, "scenes.html", session, active="scenes", rows=rows)


@router.get("/scenes/{scene_ref}")
def scene_page(
    request: Request,
    scene_ref: ParamText,
    session: PageSession,
    db: DbDep,
    frame: Annotated[ParamText | None, Query(max_length=64)] = None,
    page: Annotated[int, Query(ge=0, le=100_000)] = 0,
) -> Response:
    try:
        check_scene_access(request, db)  # a device key sees only the scenes it created
        scene = scenes.show_scene(db, scene_ref)
    except APIError as e:
        return _page(request, "error.html", session, e.status, active="scenes", error=e.message)
    all_frames = frames.all_frames(db, scene.id)
    pages = max(1, math.ceil(len(all_frames) / FRAMES_PER_PAGE))
    page = min(page, pages - 1)
    selected = next((f for f in all_frames if f.name == frame), None)
    if selected is None and all_frames:
        selected = all_frames[page * FRAMES_PER_PAGE] if frame is None else None
    if selected is not None and frame is not None:
        page = all_frames.index(selected) // FRAMES_PER_PAGE
    strip = all_frames[page * FRAMES_PER_PAGE : (page + 1) * FRAMES_PER_PAGE]
    model = models.current_model_out(db)
    nerf = nerfs.active_nerf_out(db, scene.id, scene.name)
    return _page(
        request,
        "scene.html",
        session,
        active="scenes",
        scene=scene,
        strip=strip,
        num_train=split_point(len(all_frames)),
        frame_index={f.name: i for i, f in enumerate(all_frames)},
        selected=selected,
        missing_frame=frame if frame is not None and selected is None else None,
        page=page,
        pages=pages,
        model=model,
        seg_reason=capabilities.missing_reason("seg"),
        nerf=nerf,
        nerf_quality=page_data.quality_items(nerf.quality) if nerf else [],
    )


@router.get("/jobs")
def jobs_page(request: Request, session: PageSession, db: DbDep) -> Response:
    return _page(
        request,
        "jobs.html",
        session,
        active="jobs",
        jobs=jobs.list_jobs(db, limit=100),
    )


@router.get("/jobs/{job_id}")
def job_page(
    request: Request,
    job_id: JobId,
    session: PageSession,
    db: DbDep,
) -> Response:
    try:
        job = jobs.show_job(db, job_id)
    except APIError as e:
        return _page(request, "error.html", session, e.status, active="jobs", error=e.message)
    log_lines = jobs.job_log(db, job_id, tail=200).lines
    retry_of = next(
        (
            int(line.message.split()[-1])
            for line in log_lines
            if line.message.startswith("retry of job ")
        ),
        None,
    )
    return _page(
        request,
        "job.html",
        session,
        active="jobs",
        job=job,
        log_lines=log_lines,
        retry_of=retry_of,
        terminal=sorted(TERMINAL),
    )


@router.get("/models")
def models_page(request: Request, session: PageSession, db: DbDep) -> Response:
    lineages = page_data.lineages(db)
    return _page(
        request,
        "models.html",
        session,
        active="models",
        lineages=lineages,
        scenes_of={lin.name: page_data.evaluated_scenes(lin.versions) for lin in lineages},
    )


@router.get("/continual")
def continual_page(
    request: Request,
    session: PageSession,
    db: DbDep,
    lineage: Annotated[ParamText | None, Query(max_length=128)] = None,
    split: Annotated[Literal["val", "train", "all"], Query()] = "val",
) -> Response:
    names = [lin.name for lin in page_data.lineages(db)]
    metrics = page_data.continual_metrics(db, lineage or None, split)
    return _page(
        request,
        "continual.html",
        session,
        active="continual",
        metrics=metrics,
        lineages=names,
        lineage=lineage,
        split=split,
    )


@router.get("/memory")
def memory_page(request: Request, session: PageSession, db: DbDep) -> Response:
    summary = page_data.memory_summary(db, request.app.state.model_cache)
    return _page(request, "memory.html", session, active="memory", summary=summary)


@router.get("/try")
def try_page(request: Request, session: PageSession, db: DbDep) -> Response:
    return _page(
        request,
        "try.html",
        session,
        active="try",
        model=models.current_model_out(db),
        seg_reason=capabilities.missing_reason("seg"),
        nerf_reason=capabilities.missing_reason("nerf"),
        # Renders need operator; a device key's page offers predictions only.
        nerf_scenes=page_data.nerf_scenes(db) if session.principal.allows(OPERATOR) else [],
    )


@router.get("/work")
def work_page(request: Request, session: PageSession, db: DbDep) -> Response:
    kinds = {k.kind: k for k in jobs.list_kinds()}
    presets: list[str] = []
    if kinds["adapt"].available:
        from csa_core.adapt.config import PRESETS

        presets = list(PRESETS)
    return _page(
        request,
        "work.html",
        session,
        active="work",
        scenes=scenes.all_scenes(db),
        kinds=kinds,
        model=models.current_model_out(db),
        adapt_presets=presets,
    )


@router.get("/audit")
def audit_page(
    request: Request,
    session: PageSession,
    db: DbDep,
    key_name: Annotated[ParamText | None, Query(max_length=64)] = None,
    page: Annotated[int, Query(ge=0, le=100_000)] = 0,
) -> Response:
    """The audit log, newest first, for admin keys (the route /api/v1/audit answers the same)."""
    entries, total = audit.entries_page(
        db, key_name or None, offset=page * AUDIT_PER_PAGE, limit=AUDIT_PER_PAGE
    )
    return _page(
        request,
        "audit.html",
        session,
        active="audit",
        entries=entries,
        key_name=key_name or "",
        page=page,
        pages=max(1, math.ceil(total / AUDIT_PER_PAGE)),
        total=total,
    )


# -- pictures and actions for the pages ---------------------------------------------------


def _not_modified(request: Request, etag: str) -> bool:
    return etag in [t.strip() for t in request.headers.get("if-none-match", "").split(",")]


@router.get(
    "/img/scenes/{scene_ref}/frames/{name}/{panel}.png",
    response_class=Response,
    dependencies=[Depends(require_ui_session), DeviceScope, SceneAccess],
)
def frame_panel(
    request: Request,
    scene_ref: ParamText,
    name: ParamText,
    panel: panels.Panel,
    _: ApiSession,
    db: DbDep,
    services: ServicesDep,
) -> Response:
    """One picture of a stored frame: ``prediction`` (current model), ``pseudo`` (the NeRF's
    labels rendered at the frame's pose), ``truth`` (uploaded labels) or ``overlay``."""
    frame = frames.get_frame(db, scene_ref, name)
    src = panels.panel_source(db, frame.scene, frame, panel)
    db.close()
    headers = {"ETag": src.etag, "Cache-Control": "private, no-cache"}
    if _not_modified(request, src.etag):
        return Response(status_code=status.HTTP_304_NOT_MODIFIED, headers=headers)
    state = request.app.state
    maps = _app_object(request, "ui_label_maps", panels.LabelMaps)
    body = panels.draw_panel(src, services.store, state.model_cache, state.nerf_cache, maps)
    return Response(body, media_type="image/png", headers=headers)


@router.get(
    "/img/continual.png",
    response_class=Response,
    dependencies=[Depends(require_ui_session), OperatorScope],
)
def continual_plot(
    _: ApiSession,
    db: DbDep,
    lineage: Annotated[ParamText | None, Query(max_length=128)] = None,
    split: Annotated[Literal["val", "train", "all"], Query()] = "val",
) -> Response:
    metrics = page_data.continual_metrics(db, lineage or None, split)
    if metrics is None or not metrics.steps:
        raise not_found("adaptation steps of lineage", lineage or "current")
    return Response(
        page_data.miou_per_step_png(metrics),
        media_type="image/png",
        headers={"Cache-Control": "private, no-store"},
    )


@router.post("/api/predict-preview", dependencies=[Depends(require_ui_session), DeviceScope])
async def predict_preview(
    request: Request,
    _: ApiSession,
    db: DbDep,
    services: ServicesDep,
    image: Annotated[UploadFile, File()],
) -> dict[str, Any]:
    """The current model's labels of an uploaded image as overlay, colours and legend."""
    limit = services.settings.max_inference_upload_bytes
    data = await image.read(limit + 1)
    if len(data) > limit:
        raise too_large("image", limit)
    return await run_in_threadpool(
        panels.predict_preview,
        db,
        request.app.state.model_cache,
        data,
        services.settings.max_image_pixels,
    )


@router.post(
    "/api/jobs/{job_id}/retry",
    status_code=status.HTTP_202_ACCEPTED,
    dependencies=[Depends(require_ui_session), OperatorScope],
)
def retry_job(job_id: JobId, _: ApiSession, db: DbDep) -> JobOut:
    """Queue a failed (or cancelled) job again: a new job of the same kind with the same
    resolved parameters; both logs name the other."""
    return jobs.retry_job(db, job_id)
