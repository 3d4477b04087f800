"""numba options of the compiled core, in one place.

``INLINE`` marks the small functions of one sample step (reference, control
law, cost, plant, ``sample_step``). ``forceinline`` gives them LLVM's
``alwaysinline``: each is compiled once per signature and LLVM inlines it into
every compiled caller, so a whole sample step is optimised as one function
(without it LLVM leaves ``abc_law`` and ``rk4_step`` as calls, and the lane
loop of the batch kernel cannot be vectorised). numba's own ``inline="always"``
gives the same bits and speed but copies and re-types the callee's IR at every
call site, for each kernel, so it compiles slower; with ``forceinline`` the
callees compiled for ``simulate`` are cached and serve the batch kernel too.
Inlining reorders nothing: IEEE arithmetic without fast-math gives the same
bits either way, and tests prove the batch kernel equal to the
single-episode one. They stay callable from Python.

``LEAF`` marks the smallest of them (chamber volumes, valve drops and flows,
projection, cost and metric updates, divergence test): numba's own
``inline="always"`` copies their few lines into each caller, which costs less
than compiling each as a function of its own. The start-up figures behind
these choices are in ``docs/speed.md`` (Start-up).

``KERNEL`` marks the entry points called from Python (episode, batch, scoring).
"""
KERNEL = dict(cache=True, error_model="numpy", nogil=True)
INLINE = dict(KERNEL, forceinline=True)
LEAF = dict(KERNEL, inline="always")
