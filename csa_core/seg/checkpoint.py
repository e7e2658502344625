"""Segmentation checkpoints: safetensors weights plus a JSON model card in the file header.

One file is enough to rebuild the network: the card names the architecture, the classes, the
input normalisation and how the weights were made (training config, parent checkpoint,
lineage, scores). Loading never unpickles anything.
"""

from __future__ import annotations

import hashlib
import json
import math
from dataclasses import asdict, dataclass, field, fields
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

import torch
from safetensors.torch import save_file
from torch import Tensor

from csa_core.atomic_io import atomic_file
from csa_core.data.nyu40 import CLASS_NAMES, NUM_CLASSES
from csa_core.errors import CSAInputError
from csa_core.seg.models import ARCHS, IMAGENET_MEAN, IMAGENET_STD, SegmentationNet, build_model
from csa_core.seg.safetensors_io import read_safetensors, read_safetensors_header

FORMAT = "csa-seg-checkpoint/1"
_HEADER_KEY = "csa"
# Lists and objects nest at most this deep in a card (ours nest a few levels): a card is read
# from a file anyone may have written, and JSON nested about as deep as Python's recursion
# limit fails to parse with RecursionError, or parses and then fails wherever it is encoded.
MAX_CARD_DEPTH = 32
# A card is at most this many bytes of JSON (ours hold a few KB: the lineage grows by one id
# per adaptation step). Its metrics are stored with a registered version and sent in every
# listing of the models, so a card stuffed with megabytes would weigh on each of them.
MAX_CARD_BYTES = 1 << 20
# How a safetensors header names the dtypes of torch tensors.
_DTYPE_NAMES = {
    torch.float64: "F64",
    torch.float32: "F32",
    torch.float16: "F16",
    torch.bfloat16: "BF16",
    torch.int64: "I64",
    torch.int32: "I32",
    torch.int16: "I16",
    torch.int8: "I8",
    torch.uint8: "U8",
    torch.bool: "BOOL",
}


@dataclass
class ModelCard:
    """What a checkpoint says about its network; everything needed to rebuild and use it.

    ``class_names[k]`` names output channel ``k`` (NYU40 id ``k + 1``). ``input_size`` is
    the (width, height) the network was trained at, a sensible default for inference.
    ``parent`` identifies the checkpoint this one was trained from (its ``weights_id`` or
    path) and ``lineage`` the chain of ancestors, oldest first.
    """

    arch: str
    num_classes: int = NUM_CLASSES
    class_names: list[str] = field(default_factory=lambda: list(CLASS_NAMES[1:]))
    mean: list[float] = field(default_factory=lambda: list(IMAGENET_MEAN))
    std: list[float] = field(default_factory=lambda: list(IMAGENET_STD))
    input_size: list[int] | None = None
    train_config: dict[str, Any] = field(default_factory=dict)
    metrics: dict[str, Any] = field(default_factory=dict)
    parent: str | None = None
    lineage: list[str] = field(default_factory=list)
    created: str = ""
    weights_id: str = ""
    format: str = FORMAT

    @classmethod
    def for_model(cls, model: SegmentationNet, **values: Any) -> ModelCard:
        """A card describing ``model``; ``values`` fill the remaining fields."""
        mean, std = model.normalization
        return cls(
            arch=model.arch, num_classes=model.num_classes, mean=list(mean), std=list(std), **values
        )

    def child(self, **values: Any) -> ModelCard:
        """Card of a network trained from this one: same architecture, classes and input, with
        ``parent`` set to this card's ``weights_id`` and the lineage extended; ``values``
        fill the rest (typically ``train_config`` and ``metrics``)."""
        base = {f.name: getattr(self, f.name) for f in fields(self)}
        base.update(train_config={}, metrics={}, created="", weights_id="")
        base.update(
            parent=self.weights_id or None,
            lineage=[*self.lineage, self.weights_id] if self.weights_id else list(self.lineage),
        )
        return ModelCard(**{**base, **values})

    def to_json(self) -> str:
        text = json.dumps(asdict(self), sort_keys=True, default=_jsonable)
        if len(text.encode()) > MAX_CARD_BYTES:
            raise ValueError(
                f"model card of {len(text.encode())} bytes: more than the {MAX_CARD_BYTES} a card "
                "may hold"
            )
        return text

    @classmethod
    def from_json(cls, text: str) -> ModelCard:
        size = len(text.encode(errors="replace"))
        if size > MAX_CARD_BYTES:
            raise ValueError(
                f"{size} bytes of JSON, more than the {MAX_CARD_BYTES} a card may hold"
            )
        try:
            data = json.loads(text)
        except RecursionError:
            raise ValueError(
                f"lists and objects nest more than {MAX_CARD_DEPTH} levels deep"
            ) from None
        if _depth(data) > MAX_CARD_DEPTH:
            raise ValueError(f"lists and objects nest more than {MAX_CARD_DEPTH} levels deep")
        if not isinstance(data, dict):
            raise ValueError("model card is not a JSON object")
        known = {f.name for f in fields(cls)}
        return cls(**{k: v for k, v in data.items() if k in known})


