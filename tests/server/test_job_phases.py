"""The three phases of a job (``server/jobs/phases.py``): every kind's Inputs and Outputs are
plain dataclasses, and what the Ray executor does with them (files named by checksum go to
the task, Outputs come back as values with their files). Every kind run end to end through
both executors' phases: ``test_every_kind_runs_in_three_phases`` in test_ray_executor.py."""

from __future__ import annotations

import dataclasses
import hashlib
import inspect
import json
import types
from pathlib import Path
from typing import Any, Union, get_args, get_origin, get_type_hints

import pytest

from server.artifacts import ArtifactMissing, ArtifactStore
from server.jobs.context import JobCancelled, JobContext
from server.jobs.evaluate import EvaluateInputs
from server.jobs.fit_nerf import FitNerfOutputs
from server.jobs.inputs import FrameInput, ModelInput, SceneInput
from server.jobs.kinds import KINDS
from server.jobs.phases import (
    FileRef,
    check_plain,
    compute_outputs,
    function_path,
    leaves,
    resolve_function,
    stored_file,
)
from server.jobs.pretrain import PretrainOutputs
from tests.server.conftest import ResultOutputs

PLAIN_TYPES = (type(None), bool, int, float, str, Path)


def plain_type(tp: Any, where: str) -> None:
    """Fail unless the annotation ``tp`` is a plain value's type (``Any`` stands for a JSON
    value, checked on the values themselves by ``check_plain``)."""
    origin = get_origin(tp)
    if tp in PLAIN_TYPES or tp is Any:
        return
    if dataclasses.is_dataclass(tp):
        hints = get_type_hints(tp)
        for f in dataclasses.fields(tp):
            plain_type(hints[f.name], f"{where}.{f.name}")
    elif origin in (Union, types.UnionType, list, tuple):
        for arg in get_args(tp):
            if arg is not Ellipsis:
                plain_type(arg, where)
    elif origin is dict:
        key, value = get_args(tp)
        assert key is str, f"{where}: dictionary keys must be strings, not {key}"
        plain_type(value, where)
    else:
        pytest.fail(f"{where}: {tp} is not a plain value's type")


@pytest.mark.parametrize("name", sorted(KINDS))
def test_every_kinds_inputs_and_outputs_are_plain_dataclasses(name: str) -> None:
    kind = KINDS[name]
    compute = get_type_hints(kind.compute)
    first = next(iter(inspect.signature(kind.compute).parameters))
    inputs, outputs = compute[first], compute["return"]
    assert dataclasses.is_dataclass(inputs) and dataclasses.is_dataclass(outputs)
    plain_type(inputs, inputs.__name__)
    plain_type(outputs, outputs.__name__)
    # gather makes what compute takes; register takes what compute makes
    assert get_type_hints(kind.gather)["return"] is inputs
    register = get_type_hints(kind.register)
    assert register[list(inspect.signature(kind.register).parameters)[1]] is outputs
    # the compute phase travels to a Ray task by name
    assert resolve_function(function_path(kind.compute)) is kind.compute


def test_plain_values_are_checked_down_to_the_field() -> None:
    ref = FileRef(Path("/store/blobs/ab/ab"), "ab" * 32)
    frame = FrameInput("0", ".png", [[1.0, 0.0], [0.0, 1.0]], ref, ref, None)
    scene = SceneInput(3, "room", {"width": 40, "height": 30}, None, [frame])
    check_plain(scene)
    assert (
        json.loads(json.dumps(dataclasses.asdict(scene), default=str))["frames"][0]["color"][
            "sha256"
        ]
        == ref.sha256
    )
    with pytest.raises(TypeError, match=r"outputs\.result\['net'\]: a object is not a plain value"):
        check_plain(ResultOutputs({"net": object()}), "outputs")
    with pytest.raises(TypeError, match=r"value\.result: key 3 is a int, not a string"):
        check_plain(ResultOutputs({3: "x"}))
    with pytest.raises(TypeError, match="a bytes is not a plain value"):
        check_plain([b"raw"])


def test_only_module_level_functions_travel_by_name() -> None:
    def local(inputs, workdir, ctx):
        return None

    for function in (local, lambda i, w, c: None):
        with pytest.raises(ValueError, match="not a module-level function"):
            function_path(function)
    assert function_path(plain_type) == "tests.server.test_job_phases:plain_type"


