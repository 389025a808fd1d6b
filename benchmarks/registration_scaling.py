"""Time of pso-robust against the number of pairs, at 50 % outliers and sigma 0.02 m.

The rigidity graph is O(M^2) in the pairs it holds; pso-robust builds it on at most
``graph_pairs`` (512) of them, so the whole call grows linearly with N. The "full graph" column
is the same estimator with the graph on every pair (``graph_pairs`` = N), the cost before.

    OMP_NUM_THREADS=1 python benchmarks/registration_scaling.py

Writes ``benchmarks/results/registration-scaling/scaling.json``, ``scaling.md`` and
``scaling.png``. Each cell: the median and the minimum of 15 calls on the same problem (the
minimum is the least disturbed by other processes on a shared machine).
"""

from __future__ import annotations

import json
import time
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
import numpy as np

from estimator.geometry import rotation_angle_deg
from estimator.registration.registry import register
from estimator.rendered.simulation import simulate_pair

OUT = Path(__file__).resolve().parents[1] / "benchmarks/results/registration-scaling"
DRAWN = (400, 1000, 2000, 4000, 6000, 8000)  # points drawn; about 70 % are visible pairs
REPEATS = 15


def _times(pair, **options) -> tuple[float, float, float]:
    register(pair.source, pair.target, seed=0, **options)  # warm (compiled kernels, caches)
    times, errors = [], []
    for seed in range(REPEATS):
        start = time.perf_counter()
        result = register(pair.source, pair.target, seed=seed, **options)
        times.append(time.perf_counter() - start)
        errors.append(rotation_angle_deg(result.rotation.T @ pair.rotation))
    return 1000 * float(np.median(times)), 1000 * float(np.min(times)), float(np.median(errors))


def main() -> int:
    rows = []
    for drawn in DRAWN:
        pair = simulate_pair(drawn, 0.02, 0.5, rng=1)
        count = len(pair.source)
        linear = _times(pair)
        full = _times(pair, graph_pairs=max(count, 512))
        rows.append(
            {"pairs": count, "median_ms": linear[0], "min_ms": linear[1],
             "rotation_error_deg": linear[2], "full_graph_median_ms": full[0],
             "full_graph_min_ms": full[1], "full_graph_rotation_error_deg": full[2]}
        )  # fmt: skip
        print(rows[-1], flush=True)
    lines = [
        "pso-robust, 50 % outliers, sigma 0.02 m, one core; ms per call, median / min of "
        f"{REPEATS} (shared machine: the median carries other processes' load)",
        "",
        "| pairs | subsampled graph (default) | rot. err. deg | full graph (before) "
        "| rot. err. deg |",
        "|---|---|---|---|---|",
    ]
    for row in rows:
        lines.append(
            f"| {row['pairs']} | {row['median_ms']:.2f} / {row['min_ms']:.2f} | "
            f"{row['rotation_error_deg']:.4f} | {row['full_graph_median_ms']:.2f} / "
            f"{row['full_graph_min_ms']:.2f} | {row['full_graph_rotation_error_deg']:.4f} |"
        )
    text = "\n".join(lines) + "\n"
    print(text)
    OUT.mkdir(parents=True, exist_ok=True)
    (OUT / "scaling.md").write_text(text)
    (OUT / "scaling.json").write_text(json.dumps(rows, indent=2) + "\n")
    figure, axes = plt.subplots(figsize=(6, 4))
    pairs = [row["pairs"] for row in rows]
    axes.plot(pairs, [row["min_ms"] for row in rows], "o-", label="subsampled graph (min)")
    axes.plot(pairs, [row["median_ms"] for row in rows], "o:", label="subsampled graph (median)")
    axes.plot(pairs, [row["full_graph_min_ms"] for row in rows], "s-", label="full graph (min)")
    axes.set_xlabel("pairs")
    axes.set_ylabel("ms per call (one core)")
    axes.set_title("pso-robust, 50 % outliers")
    axes.grid(True, alpha=0.3)
    axes.legend()
    figure.tight_layout()
    figure.savefig(OUT / "scaling.png", dpi=110)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
