"""``CSAClient``: the CSA service over HTTP, with typed results and readable errors."""

from __future__ import annotations

import base64
import json
import os
import tarfile
import tempfile
import time
from collections.abc import Callable, Iterator, Sequence
from pathlib import Path
from typing import Any, TypeVar
from urllib.parse import quote

import httpx
from pydantic import BaseModel, TypeAdapter

from client.errors import (
    CSAConnectionError,
    CSAError,
    CSAHTTPError,
    CSATimeout,
    JobFailed,
    NotFound,
    error_for_status,
)
from client.models import (
    ArchiveUpload,
    ContinualMetrics,
    Frame,
    FrameUpload,
    Health,
    Job,
    JobKind,
    LogLine,
    MemoryBank,
    ModelVersion,
    Nerf,
    Prediction,
    Rendering,
    Scene,
)

API = "/api/v1"
TOTAL_COUNT_HEADER = "X-Total-Count"  # the number of rows of a paged list, all pages together
T = TypeVar("T")
FileLike = str | os.PathLike[str] | bytes

# What a scene folder upload sends: the data contract's folders (other label folders stay home).
SCENE_FOLDERS = ("color", "depth", "pose", "intrinsic", "label-nyu40")


def _ref(ref: str | int) -> str:
    """A scene or model reference as one URL path segment."""
    return quote(str(ref), safe="")


def _file(value: FileLike, default_name: str) -> tuple[str, bytes]:
    if isinstance(value, bytes):
        return default_name, value
    p = Path(value)
    return p.name, p.read_bytes()


def _pose_text(pose: FileLike | Sequence[Sequence[float]]) -> bytes:
    if isinstance(pose, bytes):
        return pose
    if isinstance(pose, str | os.PathLike):
        return Path(pose).read_bytes()
    return "\n".join(" ".join(repr(float(v)) for v in row) for row in pose).encode()


