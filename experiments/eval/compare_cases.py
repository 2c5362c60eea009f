"""Per-case ATE of several bench_cases.sh labels side by side, each as a ratio to the first, and their geometric means.

python compare_cases.py BASE LABEL [LABEL ...]     # reads $BENCH/LABEL/summary.txt (default /tmp/bench)
"""

import math
import os
import sys

labels = sys.argv[1:]
data: dict[str, dict[str, float]] = {}
for label in labels:
    with open(os.path.join(os.environ.get("BENCH", "/tmp/bench"), label, "summary.txt")) as f:
        for line in f:
            parts = line.split()
            if len(parts) == 2:
                data.setdefault(parts[0], {})[label] = float(parts[1])
base = labels[0]
print("case".ljust(30), *[label[:14].rjust(14) for label in labels])
logs: dict[str, list[float]] = {label: [] for label in labels}
for case, ate in data.items():
    cells = []
    for label in labels:
        cell = f"{ate.get(label, float('nan')):.2f}"
        if label in ate and base in ate:
            logs[label].append(math.log(ate[label] / ate[base]))
            if label != base:
                cell += f" ({ate[label] / ate[base]:.2f})"
        cells.append(cell.rjust(14))
    print(case.ljust(30), *cells)
means = [f"{label}: {math.exp(sum(v) / len(v)):.3f} (n={len(v)})" for label, v in logs.items() if v]
print("geometric mean vs", base, *means)
