"""Checkpoints: bit-identical round trip, a model card that needs nothing but the file, clear
errors."""

from __future__ import annotations

import json
import struct

import pytest
import torch
from safetensors.torch import save_file

from csa_core.data.nyu40 import CLASS_NAMES
from csa_core.errors import CSAInputError
from csa_core.seg.checkpoint import ModelCard, load_checkpoint, read_model_card, save_checkpoint
from csa_core.seg.models import build_model


@pytest.fixture
def trained_like_model():
    torch.manual_seed(0)
    model = build_model()
    model.train()
    with torch.no_grad():  # move the BatchNorm statistics away from their initial values
        model(torch.rand(4, 3, 48, 64))
    return model.eval()


def test_round_trip_gives_bit_identical_logits_and_card(tmp_path, trained_like_model):
    path = tmp_path / "m.safetensors"
    card = ModelCard.for_model(
        trained_like_model,
        input_size=[64, 48],
        train_config={"epochs": 3},
        parent="abc",
        lineage=["abc"],
    )
    written = save_checkpoint(path, trained_like_model, card)
    model, loaded = load_checkpoint(path)
    x = torch.rand(2, 3, 48, 64)
    with torch.no_grad():
        assert torch.equal(model(x), trained_like_model(x))
    assert not model.training
    assert loaded == written
    assert loaded.arch == "lraspp_mobilenet_v3_large" and loaded.num_classes == 40
    assert loaded.class_names == list(CLASS_NAMES[1:]) and loaded.class_names[0] == "wall"
    assert loaded.input_size == [64, 48] and loaded.train_config == {"epochs": 3}
    assert loaded.parent == "abc" and loaded.lineage == ["abc"]
    assert len(loaded.weights_id) == 16 and loaded.created
    assert read_model_card(path) == loaded


def test_file_is_plain_safetensors_with_json_card(tmp_path, trained_like_model):
    path = tmp_path / "m.safetensors"
    save_checkpoint(path, trained_like_model)
    raw = path.read_bytes()
    (header_len,) = struct.unpack("<Q", raw[:8])
    header = json.loads(raw[8 : 8 + header_len])
    card = json.loads(header["__metadata__"]["csa"])
    assert card["arch"] == "lraspp_mobilenet_v3_large"
    assert card["mean"] == pytest.approx([0.485, 0.456, 0.406])


def test_weights_id_depends_on_weights_only(tmp_path, trained_like_model):
    a = save_checkpoint(
        tmp_path / "a.safetensors", trained_like_model, ModelCard(arch="x", metrics={"m": 1})
    )
    b = save_checkpoint(tmp_path / "b.safetensors", trained_like_model)
    with torch.no_grad():
        trained_like_model.net.classifier.high_classifier.bias[0] += 1.0
    c = save_checkpoint(tmp_path / "c.safetensors", trained_like_model)
    assert a.weights_id == b.weights_id != c.weights_id
    assert a.arch == "lraspp_mobilenet_v3_large"  # the card follows the model, not the caller


def test_missing_truncated_and_garbage_files_name_the_file(tmp_path, trained_like_model):
    good = tmp_path / "good.safetensors"
    save_checkpoint(good, trained_like_model)
    truncated = tmp_path / "truncated.safetensors"
    truncated.write_bytes(good.read_bytes()[: good.stat().st_size // 2])
    garbage = tmp_path / "garbage.safetensors"
    garbage.write_bytes(b"\x80\x04 this is a pickle, not a checkpoint" * 10)
    for path in (tmp_path / "missing.safetensors", truncated, garbage):
        with pytest.raises(CSAInputError) as err:
            load_checkpoint(path)
        assert err.value.where == str(path)


def test_foreign_or_mismatched_content_is_rejected(tmp_path, trained_like_model):
    no_card = tmp_path / "no_card.safetensors"
    save_file({"w": torch.zeros(2)}, str(no_card))
    with pytest.raises(CSAInputError, match="model card"):
        load_checkpoint(no_card)

    card = save_checkpoint(tmp_path / "ok.safetensors", trained_like_model)
    wrong_arch = tmp_path / "wrong_arch.safetensors"
    tensors = {k: v.contiguous() for k, v in trained_like_model.state_dict().items()}
    bad_card = ModelCard(**{**card.__dict__, "arch": "deeplabv3_mobilenet_v3_large"})
    save_file(tensors, str(wrong_arch), metadata={"csa": bad_card.to_json()})
    with pytest.raises(CSAInputError, match="do not match deeplabv3_mobilenet_v3_large"):
        load_checkpoint(wrong_arch)

    unknown = tmp_path / "unknown.safetensors"
    save_file(
        tensors,
        str(unknown),
        metadata={"csa": ModelCard(**{**card.__dict__, "arch": "segformer"}).to_json()},
    )
    with pytest.raises(CSAInputError, match="unknown architecture 'segformer'"):
        load_checkpoint(unknown)

    broken = tmp_path / "broken.safetensors"
    save_file(tensors, str(broken), metadata={"csa": "{not json"})
    with pytest.raises(CSAInputError, match="model card is not valid"):
        load_checkpoint(broken)


def test_cards_over_the_size_cap_are_neither_written_nor_read(tmp_path, trained_like_model):
    from csa_core.seg.checkpoint import MAX_CARD_BYTES

    stuffed = {"padding": "x" * MAX_CARD_BYTES}
    path = tmp_path / "big.safetensors"
    with pytest.raises(ValueError, match=f"more than the {MAX_CARD_BYTES} a card may hold"):
        save_checkpoint(path, trained_like_model, ModelCard(arch="x", metrics=stuffed))
    assert list(tmp_path.iterdir()) == []  # nothing half-written

    card = save_checkpoint(tmp_path / "ok.safetensors", trained_like_model)
    tensors = {k: v.contiguous() for k, v in trained_like_model.state_dict().items()}
    text = json.dumps({**card.__dict__, "metrics": stuffed})
    save_file(tensors, str(path), metadata={"csa": text})
    for read in (read_model_card, load_checkpoint):
        with pytest.raises(
            CSAInputError, match=f"{len(text)} bytes of JSON, more than the {MAX_CARD_BYTES}"
        ):
            read(path)
    # just under the cap still loads
    fits = {
        "padding": "x"
        * (MAX_CARD_BYTES - len(json.dumps({**card.__dict__, "metrics": {"padding": ""}})))
    }
    save_file(tensors, str(path), metadata={"csa": json.dumps({**card.__dict__, "metrics": fits})})
    assert read_model_card(path).metrics == fits


def test_child_card_records_its_parent(tmp_path, trained_like_model):
    parent = save_checkpoint(
        tmp_path / "p.safetensors",
        trained_like_model,
        ModelCard(arch="x", input_size=[64, 48], metrics={"val_miou": 0.5}),
    )
    child = parent.child(train_config={"task": "adapt"})
    assert child.parent == parent.weights_id and child.lineage == [parent.weights_id]
    assert (
        child.input_size == [64, 48]
        and child.metrics == {}
        and child.train_config == {"task": "adapt"}
    )
    written = save_checkpoint(tmp_path / "c.safetensors", trained_like_model, child)
    assert written.child().lineage == [parent.weights_id, written.weights_id]