class CSAClient:
    """A client of one CSA server.

    ``timeout`` bounds ordinary requests; ``upload_timeout`` uploads and downloads, which
    can be large. Errors raise :class:`client.errors.CSAError` subclasses whose message
    carries the server's explanation (and the field at fault).

    The lists of scenes, frames and model versions are read a page of ``page_size`` rows at a
    time (the server answers at most 1000 a request) and returned whole.
    """

    page_size = 1000  # rows a request of a paged list; the server's maximum

    def __init__(
        self,
        base_url: str | None = None,
        api_key: str | None = None,
        timeout: float = 30.0,
        upload_timeout: float = 600.0,
        transport: httpx.BaseTransport | None = None,
    ):
        url = base_url or os.environ.get("CSA_URL") or "http://127.0.0.1:8000"
        self.base_url = url.rstrip("/")
        key = api_key if api_key is not None else os.environ.get("CSA_API_KEY")
        headers = {"X-API-Key": key} if key else {}
        self.timeout = httpx.Timeout(timeout, connect=min(timeout, 10.0))
        self.upload_timeout = httpx.Timeout(upload_timeout, connect=min(timeout, 10.0))
        self._http = httpx.Client(
            base_url=self.base_url, headers=headers, timeout=self.timeout, transport=transport
        )

    def close(self) -> None:
        self._http.close()

    def __enter__(self) -> CSAClient:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    # -- the one place that turns HTTP into results or errors ----------------------------

    def _request(self, method: str, path: str, **kwargs: Any) -> httpx.Response:
        try:
            response = self._http.request(method, path, **kwargs)
        except httpx.TimeoutException as e:
            raise CSATimeout(
                f"{method} {self.base_url}{path}: no answer in time ({type(e).__name__})"
            ) from None
        except httpx.TransportError as e:
            raise CSAConnectionError(
                f"{method} {self.base_url}{path}: cannot reach the server ({e})"
            ) from None
        if response.status_code >= 400:
            raise self._error(response)
        return response

    @staticmethod
    def _error(response: httpx.Response) -> CSAHTTPError:
        code, field = "http_error", None
        message = response.reason_phrase or "error"
        try:
            body = response.json()
            err = body.get("error") if isinstance(body, dict) else None
            if isinstance(err, dict):
                code, message, field = (
                    err.get("code", code),
                    err.get("message", message),
                    err.get("field"),
                )
            elif isinstance(body, dict) and "detail" in body:
                message = str(body["detail"])
        except (ValueError, json.JSONDecodeError):
            text = response.text.strip()
            if text:
                message = text[:300]
        cls = error_for_status(response.status_code)
        return cls(
            response.status_code,
            message,
            code=code,
            field=field,
            method=response.request.method,
            url=str(response.request.url),
        )

    def _json(self, method: str, path: str, model: type[T] | Any, **kwargs: Any) -> T:
        data = self._request(method, path, **kwargs).json()
        if isinstance(model, type) and issubclass(model, BaseModel):
            return model.model_validate(data)  # type: ignore[return-value]
        return TypeAdapter(model).validate_python(data)

    def _all_pages(
        self, path: str, model: type[T], params: dict[str, Any] | None = None
    ) -> list[T]:
        """Every row of a paged list route, ``page_size`` rows a request. Each full page's
        ``Link: <...>; rel="next"`` names the cursor (``after``) the next request starts from,
        so rows added or deleted meanwhile neither shift nor repeat the rows read (only the
        cursor is taken from the link: the request goes to this client's own base URL). A
        server without cursors is read by ``offset`` until the total in ``X-Total-Count`` is
        read or a page comes back short (rows created or deleted meanwhile may then be missed
        or read twice); one without pages (no ``X-Total-Count``) answered the whole list."""
        adapter = TypeAdapter(list[model])  # type: ignore[valid-type]
        rows: list[T] = []
        after: str | None = None
        while True:
            where = {"after": after} if after is not None else {"offset": len(rows)}
            response = self._request(
                "GET", path, params={**(params or {}), "limit": self.page_size, **where}
            )
            batch = adapter.validate_python(response.json())
            rows += batch
            after = httpx.URL(response.links.get("next", {}).get("url", "")).params.get("after")
            if after is not None and batch:
                continue
            total = response.headers.get(TOTAL_COUNT_HEADER, "")
            if not total.isdigit() or len(batch) < self.page_size or len(rows) >= int(total):
                return rows

    # -- service -------------------------------------------------------------------------

    def health(self) -> Health:
        return self._json("GET", "/health", Health)

    # -- scenes and frames ---------------------------------------------------------------

    def scenes(self) -> list[Scene]:
        return self._all_pages(f"{API}/scenes", Scene)

    def scene(self, ref: str | int) -> Scene:
        return self._json("GET", f"{API}/scenes/{_ref(ref)}", Scene)

    def create_scene(self, name: str, description: str = "") -> Scene:
        return self._json(
            "POST", f"{API}/scenes", Scene, json={"name": name, "description": description}
        )

    def ensure_scene(self, name: str) -> Scene:
        """The scene of this name, created if needed."""
        try:
            return self.scene(name)
        except NotFound:
            return self.create_scene(name)

    def delete_scene(self, ref: str | int) -> None:
        self._request("DELETE", f"{API}/scenes/{_ref(ref)}")

    def frames(self, scene: str | int) -> list[Frame]:
        return self._all_pages(f"{API}/scenes/{_ref(scene)}/frames", Frame)

    def upload_frame(
        self,
        scene: str | int,
        color: FileLike,
        depth: FileLike,
        pose: FileLike | Sequence[Sequence[float]],
        intrinsics: FileLike | None = None,
        labels: FileLike | None = None,
        name: str | None = None,
        replace: bool = False,
        depth_intrinsics: FileLike | None = None,
    ) -> FrameUpload:
        """Upload one frame (files or bytes; the pose may also be a 4x4 nested list).
        Uploading the same content again returns the stored frame with ``created=False``."""
        files: dict[str, tuple[str, bytes]] = {
            "color": _file(color, "color.png"),
            "depth": _file(depth, "depth.png"),
            "pose": ("pose.txt", _pose_text(pose)),
        }
        for key, value in (
            ("intrinsics", intrinsics),
            ("labels", labels),
            ("depth_intrinsics", depth_intrinsics),
        ):
            if value is not None:
                files[key] = _file(value, f"{key}.txt" if "intrinsics" in key else f"{key}.png")
        data: dict[str, str] = {"replace": "true" if replace else "false"}
        if name is not None:
            data["name"] = name
        return self._json(
            "POST",
            f"{API}/scenes/{_ref(scene)}/frames",
            FrameUpload,
            files=files,
            data=data,
            timeout=self.upload_timeout,
        )

    def upload_archive(
        self, scene: str | int, archive: str | os.PathLike[str], replace: bool = False
    ) -> ArchiveUpload:
        """Upload a tar or zip of a scene folder (all frames are stored, or none)."""
        with open(archive, "rb") as f:
            return self._json(
                "POST",
                f"{API}/scenes/{_ref(scene)}/archive",
                ArchiveUpload,
                files={"archive": (Path(archive).name, f)},
                data={"replace": "true" if replace else "false"},
                timeout=self.upload_timeout,
            )

    def upload_scene_folder(
        self, folder: str | os.PathLike[str], scene: str | None = None, replace: bool = False
    ) -> tuple[Scene, ArchiveUpload]:
        """Create the scene (named after the folder unless ``scene``) and upload the folder as
        one archive: colour, depth, poses, intrinsics and ``label-nyu40`` ground truth if any."""
        root = Path(folder)
        if not (root / "color").is_dir():
            raise CSAError(f"{root}: not a scene folder (no color/ inside)")
        target = self.ensure_scene(scene or root.name)
        with tempfile.TemporaryDirectory(prefix="csa-upload-") as d:
            tar_path = Path(d) / f"{root.name}.tar"
            with tarfile.open(tar_path, "w") as tf:
                for sub in SCENE_FOLDERS:
                    src = root / sub
                    if not src.is_dir():
                        continue
                    for p in sorted(src.iterdir()):
                        if p.is_file() and not p.is_symlink() and not p.name.startswith("."):
                            tf.add(p, arcname=f"{sub}/{p.name}", recursive=False)
            result = self.upload_archive(target.id, tar_path, replace=replace)
        return self.scene(target.id), result

    # -- jobs ----------------------------------------------------------------------------

    def job_kinds(self) -> list[JobKind]:
        return self._json("GET", f"{API}/jobs/kinds", list[JobKind])

    def create_job(self, kind: str, **params: Any) -> Job:
        body = {"kind": kind, "params": {k: v for k, v in params.items() if v is not None}}
        return self._json("POST", f"{API}/jobs", Job, json=body)

    def fit_nerf(
        self,
        scene: str | int,
        labels: str = "predictions",
        preset: str = "fast",
        steps: int | None = None,
        model: str | int | None = None,
    ) -> Job:
        return self.create_job(
            "fit_nerf", scene=scene, labels=labels, preset=preset, steps=steps, model=model
        )

    def adapt(
        self,
        scene: str | int,
        model: str | int | None = None,
        preset: str = "cpu",
        mode: str | None = None,
    ) -> Job:
        """Queue a continual step: adapt the lineage's newest version (``model`` selects the
        lineage; default the current model's) to ``scene``."""
        return self.create_job("adapt", scene=scene, model=model, preset=preset, mode=mode)

    def evaluate(
        self,
        model: str | int | None = None,
        scenes: Sequence[str | int] | None = None,
        split: str = "val",
    ) -> Job:
        return self.create_job(
            "evaluate",
            model=model,
            scenes=list(scenes) if scenes is not None else None,
            split=split,
        )

    def pretrain(self, scenes: Sequence[str | int], **params: Any) -> Job:
        return self.create_job("pretrain", scenes=list(scenes), **params)

    def job(self, job_id: int) -> Job:
        return self._json("GET", f"{API}/jobs/{job_id}", Job)

    def jobs(
        self, status: str | None = None, kind: str | None = None, limit: int = 100
    ) -> list[Job]:
        params = {
            k: v
            for k, v in {"status": status, "kind": kind, "limit": limit}.items()
            if v is not None
        }
        return self._json("GET", f"{API}/jobs", list[Job], params=params)

    def job_log(self, job_id: int, tail: int = 100) -> list[LogLine]:
        response = self._request("GET", f"{API}/jobs/{job_id}/log", params={"tail": tail})
        return [LogLine.model_validate(x) for x in response.json()["lines"]]

    def cancel_job(self, job_id: int) -> Job:
        return self._json("POST", f"{API}/jobs/{job_id}/cancel", Job)

    def watch_job(self, job_id: int, timeout: float | None = None) -> Iterator[Job]:
        """Yield the job each time it changes (server-sent events), until it ends."""
        deadline = None if timeout is None else time.monotonic() + timeout
        while True:
            remaining = None if deadline is None else max(0.0, deadline - time.monotonic())
            if remaining == 0.0:
                raise CSATimeout(f"job {job_id} did not finish within {timeout:g} s")
            read_timeout = 30.0 if remaining is None else min(30.0, remaining)
            try:
                with self._http.stream(
                    "GET",
                    f"{API}/jobs/{job_id}/events",
                    timeout=httpx.Timeout(self.timeout.connect, read=read_timeout),
                ) as response:
                    if response.status_code >= 400:
                        response.read()
                        raise self._error(response)
                    event = None
                    for line in response.iter_lines():
                        if line.startswith("event:"):
                            event = line[6:].strip()
                        elif line.startswith("data:") and event == "progress":
                            job = Job.model_validate_json(line[5:].strip())
                            yield job
                            if job.done:
                                return
                        elif line.startswith("data:") and event == "end":
                            yield self.job(job_id)
                            return
            except httpx.TimeoutException:
                continue  # no change for a while: reconnect
            except httpx.TransportError as e:
                raise CSAConnectionError(f"job {job_id} event stream: {e}") from None
            job = self.job(job_id)
            if job.done:
                yield job
                return

    def wait_job(
        self,
        job_id: int,
        timeout: float | None = None,
        on_progress: Callable[[Job], None] | None = None,
        raise_on_failure: bool = True,
    ) -> Job:
        """Block until the job ends; raises :class:`JobFailed` if it failed or was cancelled."""
        job = self.job(job_id)
        for job in self.watch_job(job_id, timeout=timeout):
            if on_progress is not None:
                on_progress(job)
        if raise_on_failure and job.status != "succeeded":
            raise JobFailed(job)
        return job

    # -- models, memory bank, metrics ----------------------------------------------------

    def models(self, lineage: str | None = None) -> list[ModelVersion]:
        return self._all_pages(
            f"{API}/models", ModelVersion, params={"lineage": lineage} if lineage else None
        )

    def model(self, ref: str | int = "current") -> ModelVersion:
        return self._json("GET", f"{API}/models/{_ref(ref)}", ModelVersion)

    def set_current_model(self, ref: str | int) -> ModelVersion:
        return self._json("POST", f"{API}/models/{_ref(ref)}/current", ModelVersion)

    def register_model(
        self,
        checkpoint: str | os.PathLike[str],
        name: str,
        lineage: str | None = None,
        make_current: bool | None = None,
    ) -> ModelVersion:
        data = {"name": name}
        if lineage is not None:
            data["lineage"] = lineage
        if make_current is not None:
            data["make_current"] = "true" if make_current else "false"
        with open(checkpoint, "rb") as f:
            return self._json(
                "POST",
                f"{API}/models",
                ModelVersion,
                files={"checkpoint": (Path(checkpoint).name, f)},
                data=data,
                timeout=self.upload_timeout,
            )

    def download_model(self, ref: str | int, dest: str | os.PathLike[str]) -> Path:
        """Save a version's checkpoint to ``dest`` (written to a temporary name, then renamed)."""
        dest = Path(dest)
        tmp = dest.with_name(f".{dest.name}.part")
        try:
            with self._http.stream(
                "GET", f"{API}/models/{_ref(ref)}/download", timeout=self.upload_timeout
            ) as response:
                if response.status_code >= 400:
                    response.read()
                    raise self._error(response)
                with open(tmp, "wb") as f:
                    for chunk in response.iter_bytes():
                        f.write(chunk)
            os.replace(tmp, dest)
        except httpx.TransportError as e:
            raise CSAConnectionError(f"download of model {ref}: {e}") from None
        finally:
            tmp.unlink(missing_ok=True)
        return dest

    def memory(self) -> MemoryBank:
        return self._json("GET", f"{API}/memory", MemoryBank)

    def scene_nerf(self, scene: str | int) -> Nerf:
        return self._json("GET", f"{API}/memory/{_ref(scene)}", Nerf)

    def continual_metrics(self, lineage: str | None = None, split: str = "val") -> ContinualMetrics:
        params = {"split": split} | ({"lineage": lineage} if lineage else {})
        return self._json("GET", f"{API}/metrics/continual", ContinualMetrics, params=params)

    def prometheus_metrics(self) -> str:
        return self._request("GET", "/metrics").text

    # -- inference and rendering ---------------------------------------------------------

    def predict(
        self, image: FileLike, model: str | int | None = None, format: str = "ids"
    ) -> Prediction:
        """Label an image: PNG of uint8 NYU40 ids (``format="ids"``) or the palette picture."""
        data = {"format": format} | ({"model": str(model)} if model is not None else {})
        response = self._request(
            "POST",
            f"{API}/predict",
            files={"image": _file(image, "image.png")},
            data=data,
            timeout=self.upload_timeout,
        )
        return Prediction(
            png=response.content,
            model_id=int(response.headers.get("X-CSA-Model-Id", "0")),
            model=response.headers.get("X-CSA-Model", ""),
        )

    def render(
        self,
        scene: str | int,
        pose: Sequence[Sequence[float]],
        intrinsics: dict[str, float] | None = None,
        channels: Sequence[str] = ("color", "depth", "labels"),
        nerf_id: int | None = None,
    ) -> Rendering:
        body: dict[str, Any] = {
            "pose": [[float(v) for v in row] for row in pose],
            "channels": list(channels),
        }
        if intrinsics is not None:
            body["intrinsics"] = intrinsics
        if nerf_id is not None:
            body["nerf_id"] = nerf_id
        data = self._request(
            "POST", f"{API}/scenes/{_ref(scene)}/render", json=body, timeout=self.upload_timeout
        ).json()
        return Rendering(
            scene_id=data["scene_id"],
            nerf_id=data["nerf_id"],
            width=data["width"],
            height=data["height"],
            images={k: base64.b64decode(v) for k, v in data["images"].items()},
        )
