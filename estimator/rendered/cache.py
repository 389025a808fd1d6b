"""Rendered sequences cached between benchmark runs, re-rendered when the renderer changes.

A benchmark renders its sequence once into a data folder named by frames, length and seed and
reuses it afterwards. The name alone does not say which renderer wrote the images: a change of
the renderer's code (or of OpenCV / NumPy) can move pixels by one grey level, which moves a
rendered flight's ATE by a few tenths of a millimetre, so a result measured on a stale folder
cannot be reproduced from its commit. The folder therefore records a fingerprint of what
decides its bytes (the options, the rendering package's source, the libraries' versions), and a
folder whose fingerprint differs is rendered again.
"""

from __future__ import annotations

import hashlib
import json
import shutil
from dataclasses import asdict
from pathlib import Path

import cv2
import numpy as np

from estimator.rendered.synthetic import SynthOptions, synthesize

__all__ = ["FINGERPRINT_FILE", "render_fingerprint", "rendered_once"]

FINGERPRINT_FILE = "render_fingerprint.txt"
_PACKAGE = Path(__file__).resolve().parent


def render_fingerprint(options: SynthOptions) -> str:
    """Digest of the options, the source of ``estimator/rendered`` and the image libraries."""
    digest = hashlib.sha256()
    digest.update(json.dumps(asdict(options), sort_keys=True).encode())
    digest.update(f"cv2 {cv2.__version__} numpy {np.__version__}".encode())
    for source in sorted(_PACKAGE.glob("*.py")):
        digest.update(source.name.encode())
        digest.update(source.read_bytes())
    return digest.hexdigest()[:16]


def rendered_once(root: Path, options: SynthOptions) -> Path:
    """``root`` holding the sequence of ``options`` as the current renderer draws it.

    Reuses the folder when its recorded fingerprint matches; otherwise (missing, written by
    another renderer or with other options) removes it and renders it again.
    """
    root = Path(root)
    fingerprint = render_fingerprint(options)
    marker = root / FINGERPRINT_FILE
    if marker.is_file() and marker.read_text().strip() == fingerprint:
        return root
    if root.exists():
        shutil.rmtree(root)
    synthesize(root, options)
    marker.write_text(fingerprint + "\n")
    return root