def _depth(value: Any) -> int:
    """How deeply lists and objects nest in parsed JSON (without recursion: any depth)."""
    deepest, todo = 0, [(value, 1)]
    while todo:
        item, level = todo.pop()
        children = (
            item.values() if isinstance(item, dict) else item if isinstance(item, list) else None
        )
        if children is not None:
            deepest = max(deepest, level)
            todo.extend((child, level + 1) for child in children)
    return deepest


def _jsonable(value: Any) -> Any:
    if isinstance(value, Path):
        return str(value)
    if isinstance(value, tuple | set):
        return list(value)
    raise TypeError(f"not JSON-serialisable: {type(value).__name__}")


def weights_id(tensors: dict[str, Tensor]) -> str:
    """Short content hash of a state dict (names, dtypes, shapes and bytes)."""
    h = hashlib.sha256()
    for name in sorted(tensors):
        t = tensors[name].detach().cpu().contiguous()
        h.update(f"{name}|{t.dtype}|{tuple(t.shape)}|".encode())
        h.update(t.reshape(-1).view(torch.uint8).numpy().tobytes())
    return h.hexdigest()[:16]


def save_checkpoint(
    path: str | Path, model: SegmentationNet, card: ModelCard | None = None
) -> ModelCard:
    """Write ``model`` and its card to ``path`` atomically; returns the card as written.

    The card's ``arch``, ``num_classes`` and normalisation are taken from the model, and
    ``created`` and ``weights_id`` are filled in.
    """
    tensors = {k: v.detach().cpu().contiguous() for k, v in model.state_dict().items()}
    card = card if card is not None else ModelCard(arch=model.arch)
    mean, std = model.normalization
    written = ModelCard(
        **{
            **asdict(card),
            "arch": model.arch,
            "num_classes": model.num_classes,
            "mean": list(mean),
            "std": list(std),
            "created": datetime.now(UTC).isoformat(timespec="seconds"),
            "weights_id": weights_id(tensors),
        }
    )
    if len(written.class_names) != written.num_classes:
        raise ValueError(
            f"save_checkpoint: {len(written.class_names)} class names for {written.num_classes} "
            "outputs"
        )
    metadata = {_HEADER_KEY: written.to_json()}  # refuses an oversized card before any file
    with atomic_file(path) as tmp:
        save_file(tensors, str(tmp), metadata=metadata)
    return written


def read_model_card(path: str | Path) -> ModelCard:
    """The card of a checkpoint, without building the network or reading its tensors."""
    _, metadata = read_safetensors_header(path)
    return _card_from_metadata(path, metadata)


def _card_from_metadata(path: str | Path, metadata: dict[str, str]) -> ModelCard:
    if _HEADER_KEY not in metadata:
        raise CSAInputError(
            path, "safetensors file without a CSA model card (not a CSA segmentation checkpoint)"
        )
    try:
        card = ModelCard.from_json(metadata[_HEADER_KEY])
    except (ValueError, TypeError) as e:
        raise CSAInputError(path, f"model card is not valid ({e})") from None
    if card.format != FORMAT:
        raise CSAInputError(
            path, f"unsupported checkpoint format {card.format!r} (expected {FORMAT})"
        )
    if not isinstance(card.arch, str) or card.arch not in ARCHS:
        raise CSAInputError(path, f"unknown architecture {card.arch!r} (known: {', '.join(ARCHS)})")
    _check_card_fields(path, card)
    return card


