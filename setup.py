"""The compiled per-frame kernel (kernel/*.c) as an optional extension: where it cannot be built (no C
compiler, no Python headers) the install goes on without it and the numpy pipeline runs instead
(`optitac-edge run` says so in one line at start). Everything else is in pyproject.toml."""

from setuptools import Extension, setup

setup(
    ext_modules=[
        Extension(
            "optitac_edge.core._frame_kernel",
            sources=["kernel/module.c", "kernel/frame_kernel.c", "kernel/gradient_solve.c", "kernel/vibration.c",
                     "kernel/vibration_type.c", "kernel/motion.c", "kernel/motion_type.c"],
            depends=["kernel/frame_kernel.h", "kernel/gradient_solve.h", "kernel/simd.h", "kernel/vibration.h", "kernel/motion.h"],
            # -ffp-contract=off: no fused multiply-adds (aarch64's GCC contracts by default), so every
            # float32 step rounds as numpy's does and the results agree with the numpy pipeline
            extra_compile_args=["-O3", "-std=c99", "-ffp-contract=off"],
            optional=True,
        )
    ]
)
