"""``swarmvo bench odometry``: whole-pipeline accuracy of every estimator, real data first.

Part ``real`` (when ``../shared/data`` is present): the EuRoC MH_01 clip (hand-carried, 3.3 m,
145 degrees) and the V1_01 standstill, each run with every registered estimator
(``estimator.registration.registry.available_methods``) x the Mahalanobis refinement on / off
x vision alone (back end without IMU, ``--no-imu``) / fused with the clip's IMU, plus the plain
OpenCV stereo VO peer (``estimator.bench.peers.opencv_stereo_vo``). Each run also reports how well
the stereo noise model fits the data: the median squared Mahalanobis residual of the inliers,
which is 2.366 (chi-square, 3 DOF) when the estimated pixel and disparity noise is right.

Part ``rendered``: a loop rendered once with exact ground truth (``estimator.rendered.synthetic``:
default 200 frames, 21 m body path, EuRoC-like rig and IMU), clean and with sensor effects, each
estimator fused with the IMU (the default run), fused and front-end accuracy.

Outputs ``odometry.json`` and ``odometry.md`` (the printed tables) plus one ``swarmvo run``
style folder per run (the rendered images go to ``--data``).
"""

from __future__ import annotations

import argparse
import json
import tempfile
import time
import warnings
from pathlib import Path
from typing import Any

from estimator.evaluation.metrics import evaluate_trajectory
from estimator.formats.datasets import Sequence, open_sequence
from estimator.pipeline import build_config, run_sequence, write_outputs
from estimator.registration.methods import DEFAULT_ESTIMATOR
from estimator.registration.registry import available_methods
from estimator.rendered.cache import FINGERPRINT_FILE, rendered_once
from estimator.rendered.synthetic import SynthOptions

__all__ = ["add_arguments", "run"]

DATA = Path(__file__).resolve().parents[2].parent / "shared/data"
REAL = {name: DATA / name for name in ("euroc_mh01_moving", "euroc_v101_micro")}
RENDERED = ("rendered", "rendered_noisy")
PARTS = ("real", "rendered")
PEER = "opencv-vo"
CHI2_3_MEDIAN = 2.366  # median of chi-square with 3 degrees of freedom
# Sensor effects of the noisy variant: image noise, gain changes, motion blur, IMU as EuRoC.
NOISY_EFFECTS = {"noise": 4.0, "brightness": 0.25, "blur": 0.5}
TARGET_ATE_PCT = 1.0
TARGET_RPE_ROT_DEG = 0.1
COLUMNS = (
    ("ate_rmse_m", "ATE m", "{:.4f}"),
    ("ate_pct_of_path", "ATE %", "{:.2f}"),
    ("rpe_trans_rmse_m", "RPE m/fr", "{:.4f}"),
    ("rpe_rot_rmse_deg", "RPE deg/fr", "{:.3f}"),
    ("eq20_rms", "eq20 RMS", "{:.4f}"),
    ("final_drift_m", "drift m", "{:.3f}"),
)


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--out", type=Path, default=Path("benchmarks/results/odometry"))
    parser.add_argument("--parts", nargs="+", choices=PARTS, default=list(PARTS))
    parser.add_argument("--frames", type=int, default=200)
    parser.add_argument("--length-m", type=float, default=21.0, help="rendered body path [m]")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument(
        "--estimators", nargs="+", default=None, help="default: every registered estimator"
    )
    parser.add_argument(
        "--real", nargs="+", choices=tuple(REAL), default=list(REAL), help="real clips to run"
    )
    parser.add_argument(
        "--data",
        type=Path,
        default=Path(tempfile.gettempdir()) / "swarmvo-bench",
        help="where the rendered sequence is written once and reused (kept out of --out)",
    )
    parser.add_argument("--datasets", nargs="+", choices=RENDERED, default=list(RENDERED))
    parser.add_argument(
        "--refinement", nargs="+", choices=("on", "off"), default=["on", "off"],
        help="real clips: which refinement settings to run",
    )  # fmt: skip
    parser.add_argument(
        "--peer", action=argparse.BooleanOptionalAction, default=True,
        help="real clips: run the OpenCV stereo VO peer",
    )  # fmt: skip
    parser.add_argument("--quick", action="store_true", help="40 frames / 4 m, for a smoke run")