def test_inputs_name_their_files_which_travel_by_checksum(tmp_path: Path) -> None:
    """The Ray executor reads every file an Inputs names (each once), and the task points the
    Inputs at its own copies; the API node's Inputs are left as they were."""
    from server.executors.remote import input_files, localize_inputs, read_input_files

    store = ArtifactStore(tmp_path / "store")
    blobs = {}
    for data in (b"colour" * 50, b"depth" * 50, b"checkpoint" * 50):
        sha = hashlib.sha256(data).hexdigest()
        store.path_of(sha).parent.mkdir(parents=True, exist_ok=True)
        store.path_of(sha).write_bytes(data)
        blobs[sha] = data
    color, depth, checkpoint = (stored_file(store, sha) for sha in blobs)
    frames = [FrameInput(str(i), ".png", [[1.0]], color, depth, None) for i in range(3)]
    inputs = EvaluateInputs(
        ModelInput(1, "base", "arch", {"model.safetensors": checkpoint}),
        [SceneInput(2, "room", {}, None, frames)],
        "val",
    )

    assert input_files(inputs) == {sha: store.path_of(sha) for sha in blobs}
    assert dict(read_input_files(inputs)) == blobs
    local = {sha: tmp_path / "task" / "inputs" / sha for sha in blobs}
    moved = localize_inputs(inputs, local)
    assert [ref.path for ref in leaves(moved, FileRef)] == [
        local[ref.sha256] for ref in leaves(inputs, FileRef)
    ]
    assert all(Path(ref.path).is_relative_to(store.root) for ref in leaves(inputs, FileRef))
    check_plain(moved)

    store.path_of(checkpoint.sha256).unlink()
    with pytest.raises(
        ArtifactMissing, match=f"artifact {checkpoint.sha256[:12]} is missing from the store"
    ):
        dict(read_input_files(inputs))


def test_outputs_come_back_as_values_and_files(tmp_path: Path) -> None:
    """What a task returns: its Outputs with paths relative to the job's folder and the files
    they name; the API node writes the files into its scratch folder, checked against their
    checksums, and points the Outputs there."""
    from server.executors.remote import pack_outputs, unpack_outputs

    workdir = tmp_path / "task" / "work"
    (workdir / "memory").mkdir(parents=True)
    (workdir / "memory" / "nerf.safetensors").write_bytes(b"weights" * 100)
    outputs = FitNerfOutputs(
        3, workdir / "memory" / "nerf.safetensors", "fast", "ground_truth", {"val_psnr": 20.5}
    )

    packed, files = pack_outputs(outputs, workdir)
    sha = hashlib.sha256(b"weights" * 100).hexdigest()
    assert packed == dataclasses.replace(outputs, nerf=Path("memory/nerf.safetensors"))
    assert files == {"memory/nerf.safetensors": (sha, b"weights" * 100)}

    folder = tmp_path / "api-scratch"
    restored = unpack_outputs(packed, files, folder)
    assert restored == dataclasses.replace(outputs, nerf=folder / "memory" / "nerf.safetensors")
    assert restored.nerf.read_bytes() == b"weights" * 100
    with pytest.raises(ValueError, match="stay inside the task folder"):
        unpack_outputs(packed, {"../escape": (sha, b"x")}, folder)
    with pytest.raises(OSError, match="arrived with a different checksum"):
        unpack_outputs(packed, {"memory/nerf.safetensors": (sha, b"changed")}, folder)
    with pytest.raises(ValueError, match="which the task did not send"):
        unpack_outputs(packed, {}, folder)


class Recording(JobContext):
    """A context that keeps what the job reports."""

    def __init__(self, workdir: Path):
        super().__init__(1, "test", workdir)
        self.sent: list[tuple[Any, ...]] = []

    @property
    def settings(self) -> Any:
        from server.executors.remote import JobSettings

        return JobSettings(device="cpu")

    def _send(self, progress, message, logs) -> None:
        self.sent.append((progress, message, logs))


def test_the_compute_phase_ends_with_plain_outputs_of_its_own_files(tmp_path: Path) -> None:
    workdir = tmp_path / "work"
    workdir.mkdir()
    (workdir / "model.safetensors").write_bytes(b"net")
    made = PretrainOutputs(workdir / "model.safetensors", "base", "arch", {}, {}, None)

    def compute_with(outputs: Any) -> Any:
        def compute(inputs: Any, workdir: Path, ctx: JobContext) -> Any:
            ctx.log("computed")
            return outputs

        return compute

    ctx = Recording(workdir)
    assert compute_outputs(compute_with(made), None, workdir, ctx) is made
    assert ctx.sent == [(None, None, [("INFO", "computed")])]  # its last log lines went first
    elsewhere = tmp_path / "elsewhere.safetensors"
    elsewhere.write_bytes(b"net")
    for outputs, error in (
        (dataclasses.replace(made, checkpoint=elsewhere), "not a file the job made in its folder"),
        (
            dataclasses.replace(made, checkpoint=workdir / "never-written"),
            "not a file the job made in its folder",
        ),
        (dataclasses.replace(made, metrics={"net": object()}), "a object is not a plain value"),
    ):
        with pytest.raises((ValueError, TypeError), match=error):
            compute_outputs(compute_with(outputs), None, workdir, Recording(workdir))
    cancelled = Recording(workdir)
    cancelled.cancel_requested.set()  # a cancel that arrives after the last check
    with pytest.raises(JobCancelled):
        compute_outputs(compute_with(made), None, workdir, cancelled)
