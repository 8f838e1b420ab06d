import sys
from pathlib import Path

# tests import the shared synthetic-data helpers (tests/toydata.py) by module name
sys.path.insert(0, str(Path(__file__).parent))
