"""The long-term memory: one Semantic-NeRF checkpoint per visited scene.

:class:`NerfMemory` is what a continual step needs of a memory bank (the scenes, a scene's
NeRF, adding one, the sizes); :class:`MemoryBank` keeps it in one folder, the service keeps
it in its artifact store. In the folder, each scene is a safetensors file written by
``csa_core.nerf.checkpoint`` (tensors plus JSON metadata, never pickled); ``index.json`` lists the
scenes in the order they were added with the size of each file, which is the per-scene memory
footprint (docs/method.md "Protocols and metrics").
"""

from __future__ import annotations

import json
import re
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Protocol

from csa_core.atomic_io import write_text_atomic
from csa_core.errors import CSAInputError
from csa_core.nerf.checkpoint import load_checkpoint, save_checkpoint
from csa_core.nerf.model import SemanticNerf

INDEX = "index.json"


class NerfMemory(Protocol):
    """A memory bank as a continual step uses it (:mod:`csa_core.adapt.step`)."""

    @property
    def scenes(self) -> list[str]:
        """Scene names, oldest first."""
        ...

    def load(self, scene: str, device: str | None = "cpu") -> SemanticNerf:
        """The NeRF remembered for ``scene``, as stored (read back from its checkpoint), on
        ``device`` (``None``/``"auto"``: CUDA when present)."""
        ...

    def add(self, scene: str, nerf: SemanticNerf) -> object:
        """Store ``nerf`` as the memory of ``scene`` (replacing an earlier one of that name)."""
        ...

    def bytes_per_scene(self) -> dict[str, int]:
        """Stored size of each scene's NeRF."""
        ...


@dataclass(frozen=True)
class BankEntry:
    """One remembered scene: its name, checkpoint file (relative to the bank) and size."""

    scene: str
    file: str
    bytes: int


def _file_name(scene: str, taken: set[str]) -> str:
    stem = re.sub(r"[^A-Za-z0-9_.-]+", "_", scene).strip("._") or "scene"
    name, k = f"{stem}.safetensors", 1
    while name in taken:
        name, k = f"{stem}_{k}.safetensors", k + 1
    return name


class MemoryBank:
    """NeRF checkpoints of earlier scenes in ``folder`` (created on first use)."""

    def __init__(self, folder: str | Path):
        self.folder = Path(folder)
        self._entries: list[BankEntry] = []
        index = self.folder / INDEX
        if index.is_file():
            try:
                data = json.loads(index.read_text())
                self._entries = [BankEntry(**e) for e in data["scenes"]]
            except (ValueError, KeyError, TypeError) as e:
                raise CSAInputError(index, f"not a readable memory-bank index ({e})") from None

    @property
    def scenes(self) -> list[str]:
        """Scene names, oldest first."""
        return [e.scene for e in self._entries]

    @property
    def entries(self) -> list[BankEntry]:
        return list(self._entries)

    def __len__(self) -> int:
        return len(self._entries)

    def __contains__(self, scene: object) -> bool:
        return scene in self.scenes

    def add(self, scene: str, nerf: SemanticNerf) -> BankEntry:
        """Store ``nerf`` as the memory of ``scene`` (replacing an earlier one of that name)."""
        kept = [e for e in self._entries if e.scene != scene]
        old = next((e for e in self._entries if e.scene == scene), None)
        name = old.file if old is not None else _file_name(scene, {e.file for e in kept})
        size = save_checkpoint(nerf, self.folder / name)
        entry = BankEntry(scene=scene, file=name, bytes=int(size))
        self._entries = (
            [*kept, entry]
            if old is None
            else [entry if e.scene == scene else e for e in self._entries]
        )
        self._write_index()
        return entry

    def load(self, scene: str, device: str | None = "cpu") -> SemanticNerf:
        """The NeRF remembered for ``scene``."""
        entry = next((e for e in self._entries if e.scene == scene), None)
        if entry is None:
            raise CSAInputError(
                self.folder,
                f"no scene {scene!r} in the memory bank (have: {', '.join(self.scenes) or 'none'})",
            )
        return load_checkpoint(self.folder / entry.file, device=device)

    def bytes_per_scene(self) -> dict[str, int]:
        return {e.scene: e.bytes for e in self._entries}

    def total_bytes(self) -> int:
        return sum(e.bytes for e in self._entries)

    def _write_index(self) -> None:
        self.folder.mkdir(parents=True, exist_ok=True)
        doc = {
            "format": "csa-memory-bank",
            "version": 1,
            "scenes": [asdict(e) for e in self._entries],
        }
        write_text_atomic(self.folder / INDEX, json.dumps(doc, indent=2) + "\n")
