import sys
from pathlib import Path

# test helpers (reference_impl) import as plain modules
sys.path.insert(0, str(Path(__file__).resolve().parent))
