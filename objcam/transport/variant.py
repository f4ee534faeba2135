"""Which Mitsuba variant builds A: ``transport.variant=auto|llvm|cuda|scalar``.

``auto`` takes ``cuda_ad_rgb`` when Dr.Jit finds a CUDA device and Mitsuba has that variant, else ``llvm_ad_rgb``
(vectorised on every core). ``scalar`` names ``scalar_rgb`` only to refuse it in one line: objcam's kernels
(shadow-ray batches, the gather, the path-traced columns) hand Mitsuba numpy arrays of millions of lanes, which a
scalar variant cannot hold. The variant is process-wide (Mitsuba's), so it is set before the scene is loaded and
every later ``objcam.scene.use_mitsuba()`` keeps it.
"""

from __future__ import annotations

from typing import Callable, Iterable, Literal

from objcam.errors import StageError

Requested = Literal["auto", "llvm", "cuda", "scalar"]
VARIANTS = {"llvm": "llvm_ad_rgb", "cuda": "cuda_ad_rgb", "scalar": "scalar_rgb"}


def cuda_present() -> bool:
    """Whether Dr.Jit can reach a CUDA device (loads libcuda; False without a driver or device)."""
    try:
        import drjit as dr

        return bool(dr.has_backend(dr.JitBackend.CUDA))
    except Exception:  # no driver, no device, an old drjit: no CUDA
        return False


def llvm_present() -> bool:
    """Whether Dr.Jit found libLLVM (the llvm variants need it)."""
    try:
        import drjit as dr

        return bool(dr.has_backend(dr.JitBackend.LLVM))
    except Exception:
        return False


def available_variants() -> tuple[str, ...]:
    import mitsuba as mi

    return tuple(mi.variants())


def choose_variant(requested: str, toml=None, *, variants: Iterable[str] | None = None,
                   has_cuda: Callable[[], bool] = cuda_present, has_llvm: Callable[[], bool] = llvm_present) -> str:
    """The Mitsuba variant for ``requested`` (auto | llvm | cuda | scalar), or a one-line StageError naming
    ``toml`` and the fix. ``variants`` / ``has_cuda`` / ``has_llvm`` default to this machine's (tests pass their
    own, so the choice is checked without a GPU)."""
    have = set(available_variants() if variants is None else variants)
    where = "set transport.variant=llvm (or auto)"
    if requested == "scalar":
        raise StageError("transport.variant=scalar: objcam's transport traces batches of millions of rays from numpy "
                         "arrays, which Mitsuba's scalar_rgb variant (one ray per call) cannot run", toml, where)
    if requested not in ("auto", "llvm", "cuda"):
        raise StageError(f"unknown transport.variant {requested!r}", toml, "use auto, llvm, cuda or scalar")
    if requested in ("auto", "cuda") and VARIANTS["cuda"] in have and has_cuda():
        return VARIANTS["cuda"]
    if requested == "cuda":
        why = "this Mitsuba build has no cuda_ad_rgb" if VARIANTS["cuda"] not in have else "no CUDA device was found"
        raise StageError(f"transport.variant=cuda: {why}", toml, where + " on this machine")
    if VARIANTS["llvm"] not in have or not has_llvm():
        raise StageError("Mitsuba's llvm_ad_rgb variant needs libLLVM, which was not found", toml,
                         "run `make setup` (installs libllvm19), or set transport.variant=cuda on a GPU machine")
    return VARIANTS["llvm"]


def activate(requested: str, toml=None) -> str:
    """Choose the variant and make it Mitsuba's (process-wide); returns its name."""
    from objcam.scene import use_mitsuba

    name = choose_variant(requested, toml)
    use_mitsuba(name)
    return name
