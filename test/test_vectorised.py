"""The batch kernel's lane loop compiles to SIMD division and square root.

One sample step costs 23 divisions and 10 square roots per candidate (RK4:
3 divisions and 2 roots per stage; the law: 10 divisions and 2 roots, one of
them the ẋ3d mode's; the metric: 1 division). Scalar divsd/sqrtsd are
throughput-bound, so the batch kernel is fast only if LLVM vectorises the loop
over lanes: then each of them appears as a packed instruction on a vector
register, in both copies of the loop (one per ẋ3d mode).
"""
import re

import numpy as np
import pytest
from llvmlite import binding as llvm
from numba import njit

from has_control.core import episode
from has_control.core.jit import KERNEL
from has_control.core.params import Config

DIVISIONS, ROOTS = 23, 10
COPIES = 2


@pytest.mark.skipif("+avx" not in llvm.get_host_cpu_features().flatten(), reason="no AVX on this CPU")
def test_block_lane_loop_uses_packed_division_and_sqrt():
    fresh = njit(**dict(KERNEL, cache=False))(episode._block.py_func)   # cached kernels carry no asm
    a = episode.EpisodeArrays.from_config(Config())
    gains = np.array([[400.0, 400.0, 400.0]])
    out = np.empty((1, 6))
    fresh(gains, 0, 1, *a.kernel_args(), out)
    asm = next(iter(fresh.inspect_asm().values()))
    packed_div = re.findall(r"\bvdivpd\s+[^\n]*%[yz]mm", asm)
    packed_sqrt = re.findall(r"\bvsqrtpd\s+[^\n]*%[yz]mm", asm)
    assert len(packed_div) >= COPIES * DIVISIONS and len(packed_sqrt) >= COPIES * ROOTS, \
        (len(packed_div), len(packed_sqrt))
    assert out[0, 0] == episode.evaluate(gains)[0]