def _estimators(args: argparse.Namespace) -> list[str]:
    known = available_methods()
    chosen = args.estimators or known
    unknown = sorted(set(chosen) - set(known))
    if unknown:
        raise ValueError(f"unknown estimator(s) {unknown}; registered: {', '.join(known)}")
    # The default first, as the tables lead with it.
    return sorted(chosen, key=lambda name: (name != DEFAULT_ESTIMATOR, name))


def _open(path: Path) -> Sequence:
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # unpaired camera rows are expected in EuRoC
        return open_sequence(path)


# ----------------------------------------------------------------------------- real clips


def _real_label(estimator: str, refine: bool, imu: bool) -> str:
    return f"{estimator} refine-{'on' if refine else 'off'} {'fused' if imu else 'vision'}"


def _real_run(
    sequence: Sequence, estimator: str, refine: bool, imu: bool, args: argparse.Namespace, out: Path
) -> dict[str, Any]:
    config = build_config(estimator, args.seed, imu=imu, backend=True)
    config.registration.mahalanobis_refine = refine
    result = run_sequence(sequence, config, use_imu=imu, progress=False)
    summary = write_outputs(result, out)
    return {key: summary.get(key) for key in _REAL_KEYS}


_REAL_KEYS = (
    "frames", "frames_failed", "status_counts", "ate_rmse_m", "rpe_trans_rmse_m",
    "rpe_rot_rmse_deg", "final_drift_m", "path_length_m", "wall_time_s", "noise",
)  # fmt: skip


def _peer_run(sequence: Sequence) -> dict[str, Any]:
    from estimator.bench.peers import opencv_stereo_vo

    start = time.perf_counter()
    stamps, poses, failed = opencv_stereo_vo(sequence)
    wall = time.perf_counter() - start
    evaluation = evaluate_trajectory(
        stamps, poses, sequence.ground_truth, sequence.rig.left.T_BS, 1.0
    )
    metrics = {key: evaluation.metrics.get(key) for key in _REAL_KEYS}
    metrics.update(frames=len(stamps), frames_failed=failed, wall_time_s=wall)
    return metrics


def _run_real(
    args: argparse.Namespace, estimators: list[str], results: dict[str, Any], save
) -> None:
    """Every run of the real clips into ``results``, saved after each run (long bench)."""
    for name in args.real:
        path = REAL[name]
        if not (path / "mav0").is_dir():
            print(f"skipping {name}: no data at {path}")
            continue
        sequence = _open(path)
        runs: dict[str, Any] = results.setdefault(name, {})
        for estimator in estimators:
            for refine in (True, False):
                if ("on" if refine else "off") not in args.refinement:
                    continue
                for imu in (False, True):
                    label = _real_label(estimator, refine, imu)
                    folder = args.out / name / label.replace(" ", "_")
                    runs[label] = _real_run(sequence, estimator, refine, imu, args, folder)
                    print(f"{name} {label}: {_real_cells(runs[label])}", flush=True)
                    save()
        if args.peer:
            runs[f"{PEER} vision"] = _peer_run(sequence)
            print(f"{name} {PEER} vision: {_real_cells(runs[f'{PEER} vision'])}", flush=True)
            save()


def _real_cells(run: dict[str, Any] | None) -> str:
    if run is None:
        return "- | - | - | -"
    ate = run.get("ate_rmse_m")
    rot = run.get("rpe_rot_rmse_deg")
    drift = run.get("final_drift_m")
    return " | ".join(
        [
            "-" if ate is None else f"{1000 * ate:.1f}",
            "-" if rot is None else f"{rot:.4f}",
            "-" if drift is None else f"{1000 * drift:.1f}",
            str(run.get("frames_failed", "-")),
        ]
    )


