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


def test_variant_bench_compares_columns_on_shared_pixels_and_texels():
    """bench.variant_bench's comparison of a GPU machine's column subset with a local one: matched by pixel and
    texel index (the two builds may keep different edge pixels), relative Frobenius and worst column."""
    import numpy as np

    from bench.variant_bench import _diff_columns

    rng = np.random.default_rng(3)
    A = rng.random((1, 50, 6)).astype(np.float32)
    a = {"A": A, "pixel_index": np.arange(50), "texel_index": np.arange(0, 48, 8)}
    # b: the same columns with its pixels in another order, one pixel fewer and one extra texel
    order = rng.permutation(49)
    B = np.concatenate([A[:, order], np.zeros((1, 49, 0), np.float32)], axis=2)
    B = np.concatenate([B, rng.random((1, 49, 1)).astype(np.float32)], axis=2)
    b = {"A": B, "pixel_index": order, "texel_index": np.r_[np.arange(0, 48, 8), 99]}
    assert _diff_columns(a, b) == (0.0, 0.0)
    B2 = B.copy()
    B2[:, :, 2] *= 1.1  # one column 10% off
    rel, worst = _diff_columns(a, {**b, "A": B2})
    assert worst == pytest.approx(0.1, rel=1e-5)
    col = np.linalg.norm(A[0, :, 2][order])
    assert rel == pytest.approx(0.1 * col / np.linalg.norm(A[0][order]), rel=1e-4)
