"""transport.variant: the Mitsuba variant chosen for A (auto | llvm | cuda | scalar), checked without a GPU by
handing the choice a machine's variants and devices; the stage records its choice in stage.json's metrics."""

from __future__ import annotations

import pytest

from objcam.errors import StageError
from objcam.pipeline.stage import StageInputs
from objcam.stages import transport as stage
from objcam.transport.variant import choose_variant, cuda_present
from tests.test_transport import ENV_H, _write_artifact

ALL = ("scalar_rgb", "llvm_ad_rgb", "cuda_ad_rgb")


def _yes():
    return True


def _no():
    return False


@pytest.mark.parametrize("requested,variants,cuda,llvm,expected", [
    ("auto", ALL, _yes, _yes, "cuda_ad_rgb"),  # a GPU: auto takes it
    ("auto", ALL, _no, _yes, "llvm_ad_rgb"),  # no device
    ("auto", ("scalar_rgb", "llvm_ad_rgb"), _yes, _yes, "llvm_ad_rgb"),  # a device, but no cuda build of Mitsuba
    ("auto", ALL, _yes, _no, "cuda_ad_rgb"),  # no libLLVM: the GPU still works
    ("llvm", ALL, _yes, _yes, "llvm_ad_rgb"),  # asked for llvm on a GPU machine
    ("cuda", ALL, _yes, _no, "cuda_ad_rgb"),
])
def test_choice(requested, variants, cuda, llvm, expected):
    assert choose_variant(requested, variants=variants, has_cuda=cuda, has_llvm=llvm) == expected


@pytest.mark.parametrize("requested,variants,cuda,llvm,says", [
    ("cuda", ALL, _no, _yes, "no CUDA device"),
    ("cuda", ("scalar_rgb", "llvm_ad_rgb"), _yes, _yes, "no cuda_ad_rgb"),
    ("auto", ALL, _no, _no, "libLLVM"),
    ("llvm", ("scalar_rgb", "cuda_ad_rgb"), _yes, _yes, "libLLVM"),
    ("scalar", ALL, _yes, _yes, "scalar_rgb"),
    ("vulkan", ALL, _yes, _yes, "unknown transport.variant"),
])
def test_refusals_are_one_line_naming_the_file_and_fix(tmp_path, requested, variants, cuda, llvm, says):
    with pytest.raises(StageError) as e:
        choose_variant(requested, tmp_path / "capture.toml", variants=variants, has_cuda=cuda, has_llvm=llvm)
    msg = str(e.value)
    assert says in msg and "capture.toml" in msg and "fix:" in msg and "\n" not in msg


def test_the_stage_records_its_variant_and_refuses_what_the_machine_lacks(tmp_path):
    folder = tmp_path / "scene"
    _write_artifact(folder, cams=1)
    out = tmp_path / "out"
    out.mkdir()
    m = stage.run(StageInputs(capture=folder, upstream={"scene": folder}, out=out),
                  stage.Params(env_height=ENV_H, model="direct", subpixel_samples=4, object_subpixel_samples=4,
                               object_samples=4)).metrics
    assert m["variant"] == ("cuda_ad_rgb" if cuda_present() else "llvm_ad_rgb")
    import mitsuba as mi

    assert mi.variant() == m["variant"]  # later use_mitsuba() calls keep the stage's choice
    if not cuda_present():
        out2 = tmp_path / "out2"
        out2.mkdir()
        with pytest.raises(StageError, match="no CUDA device"):
            stage.run(StageInputs(capture=folder, upstream={"scene": folder}, out=out2),
                      stage.Params(env_height=ENV_H, model="direct", variant="cuda"))
