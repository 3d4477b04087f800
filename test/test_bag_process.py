"""The bag writer process: what it is handed ends up in the bag, even if the recording process is killed."""
import subprocess
import sys

import numpy as np
import pytest

from has_control.wire import cdr
from has_control.bag import BagError, read_bag
from has_control.bag.process import BagProcess

SCRIPT = """
import os, signal, sys
import numpy as np
from has_control.wire import cdr
from has_control.bag.process import BagProcess
from has_control.wire.topics import JOINT_STATE, STATE_NAMES
bag = BagProcess(sys.argv[1])
bag.add_topic("/state", JOINT_STATE)
for k in range(3):
    n = 1000
    msgs = cdr.encode_joint_states((np.arange(n) + k * n) * 300_000, STATE_NAMES, *np.zeros((3, n, 3)))
    bag.write_messages({"/state": (JOINT_STATE, msgs)})
if sys.argv[2] == "kill":
    os.kill(os.getpid(), signal.SIGKILL)           # the recording process dies; the writer keeps the bag
bag.close()
"""


@pytest.mark.parametrize("end", ["close", "kill"])
def test_everything_handed_over_is_in_the_bag(tmp_path, end):
    path = tmp_path / "run"
    r = subprocess.run([sys.executable, "-c", SCRIPT, str(path), end], capture_output=True, text=True, timeout=120)
    assert r.returncode == (0 if end == "close" else -9), r.stderr
    bag = read_bag(path)
    assert bag.complete and bag.count("/state") == 3000
    np.testing.assert_array_equal(cdr.stamps_ns([m for _, m in bag.messages["/state"]]), np.arange(3000) * 300_000)


def test_an_existing_bag_is_refused_before_anything_starts(tmp_path):
    (tmp_path / "run").mkdir()
    with pytest.raises(BagError, match="exists already"):
        BagProcess(tmp_path / "run")
