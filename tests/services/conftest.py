import sys
from pathlib import Path

# Lets test modules here share the step helpers of test_steps.py.
sys.path.insert(0, str(Path(__file__).parent))
