"""Model builders: 40 NYU40 outputs, no downloads, local weights by name and shape."""

from __future__ import annotations

import pytest
import torch
from safetensors.torch import save_file

from csa_core.errors import CSAInputError
from csa_core.seg.config import ARCH_NAMES, DEFAULT_ARCH, PAPER_ARCH
from csa_core.seg.models import ARCHS, build_model, count_parameters, load_foreign_weights


def test_registry_matches_config_names():
    assert tuple(ARCHS) == ARCH_NAMES
    assert DEFAULT_ARCH in ARCHS and PAPER_ARCH == "deeplabv3_resnet101"


@pytest.mark.parametrize("arch", ["lraspp_mobilenet_v3_large", "deeplabv3_mobilenet_v3_large"])
def test_light_models_output_40_channels_at_input_size(arch):
    torch.manual_seed(0)
    model = build_model(arch).eval()
    with torch.no_grad():
        out = model(torch.rand(2, 3, 48, 64))
    assert out.shape == (2, 40, 48, 64)
    assert out.dtype == torch.float32 and torch.isfinite(out).all()


def test_light_model_is_small():
    assert count_parameters(build_model("lraspp_mobilenet_v3_large")) < 4_000_000


def test_normalisation_is_applied_inside_and_not_saved():
    model = build_model(mean=(0.5, 0.5, 0.5), std=(0.25, 0.25, 0.25))
    assert model.normalization == ((0.5, 0.5, 0.5), (0.25, 0.25, 0.25))
    assert "mean" not in model.state_dict() and "std" not in model.state_dict()


def test_unknown_arch_and_bad_input_are_errors():
    with pytest.raises(ValueError, match="unknown architecture"):
        build_model("unet")
    with pytest.raises(ValueError, match=r"\(B, 3, H, W\)"):
        build_model()(torch.rand(3, 48, 64))


def test_foreign_weights_load_backbone_by_name(tmp_path):
    torch.manual_seed(1)
    donor = build_model()
    # A bare MobileNetV3 backbone as torchvision names it ("features.<i>...") plus a mismatching
    # head.
    backbone = {f"features.{k}": v.clone() for k, v in donor.net.backbone.state_dict().items()}
    backbone["classifier.3.weight"] = torch.zeros(1000, 1280)
    path = tmp_path / "backbone.safetensors"
    save_file(backbone, str(path))
    torch.manual_seed(2)
    model = build_model()
    loaded, skipped = load_foreign_weights(model, path)
    assert skipped == ["classifier.3.weight"] and len(loaded) == len(backbone) - 1
    for k, v in donor.net.backbone.state_dict().items():
        assert torch.equal(model.net.backbone.state_dict()[k], v)
    assert not torch.equal(
        model.net.classifier.high_classifier.weight, donor.net.classifier.high_classifier.weight
    )


def test_foreign_weights_that_match_nothing_are_an_error(tmp_path):
    path = tmp_path / "other.safetensors"
    save_file({"encoder.w": torch.zeros(3)}, str(path))
    with pytest.raises(CSAInputError, match="no tensor matches"):
        build_model(weights=path)
