"""Which CPU a benchmark ran on: every benchmark prints this first, and README figures quote it.

The label itself lives in shared.runtime.cpus (`splittag profile` prints it too); this module keeps
the benchmarks' import and `python -m bench.machine`.
"""

from __future__ import annotations

from shared.runtime.cpus import FEATURES, cpu_label

__all__ = ["FEATURES", "cpu_label"]

if __name__ == "__main__":
    print(cpu_label())