def _is_number(v: Any) -> bool:
    return isinstance(v, int | float) and not isinstance(v, bool) and math.isfinite(v)


def _check_card_fields(path: str | Path, card: ModelCard) -> None:
    """The card's fields have the types and ranges the code that uses them relies on (a card is
    read from a file anyone may have written): a :class:`CSAInputError` naming the field."""
    n = card.num_classes
    if not isinstance(n, int) or isinstance(n, bool) or not 1 <= n <= NUM_CLASSES:
        raise CSAInputError(
            path,
            f"model card: num_classes must be an integer within 1..{NUM_CLASSES} (NYU40 ids), got "
            f"{n!r}",
        )
    if not (
        isinstance(card.class_names, list)
        and len(card.class_names) == n
        and all(isinstance(c, str) for c in card.class_names)
    ):
        raise CSAInputError(
            path, f"model card: class_names must be a list of {n} names (one per class)"
        )
    for name in ("mean", "std"):
        values = getattr(card, name)
        if not (
            isinstance(values, list) and len(values) == 3 and all(_is_number(v) for v in values)
        ):
            raise CSAInputError(
                path, f"model card: {name} must be a list of 3 finite numbers, got {values!r}"[:300]
            )
    if min(card.std) <= 0:
        raise CSAInputError(path, "model card: std entries must be > 0")
    size = card.input_size
    if size is not None and not (
        isinstance(size, list) and len(size) == 2 and all(type(v) is int and v >= 1 for v in size)
    ):
        raise CSAInputError(
            path, f"model card: input_size must be [width, height], got {size!r}"[:300]
        )
    for name in ("train_config", "metrics"):
        if not isinstance(getattr(card, name), dict):
            raise CSAInputError(path, f"model card: {name} must be a JSON object")
    if not (isinstance(card.lineage, list) and all(isinstance(v, str) for v in card.lineage)):
        raise CSAInputError(path, "model card: lineage must be a list of strings")
    for name in ("created", "weights_id"):
        if not isinstance(getattr(card, name), str):
            raise CSAInputError(path, f"model card: {name} must be a string")
    if card.parent is not None and not isinstance(card.parent, str):
        raise CSAInputError(path, "model card: parent must be a string or null")


def load_checkpoint(
    path: str | Path, device: str | torch.device = "cpu"
) -> tuple[SegmentationNet, ModelCard]:
    """Rebuild the network stored at ``path``; returns it in eval mode on ``device`` with its card.

    A missing, truncated or foreign file, or weights that do not fit the card's architecture,
    raise :class:`CSAInputError` naming the file; names, dtypes and shapes are checked from
    the header, before any tensor is read.
    """
    layout, metadata = read_safetensors_header(path)
    card = _card_from_metadata(path, metadata)
    model = build_model(card.arch, num_classes=card.num_classes, mean=card.mean, std=card.std)
    expected = {
        k: (_DTYPE_NAMES.get(v.dtype, str(v.dtype)), tuple(v.shape))
        for k, v in model.state_dict().items()
    }
    missing = sorted(set(expected) - set(layout))
    unexpected = sorted(set(layout) - set(expected))
    if missing or unexpected:
        detail = f"missing {missing[:3]}" if missing else f"unexpected {unexpected[:3]}"
        raise CSAInputError(path, f"weights do not match {card.arch}: {detail}")
    wrong = [k for k, v in layout.items() if v != expected[k]]
    if wrong:
        k = wrong[0]
        raise CSAInputError(
            path,
            f"tensor {k} is {layout[k][0]} {layout[k][1]}, {card.arch} needs {expected[k][0]} "
            f"{expected[k][1]}",
        )
    # The header matches the network: only now are the tensors read.
    tensors, _ = read_safetensors(path)
    model.load_state_dict(tensors)
    return model.to(device).eval(), card
