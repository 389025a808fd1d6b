"""How long a stereo frame's PNGs take to decode: OpenCV's libpng against estimator/formats/png.py.

Reads every PNG of a sequence's left and right folders into memory once, then decodes them in
rounds, OpenCV and the project's decoder interleaved round by round (both see the same load),
CPU time per image (``time.process_time``, one core). Every image is checked to decode to the
same pixels both ways before anything is timed.

    OMP_NUM_THREADS=1 python benchmarks/image_decode.py FOLDER [FOLDER ...] [--limit N] [--rounds R]

FOLDER: a folder of PNGs (e.g. ``mav0/cam0/data`` or KITTI's ``image_0``). Prints a markdown
table (docs/performance.md, "Decoding the frames").
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time
from collections.abc import Callable
from pathlib import Path

import cv2
import numpy as np

from estimator.formats.png import decode_grey8_png


def _opencv(data: bytes) -> np.ndarray | None:
    return cv2.imdecode(np.frombuffer(data, dtype=np.uint8), cv2.IMREAD_UNCHANGED)


def _per_image_ms(decode: Callable[[bytes], object], blobs: list[bytes]) -> float:
    start = time.process_time()
    for blob in blobs:
        decode(blob)
    return (time.process_time() - start) / len(blobs) * 1e3


def _folder_row(folder: Path, limit: int, rounds: int) -> str:
    paths = sorted(folder.glob("*.png"))[:limit]
    if not paths:
        raise ValueError(f"no PNG files in {folder}")
    blobs = [path.read_bytes() for path in paths]
    for path, blob in zip(paths, blobs, strict=True):
        ours = decode_grey8_png(blob)
        if ours is None:
            raise ValueError(f"{path} is not a grey 8-bit PNG (the fast path does not apply)")
        if not np.array_equal(ours, _opencv(blob)):
            raise ValueError(f"{path}: the two decoders disagree")
    timings: dict[str, list[float]] = {"opencv": [], "project": []}
    for _ in range(rounds):
        timings["opencv"].append(_per_image_ms(_opencv, blobs))
        timings["project"].append(_per_image_ms(decode_grey8_png, blobs))
    old, new = (statistics.median(timings[key]) for key in ("opencv", "project"))
    height, width = _opencv(blobs[0]).shape[:2]
    kilobytes = statistics.mean(len(blob) for blob in blobs) / 1024
    return (
        f"| {folder} | {width}x{height} | {len(blobs)} | {kilobytes:.0f} | {old:.2f} | "
        f"{new:.2f} | {old / new:.2f}x |"
    )


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("folders", type=Path, nargs="+")
    parser.add_argument("--limit", type=int, default=100, help="PNGs per folder")
    parser.add_argument("--rounds", type=int, default=5)
    args = parser.parse_args(argv)
    if args.limit < 1 or args.rounds < 1:
        print("error: --limit and --rounds must be at least 1", file=sys.stderr)
        return 2
    print("| folder | size | images | KiB | OpenCV ms | project ms | speed-up |")
    print("|---|---|---:|---:|---:|---:|---:|")
    decode_grey8_png(cv2.imencode(".png", np.zeros((4, 4), np.uint8))[1])  # load the kernel
    for folder in args.folders:
        if not folder.is_dir():
            print(f"error: {folder} is not a folder", file=sys.stderr)
            return 2
        try:
            print(_folder_row(folder, args.limit, args.rounds), flush=True)
        except ValueError as error:
            print(f"error: {error}", file=sys.stderr)
            return 2
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
