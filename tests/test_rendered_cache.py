"""A cached rendered sequence is reused only when the current renderer would draw the same one."""

from __future__ import annotations

import json
from pathlib import Path

from estimator.rendered.cache import FINGERPRINT_FILE, render_fingerprint, rendered_once
from estimator.rendered.synthetic import SynthOptions

TINY = SynthOptions(frames=3, length_m=0.5, seed=3)


def _images(root: Path) -> dict[str, bytes]:
    return {p.name: p.read_bytes() for p in sorted((root / "mav0/cam0/data").glob("*.png"))}


def test_fingerprint_follows_the_options() -> None:
    assert render_fingerprint(TINY) == render_fingerprint(
        SynthOptions(frames=3, length_m=0.5, seed=3)
    )
    assert render_fingerprint(TINY) != render_fingerprint(
        SynthOptions(frames=3, length_m=0.5, seed=4)
    )
    assert render_fingerprint(TINY) != render_fingerprint(
        SynthOptions(frames=3, length_m=0.5, seed=3, noise=1.0)
    )


def test_a_matching_folder_is_reused(tmp_path: Path) -> None:
    root = rendered_once(tmp_path / "seq", TINY)
    marker = root / FINGERPRINT_FILE
    assert marker.read_text().strip() == render_fingerprint(TINY)
    # A file the renderer never writes survives a reuse (the folder is not rendered again).
    (root / "kept.txt").write_text("reused")
    assert rendered_once(tmp_path / "seq", TINY) == root
    assert (root / "kept.txt").read_text() == "reused"


def test_a_stale_folder_is_rendered_again(tmp_path: Path) -> None:
    fresh = _images(rendered_once(tmp_path / "fresh", TINY))
    # The same name, written by another renderer: images one grey level off, old fingerprint.
    root = rendered_once(tmp_path / "seq", TINY)
    for image in (root / "mav0/cam0/data").glob("*.png"):
        image.write_bytes(b"not the current rendering")
    (root / FINGERPRINT_FILE).write_text("written-by-an-older-renderer\n")
    rendered_once(root, TINY)
    assert _images(root) == fresh
    assert (root / FINGERPRINT_FILE).read_text().strip() == render_fingerprint(TINY)


def test_a_folder_of_other_options_is_replaced(tmp_path: Path) -> None:
    other = SynthOptions(frames=4, length_m=0.5, seed=5)
    rendered_once(tmp_path / "seq", other)
    root = rendered_once(tmp_path / "seq", TINY)
    written = json.loads((root / "synth.json").read_text())["options"]
    assert written["frames"] == TINY.frames and written["seed"] == TINY.seed
    assert len(_images(root)) == TINY.frames
