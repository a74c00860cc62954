"""Golden values for tests/metrics_savgol.rs: scipy.signal.savgol_filter (mode="interp") on a fixed signal.

Run: python3 tools/metrics_savgol_golden.py > tests/fixtures/nuplan/savgol_golden.json  (needs numpy, scipy)
"""
import json

import numpy as np
import scipy
from scipy.signal import savgol_filter

x = [float(v) for v in np.random.RandomState(0).randn(20)]
cases = []
for window, poly, deriv, delta in [(8, 2, 0, 1.0), (15, 2, 1, 0.1), (5, 2, 1, 0.1), (5, 3, 2, 0.1), (20, 2, 0, 1.0), (4, 3, 1, 0.1)]:
    y = savgol_filter(x, window, poly, deriv=deriv, delta=delta)
    cases.append({"window": window, "poly": poly, "deriv": deriv, "delta": delta, "y": [float(v) for v in y]})
print(json.dumps({"source": f"scipy {scipy.__version__} savgol_filter(mode='interp')", "x": x, "cases": cases}, indent=1))
