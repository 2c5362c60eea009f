"""The default-weighting rule over bench_cases.sh labels: a candidate replaces the default when its geometric-mean ATE
ratio over the cases is <= 0.92 and no family of cases (the median ratio over its seeds and jitter copies) is above
1.10.

    python experiments/eval/default_rule.py BASE CANDIDATE [CANDIDATE ...]   # reads $BENCH/LABEL/summary.txt

A family is a case name without its seed digit and jitter suffix (boxclean0..2 -> boxclean,
visp_castle_simu_depthnoise_j1..3 -> visp_castle_simu_depthnoise).
"""

import math
import os
import re
import statistics
import sys
from collections import defaultdict

GEOMEAN_MAX, FAMILY_MAX = 0.92, 1.10


def read(label: str) -> dict[str, float]:
    out = {}
    with open(os.path.join(os.environ.get("BENCH", "/tmp/bench"), label, "summary.txt")) as f:
        for line in f:
            parts = line.split()
            if len(parts) == 2:
                out[parts[0]] = float(parts[1])
    return out


def family(case: str) -> str:
    case = re.sub(r"_j\d+$", "", case)
    return re.sub(r"\d$", "", case) if case.startswith(("box", "scene")) else case


def main() -> None:
    base_label, *candidates = sys.argv[1:]
    base = read(base_label)
    for label in candidates:
        ate = read(label)
        ratios = {c: ate[c] / base[c] for c in base if c in ate}
        geo = math.exp(statistics.fmean(math.log(r) for r in ratios.values()))
        fams = defaultdict(list)
        for c, r in ratios.items():
            fams[family(c)].append(r)
        med = {f: statistics.median(r) for f, r in fams.items()}
        bad = {f: m for f, m in med.items() if m > FAMILY_MAX}
        ok = geo <= GEOMEAN_MAX and not bad and len(ratios) == len(base)
        print(
            f"{label} vs {base_label}: geometric mean {geo:.3f} over {len(ratios)} of {len(base)} cases; "
            f"worst family {max(med, key=med.get)} {max(med.values()):.2f}; rule {'MET' if ok else 'NOT met'}"
        )
        for f in sorted(med):
            print(f"  {f:32s} {med[f]:.2f}  ({', '.join(f'{r:.2f}' for r in fams[f])})")


if __name__ == "__main__":
    main()