def _noise_cell(run: dict[str, Any] | None) -> str:
    noise = (run or {}).get("noise") or {}
    median = noise.get("median_squared_mahalanobis")
    if median is None:
        return "-"
    return f"{median:.2f} ({median / CHI2_3_MEDIAN:.2f}x)"


def _real_table(results: dict[str, Any]) -> str:
    lines: list[str] = []
    for name, runs in results.items():
        lines += [
            f"\n{name} (real): ATE mm / RPE rotation deg per frame / final drift mm / frames "
            "failed; median squared Mahalanobis residual of the inliers (chi-square 3 DOF "
            f"median {CHI2_3_MEDIAN}) with the noise model's final estimate",
            "",
            "| estimator | refinement | vision ATE | vision deg/fr | vision drift | vision failed"
            " | fused ATE | fused deg/fr | fused drift | fused failed | vision d^2 median |",
            "|---|---|---|---|---|---|---|---|---|---|---|",
        ]
        estimators = sorted(
            {label.split(" ")[0] for label in runs if not label.startswith(PEER)},
            key=lambda e: (e != DEFAULT_ESTIMATOR, e),
        )
        for estimator in estimators:
            for refine in (True, False):
                vision = runs.get(_real_label(estimator, refine, False))
                fused = runs.get(_real_label(estimator, refine, True))
                lines.append(
                    f"| {estimator} | {'on' if refine else 'off'} | {_real_cells(vision)} | "
                    f"{_real_cells(fused)} | {_noise_cell(vision)} |"
                )
        peer = runs.get(f"{PEER} vision")
        if peer is not None:
            lines.append(f"| {PEER} (peer) | - | {_real_cells(peer)} | - | - | - | - | - |")
        lines.append(_noise_line(runs))
    return "\n".join(lines).strip() + "\n"


def _noise_line(runs: dict[str, Any]) -> str:
    default = runs.get(_real_label(DEFAULT_ESTIMATOR, True, False)) or {}
    noise = default.get("noise") or {}
    if not noise:
        return ""
    ratio = noise["median_squared_mahalanobis"] / CHI2_3_MEDIAN
    return (
        "\nnoise model (pso-robust, vision alone): sigma_u {sigma_u_px:.3f} px, sigma_v "
        "{sigma_v_px:.3f} px, sigma_d {sigma_d_px:.3f} px at {typical_disparity} px of disparity, "
        "growing {growth}; median squared Mahalanobis residual "
        "of the inliers {median_squared_mahalanobis:.3f} (chi-square 3 DOF: {chi2:.3f}, "
        "ratio {ratio:.2f}, within 20 %: {ok})"
    ).format(
        chi2=CHI2_3_MEDIAN,
        ratio=ratio,
        typical_disparity=f"{noise.get('typical_disparity_px', 0.0):.1f}",
        growth=f"{noise.get('disparity_gain_per_px', 0.0):.3f} per px of disparity",
        ok="PASS" if abs(ratio - 1.0) <= 0.2 else "MISS",
        **noise,
    )


# ----------------------------------------------------------------------------- rendered loops


def _row(label: str, metrics: dict[str, Any]) -> str:
    cells = [
        "-" if metrics.get(key) is None else fmt.format(metrics[key]) for key, _, fmt in COLUMNS
    ]
    return f"| {label} | " + " | ".join(cells) + " |"


def _rendered(args: argparse.Namespace, noisy: bool) -> Path:
    """The rendered loop (clean or with sensor effects), rendered once into ``--data`` and
    rendered again when the renderer changed (estimator/rendered/cache.py)."""
    frames, length = (40, 4.0) if args.quick else (args.frames, args.length_m)
    effects = NOISY_EFFECTS if noisy else {}
    suffix = "_noisy" if noisy else ""
    root = args.data / f"rendered{suffix}_{frames}f_{length:g}m_seed{args.seed}"
    options = SynthOptions(frames=frames, length_m=length, seed=args.seed, **effects)
    return rendered_once(root, options)


