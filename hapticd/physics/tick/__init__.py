"""The tick's physics, one module a stage, written once in the subset of Python numba
compiles: float arithmetic, ``math``, loops over preallocated numpy arrays, no objects, no
allocation. Each stage module declares itself (``layout.Declaration``: the frame fields it
reads and writes, its carried state, its plan blocks, its parameter slots) and owns its
kernel; ``step`` lays the call's interface out from the declarations and composes the
kernels into the one call, ``tick_step``. hapticd.physics.kernels re-exports them under
their old names; the picture: docs/architecture.md."""
