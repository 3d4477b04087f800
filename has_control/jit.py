"""numba options of the compiled core, in one place.

``INLINE`` marks the small functions of one sample step (reference, control
law, cost, plant). numba inlines them into each compiled caller at its own IR
level, so LLVM optimises a whole sample step as one function: without it, LLVM
leaves ``abc_law`` and ``rk4_step`` as calls and the batch kernel is slower
(154 against 131 ns per sample per core, see README). Inlining reorders nothing: IEEE arithmetic
without fast-math gives the same bits either way, and a test proves the batch
kernel equal to the single-episode one. They stay callable from Python.

``KERNEL`` marks the entry points called from Python (episode, batch, scoring).
"""
KERNEL = dict(cache=True, error_model="numpy", nogil=True)
INLINE = dict(KERNEL, inline="always")
