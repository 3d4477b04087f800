"""Start-up: ``import has_control`` is cheap and changes nothing in the process;
the compiled core still runs under the cache keyed by all of its sources."""
import subprocess
import sys


def _run(code: str) -> str:
    return subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout.strip()


def test_importing_the_package_loads_no_kernel_and_installs_no_signal_handler():
    out = _run("import signal, sys\n"
               "before = (signal.getsignal(signal.SIGINT), signal.getsignal(signal.SIGTERM))\n"
               "import has_control\n"
               "after = (signal.getsignal(signal.SIGINT), signal.getsignal(signal.SIGTERM))\n"
               "print('numba' in sys.modules, 'has_control.core.episode' in sys.modules, before == after)")
    assert out == "False False True"


def test_a_compiled_module_runs_under_the_keyed_cache_and_numba_keeps_its_setting():
    out = _run("import numba\n"
               "before = numba.config.CACHE_DIR\n"
               "from has_control.core import episode\n"
               "import has_control\n"
               "print(numba.config.CACHE_DIR == before, type(episode.__loader__).__name__,\n"
               "      has_control.simulate is episode.simulate)")
    assert out == "True _KeyedLoader True"