def _run_rendered(
    args: argparse.Namespace, estimators: list[str], results: dict[str, Any], save
) -> None:
    for name in args.datasets:
        root = _rendered(args, noisy=name == "rendered_noisy")
        sequence = _open(root)
        results[name] = {}
        for estimator in estimators:
            config = build_config(estimator, args.seed, imu=True, backend=True)
            result = run_sequence(sequence, config, progress=False)
            summary = write_outputs(result, args.out / name / estimator)
            # Which rendering the numbers belong to (the same fingerprint reproduces them).
            summary["render_fingerprint"] = (root / FINGERPRINT_FILE).read_text().strip()
            results[name][estimator] = summary
            for section in ("fused", "frontend"):
                print(_row(f"{name} {estimator} {section}", summary[section]), flush=True)
            print(f"{name} {estimator} noise: {_noise_cell(summary)}", flush=True)
            save()


def _rendered_table(results: dict[str, Any]) -> str:
    header = "| estimator / poses | " + " | ".join(title for _, title, _ in COLUMNS) + " |"
    rule = "|" + "---|" * (len(COLUMNS) + 1)
    lines: list[str] = []
    for name in RENDERED:
        if name not in results:
            continue
        runs = results[name]
        first = next(iter(runs.values()))
        lines += [f"\n{name}: {first['frames']} frames", "", header, rule]
        for estimator, summary in runs.items():
            for section in ("fused", "frontend"):
                lines.append(_row(f"{estimator} {section}", summary[section]))
        lines.append(
            "\nframes failed: "
            + ", ".join(f"{e} {r['frames_failed']}" for e, r in runs.items())
            + "; median squared Mahalanobis residual of the inliers (chi-square 3 DOF "
            f"median {CHI2_3_MEDIAN}): "
            + ", ".join(f"{e} {_noise_cell(r)}" for e, r in runs.items())
        )
    fused = results.get("rendered", {}).get(DEFAULT_ESTIMATOR, {}).get("fused")
    if fused is not None:
        ate_ok = fused["ate_pct_of_path"] is not None and fused["ate_pct_of_path"] < TARGET_ATE_PCT
        rot_ok = fused["rpe_rot_rmse_deg"] < TARGET_RPE_ROT_DEG
        lines.append(
            f"\npso-robust on the rendered loop: ATE {fused['ate_pct_of_path']:.2f} % of path "
            f"(target < {TARGET_ATE_PCT} %) {'PASS' if ate_ok else 'MISS'}; RPE rotation "
            f"{fused['rpe_rot_rmse_deg']:.3f} deg/frame (target < {TARGET_RPE_ROT_DEG}) "
            f"{'PASS' if rot_ok else 'MISS'}"
        )
    return "\n".join(lines).strip() + "\n"


# ----------------------------------------------------------------------------- entry point


def run(args: argparse.Namespace) -> int:
    out: Path = args.out
    out.mkdir(parents=True, exist_ok=True)
    try:
        estimators = _estimators(args)
    except ValueError as error:
        print(f"error: {error}")
        return 2
    results_file = out / "odometry.json"
    # Runs of a subset update the stored results instead of discarding the rest.
    stored = json.loads(results_file.read_text()) if results_file.is_file() else {}
    results: dict[str, Any] = {part: stored.get(part, {}) for part in PARTS}

    def save() -> str:
        table = _real_table(results["real"]) + "\n" + _rendered_table(results["rendered"])
        (out / "odometry.md").write_text(table)
        results_file.write_text(json.dumps(results, indent=2) + "\n")
        return table

    if "real" in args.parts:
        _run_real(args, estimators, results["real"], save)
    if "rendered" in args.parts:
        _run_rendered(args, estimators, results["rendered"], save)
    table = save()
    print("\n" + table)
    return 0
