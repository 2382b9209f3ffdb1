"""The Mitsuba variant a render runs in: the default one, activating it with the package's plugins,
checking a variant asked for, and giving Dr.Jit's cached memory back after a large render.
"""

import os

from ...errors import InputError, VariantError


def default_variant():
    """The variant named by the environment variable ``MM_VARIANT`` when set (``llvm_ad_rgb`` or
    ``cuda_ad_rgb``, the latter refused where CUDA does not run), else ``cuda_ad_rgb`` when a GPU
    works, else ``llvm_ad_rgb``.
    """
    import mitsuba as mi

    chosen = os.environ.get("MM_VARIANT")
    if chosen:
        usable = [v for v in ("llvm_ad_rgb", "cuda_ad_rgb") if v in mi.variants()]
        if chosen not in usable:
            raise VariantError(
                f"MM_VARIANT={chosen}: the tools render in "
                f"{' or '.join(usable)}; unset MM_VARIANT or name one of those"
            )
        if chosen.startswith("cuda") and not _cuda_works():
            raise VariantError(
                f"MM_VARIANT={chosen}: no CUDA device or driver works here; unset "
                "MM_VARIANT or use llvm_ad_rgb"
            )
        return chosen
    if "cuda_ad_rgb" in mi.variants() and _cuda_works():
        return "cuda_ad_rgb"
    return "llvm_ad_rgb"


def _cuda_works():
    """Whether Dr.Jit's CUDA backend runs here (a device and a driver)."""
    try:
        import drjit as dr

        return bool(dr.has_backend(dr.JitBackend.CUDA))
    except Exception:  # no driver
        return False


def use_variant(variant=None, jit=False):
    """The variant to render in, active and with the package's plugins; returns ``mi``.

    Never switches the variant unless asked, as Mitsuba itself:

    - ``variant`` given: that one (checked, :func:`check_variant`), activated as
      ``mi.set_variant(variant)`` would (the scenes loaded then live in it);
    - else the active variant, checked (an unsuitable one is refused, not replaced);
    - else (no variant is active yet) :func:`default_variant`, activated.

    To render in another variant for a while, wrap the calls in Mitsuba's own
    ``with mi.util.scoped_set_variant("llvm_ad_rgb"): ...``.

    Parameters
    ----------
    jit : bool
        Require a JIT variant, as the ``manifold_path`` integrator does.
    """
    import mitsuba as mi

    from ..plugin import plugins

    if variant is not None:
        check_variant(variant, jit=jit)
        if mi.variant() != variant:
            mi.set_variant(variant)
    elif mi.variant() is not None:
        try:
            check_variant(mi.variant(), "the active Mitsuba variant", jit)
        except InputError as e:
            raise InputError(f"{e}; call mi.set_variant(...) or pass `variant`") from None
    else:
        mi.set_variant(default_variant())
    plugins.install()
    plugins.register()
    return mi


def release_render_memory():
    """Give the memory Dr.Jit keeps for reuse after a render back to the system.

    Dr.Jit caches the buffers a kernel frees (the paths and splats of a pass) for later kernels
    of the same sizes; after a large render they would stay in the process, beside the NumPy
    arrays of the next steps, until it ends. Called where a large render is done.
    """
    import drjit as dr

    dr.flush_malloc_cache()


def check_variant(value, name="`variant`", jit=False):
    """A Mitsuba variant that is installed and renders measured RGB tables.

    Parameters
    ----------
    jit : bool
        Also require a JIT variant (``llvm_*``/``cuda_*``), as the ``manifold_path``
        integrator does (``scalar_rgb`` renders ``manifold_brdf`` but not a basis).
    """
    import mitsuba as mi

    known = list(mi.variants())
    if value not in known:
        raise InputError(
            f"{name} {value!r} is not a Mitsuba variant of this installation "
            f"(installed: {', '.join(known)})"
        )
    rgb = value.endswith("_rgb") and "polarized" not in value
    if not rgb or (jit and not value.startswith(("llvm_", "cuda_"))):
        usable = [
            v
            for v in known
            if v.endswith("_rgb")
            and "polarized" not in v
            and (not jit or v.startswith(("llvm_", "cuda_")))
        ]
        need = "an RGB JIT variant" if jit else "an RGB variant"
        raise InputError(
            f"{name} {value!r} cannot be used here: this needs {need} "
            f"({', '.join(usable) or 'none installed'})"
        )
    if value.startswith("cuda_"):
        import drjit as dr

        try:
            ok = dr.has_backend(dr.JitBackend.CUDA)
        except Exception:
            ok = False
        if not ok:
            raise InputError(f"{name} {value!r} needs a CUDA GPU, and none is usable here")
    return value
